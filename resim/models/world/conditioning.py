"""New conditioning modules: ReSim's trajectory encoder and Vid2World's per-frame action encoder.

Both end in a zero-initialised linear layer and have zero-initialised "null" embeddings (used for a dropped or
absent condition), so a model freshly loaded from CogVideoX computes exactly what the pretrained DiT computes;
training moves them away from zero (ControlNet-style zero init).

* :class:`TrajectoryEncoder` (ReSim App. B.2): 8 waypoints ``(x m, y m, yaw rad)`` → linear → 2 attention blocks
  → mean pool → linear head → one ``(B, D)`` vector that the DiT adds to every video token at its input.
* :class:`ActionEncoder` (Vid2World Sec. 4.2): an action per latent frame → small MLP → ``(B, T, D_t)`` added
  to that frame's noise-level embedding (so it modulates only that frame's tokens through AdaLN).
* :class:`TextPooler`: the prompt's T5 tokens ``(B, L, D_text)`` → attention pooling with learned queries →
  ``(B, D_t)`` added to every frame's noise-level embedding (a direct path for the command, see
  ``TextPoolConfig``). Its null is the pooled null prompt, so text dropout and guidance need nothing new.
* :func:`actions_from_trajectory`: per-latent-frame ego motion read off a trajectory, which turns ReSim's
  trajectory into Vid2World-style step-by-step actions for interactive rollouts.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from resim.models.world.config import ActionConfig, TextPoolConfig, TrajectoryEncoderConfig


class _EncoderBlock(nn.Module):
    """Pre-norm transformer block (self-attention over waypoints + MLP)."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.heads = heads
        self.norm1 = nn.LayerNorm(dim)
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)
        self.norm2 = nn.LayerNorm(dim)
        self.mlp = nn.Sequential(nn.Linear(dim, 4 * dim), nn.GELU(approximate="tanh"), nn.Linear(4 * dim, dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, n, d = x.shape
        q, k, v = self.qkv(self.norm1(x)).view(b, n, 3, self.heads, d // self.heads).permute(2, 0, 3, 1, 4)
        a = F.scaled_dot_product_attention(q, k, v).transpose(1, 2).reshape(b, n, d)
        x = x + self.proj(a)
        return x + self.mlp(self.norm2(x))


class TrajectoryEncoder(nn.Module):
    """``(B, num_waypoints, 3)`` float (ego frame, metres/radians) → ``(B, out_dim)``; None/dropped → null."""

    def __init__(self, cfg: TrajectoryEncoderConfig, out_dim: int):
        super().__init__()
        self.cfg = cfg
        h = cfg.hidden_dim
        self.register_buffer("input_scale", torch.tensor(cfg.input_scale, dtype=torch.float32), persistent=False)
        self.proj_in = nn.Linear(cfg.waypoint_dim, h)
        self.pos = nn.Parameter(torch.randn(cfg.num_waypoints, h) * 0.02)
        self.blocks = nn.ModuleList([_EncoderBlock(h, cfg.num_heads) for _ in range(cfg.num_layers)])
        self.norm = nn.LayerNorm(h)
        self.head = nn.Linear(h, out_dim)
        self.null = nn.Parameter(torch.zeros(out_dim))
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    def forward(self, traj: torch.Tensor | None, keep: torch.Tensor | None = None, batch_size: int | None = None,
                dtype: torch.dtype | None = None) -> torch.Tensor:
        """``keep`` (B,) bool: False rows get the null embedding (condition dropout / CFG)."""
        if traj is None:
            if batch_size is None:
                raise ValueError("TrajectoryEncoder needs batch_size when traj is None")
            return self.null.to(dtype or self.null.dtype).expand(batch_size, -1)
        expect = (self.cfg.num_waypoints, self.cfg.waypoint_dim)
        if traj.dim() != 3 or tuple(traj.shape[1:]) != expect:
            raise ValueError(f"trajectory must be (B, {expect[0]}, {expect[1]}), got {tuple(traj.shape)}")
        x = self.proj_in((traj.float() / self.input_scale).to(self.proj_in.weight.dtype)) + self.pos
        for blk in self.blocks:
            x = blk(x)
        out = self.head(self.norm(x).mean(dim=1))
        if keep is not None:
            out = torch.where(keep.to(out.device)[:, None], out, self.null.to(out.dtype))
        return out.to(dtype) if dtype is not None else out


class ActionEncoder(nn.Module):
    """Per-frame actions → ``(B, T, out_dim)`` added to the frames' noise-level embeddings.

    continuous: ``(B, T, action_dim)`` float → linear → SiLU → linear; discrete: ``(B, T)`` int ids →
    embedding → SiLU → linear. ``keep`` (B, T) bool: False frames get the null embedding (Vid2World's action
    dropout, which trains the unconditional branch of causal action guidance).
    """

    def __init__(self, cfg: ActionConfig, out_dim: int):
        super().__init__()
        self.cfg = cfg
        h = cfg.hidden_dim
        if cfg.kind == "continuous":
            self.register_buffer("input_scale", torch.tensor(cfg.input_scale, dtype=torch.float32), persistent=False)
            self.proj_in = nn.Linear(cfg.action_dim, h)
        elif cfg.kind == "discrete":
            self.proj_in = nn.Embedding(cfg.num_actions, h)
        else:
            raise ValueError("ActionEncoder built with actions.kind='none'")
        self.act = nn.SiLU()
        self.proj_out = nn.Linear(h, out_dim)
        self.null = nn.Parameter(torch.zeros(out_dim))
        nn.init.zeros_(self.proj_out.weight)
        nn.init.zeros_(self.proj_out.bias)

    def forward(self, actions: torch.Tensor, keep: torch.Tensor | None = None) -> torch.Tensor:
        if self.cfg.kind == "continuous":
            if actions.dim() != 3 or actions.shape[-1] != self.cfg.action_dim:
                raise ValueError(f"continuous actions must be (B, T, {self.cfg.action_dim}), got {tuple(actions.shape)}")
            x = self.proj_in((actions.float() / self.input_scale).to(self.proj_in.weight.dtype))
        else:
            if actions.dim() != 2 or actions.dtype.is_floating_point:
                raise ValueError(f"discrete actions must be (B, T) integer ids, got {tuple(actions.shape)} {actions.dtype}")
            if actions.numel() and (actions.min() < 0 or actions.max() >= self.cfg.num_actions):
                raise ValueError(f"discrete action ids must be in [0, {self.cfg.num_actions})")
            x = self.proj_in(actions)
        out = self.proj_out(self.act(x))
        if keep is not None:
            out = torch.where(keep.to(out.device)[..., None], out, self.null.to(out.dtype))
        return out


class TextPooler(nn.Module):
    """``(B, L, text_dim)`` prompt embedding → ``(B, out_dim)``; zero output at initialisation.

    One learned query per head attends over the text tokens (no mask: the model's text input carries none,
    and the placeholder/T5 padding positions are the same for every prompt), then SiLU → zero-initialised
    linear, as the trajectory and action encoders end.
    """

    def __init__(self, cfg: TextPoolConfig, text_dim: int, out_dim: int):
        super().__init__()
        self.cfg = cfg
        h = cfg.hidden_dim
        self.norm = nn.LayerNorm(text_dim)
        self.to_kv = nn.Linear(text_dim, 2 * h)
        self.query = nn.Parameter(torch.randn(cfg.num_heads, h // cfg.num_heads) * 0.02)
        self.proj = nn.Linear(h, h)
        self.act = nn.SiLU()
        self.head = nn.Linear(h, out_dim)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    def forward(self, text: torch.Tensor) -> torch.Tensor:
        b, n, _ = text.shape
        heads = self.cfg.num_heads
        k, v = self.to_kv(self.norm(text)).view(b, n, 2, heads, -1).permute(2, 0, 3, 1, 4)   # (B, H, L, d)
        q = self.query.to(k.dtype)[None, :, None].expand(b, -1, -1, -1)                     # (B, H, 1, d)
        pooled = F.scaled_dot_product_attention(q, k, v).reshape(b, -1)
        return self.head(self.act(self.proj(pooled)))


def _interp(times: torch.Tensor, knots_t: torch.Tensor, knots_v: torch.Tensor) -> torch.Tensor:
    """Piecewise-linear interpolation, clamped at the ends. knots_v (B, K, C), times (M,) → (B, M, C)."""
    idx = torch.searchsorted(knots_t, times.clamp(knots_t[0], knots_t[-1]), right=True).clamp(1, len(knots_t) - 1)
    t0, t1 = knots_t[idx - 1], knots_t[idx]
    w = ((times.clamp(knots_t[0], knots_t[-1]) - t0) / (t1 - t0))[None, :, None]
    return knots_v[:, idx - 1] * (1 - w) + knots_v[:, idx] * w


def actions_from_trajectory(traj: torch.Tensor, num_frames: int, first_future_frame: int,
                            frame_dt_s: float = 0.4, waypoint_dt_s: float = 0.5) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-latent-frame ego motion ``(dx m, dy m, dyaw rad)`` from a future trajectory.

    ``traj`` (B, K, 3): waypoints at ``waypoint_dt_s, 2*waypoint_dt_s, …`` in the ego frame of the current
    frame (x forward, y left, yaw left +; origin pose (0, 0, 0) at time 0). Latent frame
    ``f >= first_future_frame`` spans ``[(f - first_future_frame) * frame_dt_s, … + frame_dt_s]`` after the
    current frame (CogVideoX: 4 pixel frames per latent frame, so 0.4 s at 10 Hz); its action is the motion
    from the pose at the span's start to the pose at its end, in the start pose's frame. Poses in between
    waypoints are linearly interpolated (yaw unwrapped first).

    Returns ``actions`` (B, num_frames, 3) float32 and ``valid`` (B, num_frames) bool: history frames and frames
    reaching past the trajectory's horizon are not valid (actions 0 there; give them the null action).
    """
    if traj.dim() != 3 or traj.shape[-1] != 3:
        raise ValueError(f"trajectory must be (B, K, 3), got {tuple(traj.shape)}")
    b, k, _ = traj.shape
    dev = traj.device
    poses = torch.cat([traj.new_zeros(b, 1, 3), traj], dim=1).double()
    yaw = poses[..., 2]
    dyaw = torch.remainder(yaw[:, 1:] - yaw[:, :-1] + math.pi, 2 * math.pi) - math.pi  # unwrap
    poses[..., 2] = torch.cat([yaw[:, :1], yaw[:, :1] + torch.cumsum(dyaw, dim=1)], dim=1)
    knots_t = torch.arange(k + 1, dtype=torch.float64, device=dev) * waypoint_dt_s
    f = torch.arange(num_frames, device=dev)
    start = (f - first_future_frame).double() * frame_dt_s
    end = start + frame_dt_s
    valid = (start >= -1e-9) & (end <= knots_t[-1] + 1e-9)
    ps, pe = _interp(start, knots_t, poses), _interp(end, knots_t, poses)
    d = pe[..., :2] - ps[..., :2]
    c, s = torch.cos(ps[..., 2]), torch.sin(ps[..., 2])
    dx = c * d[..., 0] + s * d[..., 1]          # rotate world delta into the start pose's frame
    dy = -s * d[..., 0] + c * d[..., 1]
    out = torch.stack([dx, dy, pe[..., 2] - ps[..., 2]], dim=-1).float()
    out = torch.where(valid[None, :, None], out, torch.zeros_like(out))
    return out, valid[None].expand(b, -1).clone()
