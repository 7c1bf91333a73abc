"""Inverse dynamics model (IDM): a driving video clip in, the ego trajectory (8 waypoints) out.

ReSim measures controllability by running an IDM on generated video and comparing the trajectory it reads
off with the trajectory the world model was conditioned on ("Trajectory Difference"); its IDM reuses XVO's
visual-odometry backbone, which is not available to us. This is our own, small network:

**Video encoder** (a (2+1)D convnet, Tran et al. 2018, "A Closer Look at Spatiotemporal Convolutions"):
  * input: ``num_frames`` RGB frames resized to ``input_hw``, each concatenated with its difference to the
    previous frame (6 channels; the first frame's difference is 0) — the difference is an explicit motion cue
    (as in TSN's RGB-difference stream), cheap and helpful at the low resolutions we work at;
  * a per-frame 2-D stem (3x3 conv, stride 2) then ``len(channels)`` stages, each one (2+1)-D residual block:
    a 3x3 spatial conv (stride 2 except in the first stage) followed by a 3-tap temporal conv, GroupNorm +
    SiLU after each, a 1x1x1 projection on the skip path; time is never subsampled (waypoints are
    fine-grained in time);
  * the last feature map is pooled to ``token_grid`` x ``token_grid`` per frame → ``T * g^2`` tokens with
    learned frame and grid position embeddings.

**Heads** (``head``):
  * ``"odometry"`` (default of the future-window presets; :class:`OdometryHead`): per frame an MLP gives the
    ego motion since the previous window frame; the motions are composed in SE(2) and read out at the
    waypoints' times. Visual odometry's structure: a local, time-shared function, then integration.
  * ``"queries"`` (the history-window planner, ``tiny-queries``): an attention head, below.

**Attention head**: ``num_waypoints`` learned queries (one per waypoint, DETR-style) pass through
``head_layers`` pre-norm blocks of cross-attention to the video tokens, self-attention among the queries and
an MLP; a linear layer maps each query to (x, y, yaw). Outputs are in units of ``target_scale`` (metres,
metres, radians) so the three coordinates weigh alike in the loss.

``window`` chooses which frames of a clip the model sees (clips are ``num_history_frames`` + future, the
trajectory is in the ego frame at the last history frame, x forward, y left, yaw left +):
  * ``"future"`` (the IDM): the last history frame and the following ``future_frames`` frames;
  * ``"history"`` (the VO-style planner baseline, same architecture): the last ``num_frames`` history frames
    (every ``frame_step``), i.e. it must *predict* the future trajectory from the past alone.

``loss(batch) -> (loss, logs)`` takes ``{"video": (B, T, 3, H, W) float [0, 1] already windowed,
"trajectory": (B, N, 3)}`` or a ``resim.train.data.Batch`` loaded with ``data.load_frames`` (uint8 frames of
whole clips; windowed here; samples without a trajectory are masked out).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import torch
import torch.nn.functional as F
from torch import nn

from resim.config import ConfigError, from_dict


@dataclass
class IDMConfig:
    window: Literal["future", "history"] = "future"
    future_frames: int = 40            # frames after the last history frame the trajectory spans (4 s at 10 Hz)
    frame_step: int = 2                # take every frame_step-th frame of the window
    num_frames: int = 21               # frames the model sees: (future_frames / frame_step) + 1 for "future"
    input_hw: tuple[int, int] = (48, 80)
    channels: tuple[int, ...] = (24, 48, 96)
    token_grid: int = 2
    head_dim: int = 96
    head_heads: int = 4
    head_layers: int = 2
    num_waypoints: int = 8
    target_scale: tuple[float, float, float] = (10.0, 2.0, 0.2)   # m, m, rad
    loss: Literal["l1", "smooth_l1", "mse"] = "smooth_l1"
    head: Literal["queries", "odometry"] = "queries"   # see the module docstring

    def __post_init__(self):
        if self.window not in ("future", "history"):
            raise ConfigError(f"window must be 'future' or 'history', got {self.window!r}")
        if self.frame_step < 1 or self.num_frames < 2:
            raise ConfigError("frame_step must be >= 1 and num_frames >= 2")
        if self.window == "future" and (self.num_frames - 1) * self.frame_step != self.future_frames:
            raise ConfigError(f"window 'future': (num_frames - 1) * frame_step = "
                              f"{(self.num_frames - 1) * self.frame_step} must equal future_frames "
                              f"{self.future_frames} (the frames the waypoints span)")
        # checked before the divisibility test below, which would otherwise divide by zero
        for name in ("head_dim", "head_heads", "num_waypoints", "token_grid", "future_frames"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.head_layers < 0:
            raise ConfigError(f"head_layers must be >= 0, got {self.head_layers}")
        if self.head_dim % self.head_heads:
            raise ConfigError(f"head_dim {self.head_dim} must be divisible by head_heads {self.head_heads}")
        if not self.channels or any(c < 1 for c in self.channels):
            raise ConfigError(f"channels must be one or more widths >= 1, got {self.channels}")
        if min(self.input_hw) < 2 ** len(self.channels):
            raise ConfigError(f"input_hw {self.input_hw} too small for {len(self.channels)} stages")
        if any(not (math.isfinite(s) and s > 0) for s in self.target_scale):  # nan passes `s <= 0`
            raise ConfigError(f"target_scale entries must be finite and > 0, got {self.target_scale}")
        if self.head not in ("queries", "odometry"):
            raise ConfigError(f"head must be 'queries' or 'odometry', got {self.head!r}")
        if self.head == "odometry" and self.window != "future":
            raise ConfigError("head 'odometry' integrates the motion it sees: window must be 'future' "
                              "(the history-only planner predicts motion it does not see; use head 'queries')")

    def waypoint_positions(self) -> list[float]:
        """Where waypoint k (1-based) falls in the model's window, in window frames (may be fractional).

        The waypoints span the ``future_frames`` after the anchor evenly (0.5 s steps over 4 s at 10 Hz:
        every 5th frame), i.e. waypoint k sits at window index ``k * future_frames / (N * frame_step)``."""
        return [k * self.future_frames / (self.num_waypoints * self.frame_step)
                for k in range(1, self.num_waypoints + 1)]

    def frame_indices(self, num_history_frames: int, clip_frames: int) -> list[int]:
        """Indices (into a clip of ``clip_frames``) of the frames this model sees."""
        anchor = num_history_frames - 1
        if self.window == "future":
            idx = [anchor + i * self.frame_step for i in range(self.num_frames)]
        else:
            idx = [anchor - (self.num_frames - 1 - i) * self.frame_step for i in range(self.num_frames)]
        if idx[0] < 0 or idx[-1] >= clip_frames:
            raise ValueError(f"window {self.window!r} needs frames {idx[0]}..{idx[-1]} of a {clip_frames}-frame clip "
                             f"with {num_history_frames} history frames")
        return idx


IDM_PRESETS: dict[str, dict] = {
    # CPU tests / the synthetic world at low resolution. The odometry head: held-out ADE 1.31 m vs 2.00 m for the
    # query head on the same synthetic split (docs/lab/2026-11-22-idm-ground-plane-world.md); "tiny-queries" keeps
    # the query head
    "tiny": dict(input_hw=(32, 48), frame_step=2, num_frames=21, channels=(16, 32, 48), head_dim=48, head_heads=4,
                 head_layers=1, head="odometry"),
    "tiny-queries": dict(input_hw=(32, 48), frame_step=2, num_frames=21, channels=(16, 32, 48), head_dim=48,
                         head_heads=4, head_layers=1),
    # default size (about 0.5 M parameters); still trains on a CPU for small sets
    "small": dict(head="odometry"),
    # history-only planner twin of "small" (9 history frames, every one)
    "small-history": dict(window="history", frame_step=1, num_frames=9),
    "tiny-history": dict(window="history", frame_step=1, num_frames=9, input_hw=(32, 48), channels=(16, 32, 48),
                         head_dim=48, head_heads=4, head_layers=1),
}


def idm_preset(name: str, **overrides: Any) -> IDMConfig:
    if name not in IDM_PRESETS:
        raise ConfigError(f"unknown IDM preset {name!r}; known: {sorted(IDM_PRESETS)}")
    return from_dict(IDMConfig, {**IDM_PRESETS[name], **overrides})


def _gn(c: int) -> nn.GroupNorm:
    return nn.GroupNorm(min(8, c), c)


class Block2p1D(nn.Module):
    """(2+1)-D residual block on ``(B, C, T, H, W)``: spatial 3x3 (stride s) then temporal 3-tap conv.

    Both are run as ``Conv2d`` (spatial on ``(B*T, C, H, W)``, temporal on ``(B, C, T, H*W)`` with a 3x1
    kernel): the same operator as a factorised ``Conv3d``, and several times faster on CPUs."""

    def __init__(self, cin: int, cout: int, stride: int):
        super().__init__()
        self.stride = stride
        self.spatial = nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=False)
        self.n1 = _gn(cout)
        self.temporal = nn.Conv2d(cout, cout, (3, 1), padding=(1, 0), bias=False)
        self.n2 = _gn(cout)
        self.skip = nn.Conv2d(cin, cout, 1, stride=stride, bias=False)

    def forward(self, x):
        b, c, t, h, w = x.shape
        x2 = x.transpose(1, 2).reshape(b * t, c, h, w)
        s = self.spatial(x2)
        co, ho, wo = s.shape[1:]
        s = s.view(b, t, co, ho, wo).transpose(1, 2)                          # (B, C', T, H', W')
        s = F.silu(self.n1(s))
        hh = self.n2(self.temporal(s.reshape(b, co, t, ho * wo)).view(b, co, t, ho, wo))
        skip = self.skip(x2).view(b, t, co, ho, wo).transpose(1, 2)
        return F.silu(hh + skip)


class VideoEncoder(nn.Module):
    """``(B, T, 3, H, W)`` float [0, 1] → tokens ``(B, T * g * g, C_last)``."""

    def __init__(self, cfg: IDMConfig):
        super().__init__()
        self.cfg = cfg
        c0 = cfg.channels[0]
        self.stem = nn.Conv2d(6, c0, 3, stride=2, padding=1, bias=False)
        self.stem_norm = _gn(c0)
        stages, cin = [], c0
        for i, c in enumerate(cfg.channels):
            stages.append(Block2p1D(cin, c, 1 if i == 0 else 2))
            cin = c
        self.stages = nn.Sequential(*stages)
        self.pool = nn.AdaptiveAvgPool3d((cfg.num_frames, cfg.token_grid, cfg.token_grid))
        self.pos_t = nn.Parameter(torch.zeros(1, cfg.num_frames, 1, cin))
        self.pos_s = nn.Parameter(torch.zeros(1, 1, cfg.token_grid ** 2, cin))
        nn.init.normal_(self.pos_t, std=0.02)
        nn.init.normal_(self.pos_s, std=0.02)
        self.out_dim = cin

    def forward(self, video: torch.Tensor) -> torch.Tensor:
        b, t = video.shape[:2]
        if t != self.cfg.num_frames:
            raise ValueError(f"the model sees {self.cfg.num_frames} frames, got {t}")
        x = video.float()
        if tuple(x.shape[-2:]) != tuple(self.cfg.input_hw):
            x = F.interpolate(x.flatten(0, 1), size=tuple(self.cfg.input_hw), mode="bilinear",
                              align_corners=False, antialias=True).view(b, t, 3, *self.cfg.input_hw)
        x = 2 * x - 1
        diff = torch.cat([torch.zeros_like(x[:, :1]), x[:, 1:] - x[:, :-1]], dim=1)
        x = self.stem(torch.cat([x, diff], dim=2).flatten(0, 1))  # (B*T, C0, H/2, W/2)
        x = x.view(b, t, *x.shape[1:]).transpose(1, 2)             # (B, C0, T, H/2, W/2)
        x = self.stages(F.silu(self.stem_norm(x)))
        x = self.pool(x)                                           # (B, C, T, g, g)
        x = x.flatten(3).permute(0, 2, 3, 1)                       # (B, T, g*g, C)
        x = x + self.pos_t + self.pos_s
        return x.flatten(1, 2)


class _HeadBlock(nn.Module):
    def __init__(self, d: int, heads: int):
        super().__init__()
        self.nq, self.nkv = nn.LayerNorm(d), nn.LayerNorm(d)
        self.cross = nn.MultiheadAttention(d, heads, batch_first=True)
        self.ns = nn.LayerNorm(d)
        self.self_attn = nn.MultiheadAttention(d, heads, batch_first=True)
        self.nm = nn.LayerNorm(d)
        self.mlp = nn.Sequential(nn.Linear(d, 2 * d), nn.GELU(), nn.Linear(2 * d, d))

    def forward(self, q, kv):
        kv = self.nkv(kv)
        q = q + self.cross(self.nq(q), kv, kv, need_weights=False)[0]
        h = self.ns(q)
        q = q + self.self_attn(h, h, h, need_weights=False)[0]
        return q + self.mlp(self.nm(q))


class OdometryHead(nn.Module):
    """Per-step ego motion, integrated into waypoints (the ``"odometry"`` head; future window only).

    Frame ``t``'s tokens (its frame difference to ``t - 1`` is in the encoder's input) → an MLP → the motion
    from window frame ``t - 1`` to ``t`` as (dx, dy, dyaw) in the ego frame of ``t - 1``, in units of
    ``target_scale / (num_frames - 1)``. The steps are composed in SE(2) (``pose_t = pose_{t-1} ∘ delta_t``,
    the anchor frame at the origin) and the poses are linearly interpolated at the waypoints' window
    positions (:meth:`IDMConfig.waypoint_positions`). Why: ego motion between two frames is a *local*
    quantity, the same function at every step; the query head must learn the whole 4 s trajectory as one
    global regression, and overfit doing so on the synthetic world (train ADE 1.05 m vs held-out 2.00 m,
    docs/lab/2026-11-22-idm-ground-plane-world.md). This is the classical visual-odometry structure (motion per
    frame pair, then integration)."""

    def __init__(self, cfg: IDMConfig, in_dim: int):
        super().__init__()
        d = cfg.head_dim
        self.mlp = nn.Sequential(nn.LayerNorm(in_dim * cfg.token_grid ** 2), nn.Linear(in_dim * cfg.token_grid ** 2, d),
                                 nn.GELU(), nn.Linear(d, d), nn.GELU(), nn.Linear(d, 3))
        self.t, self.g2 = cfg.num_frames, cfg.token_grid ** 2
        self.register_buffer("step_scale", torch.tensor(cfg.target_scale, dtype=torch.float32) / (cfg.num_frames - 1),
                             persistent=False)
        pos = torch.tensor(cfg.waypoint_positions(), dtype=torch.float32)
        lo = pos.floor().long().clamp(max=cfg.num_frames - 2)
        self.register_buffer("lo", lo, persistent=False)
        self.register_buffer("frac", (pos - lo.float()).view(1, -1, 1), persistent=False)

    def steps(self, tokens: torch.Tensor) -> torch.Tensor:
        """tokens ``(B, T * g², C)`` → per-step motions ``(B, T - 1, 3)`` (dx m, dy m, dyaw rad)."""
        b = tokens.shape[0]
        f = tokens.reshape(b, self.t, self.g2 * tokens.shape[-1])[:, 1:]
        return self.mlp(f) * self.step_scale

    @staticmethod
    def integrate(steps: torch.Tensor) -> torch.Tensor:
        """``(B, S, 3)`` per-step motions → poses ``(B, S + 1, 3)`` in the first frame's ego frame."""
        yaw = torch.cumsum(steps[..., 2], dim=1)                                        # heading after step s
        head = torch.cat([torch.zeros_like(yaw[:, :1]), yaw[:, :-1]], dim=1)            # heading before step s
        c, s = torch.cos(head), torch.sin(head)
        dx = c * steps[..., 0] - s * steps[..., 1]
        dy = s * steps[..., 0] + c * steps[..., 1]
        poses = torch.stack([torch.cumsum(dx, 1), torch.cumsum(dy, 1), yaw], dim=-1)
        return torch.cat([torch.zeros_like(poses[:, :1]), poses], dim=1)

    def forward(self, tokens: torch.Tensor) -> torch.Tensor:
        """→ waypoints ``(B, N, 3)`` in metres / radians."""
        poses = self.integrate(self.steps(tokens))
        return poses[:, self.lo] * (1 - self.frac) + poses[:, self.lo + 1] * self.frac


class InverseDynamicsModel(nn.Module):
    """Video window ``(B, num_frames, 3, H, W)`` float [0, 1] → waypoints ``(B, N, 3)`` (x m, y m, yaw rad)."""

    def __init__(self, cfg: IDMConfig):
        super().__init__()
        self.cfg = cfg
        self.encoder = VideoEncoder(cfg)
        d = cfg.head_dim
        self.register_buffer("scale", torch.tensor(cfg.target_scale, dtype=torch.float32), persistent=False)
        if cfg.head == "odometry":
            self.odometry = OdometryHead(cfg, self.encoder.out_dim)
            return
        self.proj = nn.Linear(self.encoder.out_dim, d)
        self.queries = nn.Parameter(torch.randn(1, cfg.num_waypoints, d) * 0.02)
        self.blocks = nn.ModuleList(_HeadBlock(d, cfg.head_heads) for _ in range(cfg.head_layers))
        self.norm = nn.LayerNorm(d)
        self.out = nn.Linear(d, 3)

    def forward_normalised(self, video: torch.Tensor) -> torch.Tensor:
        """Waypoints in units of ``target_scale`` (the loss's units)."""
        if self.cfg.head == "odometry":
            return self.odometry(self.encoder(video)) / self.scale
        kv = self.proj(self.encoder(video))
        q = self.queries.expand(video.shape[0], -1, -1)
        for blk in self.blocks:
            q = blk(q, kv)
        return self.out(self.norm(q))

    def forward(self, video: torch.Tensor) -> torch.Tensor:
        if self.cfg.head == "odometry":
            return self.odometry(self.encoder(video))
        return self.forward_normalised(video) * self.scale

    # ---------------------------------------------------------------------------------------- batches
    def window(self, frames: torch.Tensor, num_history_frames: int) -> torch.Tensor:
        """Whole clips ``(B, T, 3, H, W)`` (uint8 0..255 or float [0, 1]) → the model's window, float [0, 1]."""
        idx = self.cfg.frame_indices(num_history_frames, frames.shape[1])
        w = frames[:, idx]
        return w.float() / 255.0 if not w.is_floating_point() else w.float()

    def _inputs(self, batch: Any) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        if isinstance(batch, dict):
            video, traj = batch["video"], batch["trajectory"]
            mask = batch.get("has_trajectory", torch.ones(video.shape[0], dtype=torch.bool, device=video.device))
            return video, traj.float(), mask.bool()
        if getattr(batch, "frames", None) is None:
            raise ValueError("the IDM needs pixel frames: load the data with data.load_frames=true")
        video = self.window(batch.frames, batch.num_history_frames)
        return video, batch.trajectory.float(), batch.has_trajectory.bool()

    def loss(self, batch: Any) -> tuple[torch.Tensor, dict]:
        video, traj, mask = self._inputs(batch)
        if traj.shape[1] != self.cfg.num_waypoints:
            raise ValueError(f"trajectory has {traj.shape[1]} waypoints, the model predicts {self.cfg.num_waypoints}")
        pred = self.forward_normalised(video)
        target = traj / self.scale
        fn = {"l1": F.l1_loss, "smooth_l1": F.smooth_l1_loss, "mse": F.mse_loss}[self.cfg.loss]
        per = fn(pred, target, reduction="none").mean(dim=(1, 2))            # (B,)
        m = mask.float()
        loss = (per * m).sum() / m.sum().clamp_min(1.0)
        with torch.no_grad():
            d = ((pred * self.scale)[..., :2] - traj[..., :2]).norm(dim=-1)  # (B, N) metres
            denom = m.sum().clamp_min(1.0)
            logs = {"ade_m": (d.mean(1) * m).sum() / denom, "fde_m": (d[:, -1] * m).sum() / denom}
        return loss, logs


def num_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def build_idm(model_cfg: dict, *, device: str | torch.device = "cpu") -> InverseDynamicsModel:
    """Registry builder (``resim.models.registry``: "idm"): ``{"preset": NAME, **IDMConfig overrides}``."""
    d = dict(model_cfg)
    name = d.pop("preset", None)
    cfg = idm_preset(name, **d) if name else from_dict(IDMConfig, d, prefix="model")
    with torch.device(device):
        return InverseDynamicsModel(cfg)


def receptive_note(cfg: IDMConfig) -> str:
    """One line describing the network, for reports."""
    head = ("per-step odometry MLP integrated in SE(2)" if cfg.head == "odometry"
            else f"{cfg.head_layers}-layer waypoint-query attention head")
    return (f"(2+1)D convnet {list(cfg.channels)} on {cfg.num_frames} frames (+ frame differences) at "
            f"{cfg.input_hw[0]}x{cfg.input_hw[1]}, {cfg.token_grid}x{cfg.token_grid} tokens/frame, "
            f"{head}; window={cfg.window}, step={cfg.frame_step}"
            f" ({math.prod(cfg.input_hw)} px/frame)")
