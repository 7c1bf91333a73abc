"""A driving policy from pixels: the last history frames and a navigation command → the next 8 waypoints.

The policy a world model is asked to judge must read what the world model can show it: camera frames (the
true simulator's, or the world model's decoded rollout) and a route command, never the simulator's state.

* Encoder: the IDM's (2+1)-D video encoder (``resim.models.idm.VideoEncoder``) on ``num_frames`` history
  frames, every ``frame_step``-th, ending at the current frame: frame differences show the speed and the yaw
  rate, the last frame the road ahead.
* Head: one branch per command, as in conditional imitation learning (Codevilla et al., "End-to-end Driving
  via Conditional Imitation Learning", ICRA 2018): an MLP on the pooled tokens predicts the 8 waypoints under
  each of the three commands and the command picks one. At a junction the frames alone do not say which way
  the route goes; the command does, and a branched head cannot ignore it (a command fed as one more input
  can be, and is, when the frames predict the future on most training clips).
* Output: ``(B, 8, 3)`` waypoints (x m forward, y m left, yaw rad left +) at 0.5 … 4 s in the ego frame of
  the current frame: the world model's trajectory input (ReSim App. B.2).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from resim.config import ConfigError, from_dict
from resim.models.idm import IDMConfig, VideoEncoder
from resim.shards.schema import COMMANDS


@dataclass
class PolicyConfig:
    num_frames: int = 5                   # history frames the policy sees
    frame_step: int = 2                   # every frame_step-th frame, ending at the current one (10 Hz clips: 0.8 s)
    input_hw: tuple[int, int] = (32, 48)  # frames are resized to this
    channels: tuple[int, ...] = (16, 32, 48)
    token_grid: int = 2
    hidden: int = 128
    num_waypoints: int = 8
    target_scale: tuple[float, float, float] = (10.0, 2.0, 0.2)   # m, m, rad: the loss's units
    frame_hw: tuple[int, int] = (64, 96)  # the clips' frame size it is trained on (the pipeline's geometry);
                                          # a caller with other frames cover-crops them to this first

    def __post_init__(self):
        if self.num_frames < 2 or self.frame_step < 1:
            raise ConfigError("num_frames must be >= 2 (motion is read from frame differences) and frame_step >= 1")
        for name in ("hidden", "num_waypoints", "token_grid"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name} must be >= 1, got {getattr(self, name)}")
        if any(not (math.isfinite(s) and s > 0) for s in self.target_scale):
            raise ConfigError(f"target_scale entries must be finite and > 0, got {self.target_scale}")
        if min(self.input_hw) < 2 ** len(self.channels):
            raise ConfigError(f"input_hw {self.input_hw} too small for {len(self.channels)} stages")

    @property
    def span_frames(self) -> int:
        """History frames the window covers, the current one included."""
        return (self.num_frames - 1) * self.frame_step + 1

    def encoder_cfg(self) -> IDMConfig:
        return IDMConfig(window="history", frame_step=self.frame_step, num_frames=self.num_frames,
                         input_hw=self.input_hw, channels=self.channels, token_grid=self.token_grid)


POLICY_PRESETS: dict[str, dict] = {
    "tiny": {},                                                        # ~0.1 M parameters: CPU minutes
    "small": dict(input_hw=(48, 80), channels=(24, 48, 96), hidden=256),
}


def policy_preset(name: str, **overrides: Any) -> PolicyConfig:
    if name not in POLICY_PRESETS:
        raise ConfigError(f"unknown policy preset {name!r}; known: {sorted(POLICY_PRESETS)}")
    return from_dict(PolicyConfig, {**POLICY_PRESETS[name], **overrides})


def command_index(command: str) -> int:
    """"Turning left" / "Moving forward" / "Turning right" → 0 / 1 / 2 (``resim.shards.schema.COMMANDS``)."""
    if command not in COMMANDS:
        raise ValueError(f"unknown command {command!r}; expected one of {list(COMMANDS)}")
    return COMMANDS.index(command)


class DrivingPolicy(nn.Module):
    """``video (B, num_frames, 3, H, W)`` float [0, 1] and ``command (B,)`` long (index into ``COMMANDS``) →
    waypoints ``(B, num_waypoints, 3)`` float (m, m, rad)."""

    def __init__(self, cfg: PolicyConfig):
        super().__init__()
        self.cfg = cfg
        self.encoder = VideoEncoder(cfg.encoder_cfg())
        d_in = self.encoder.out_dim * cfg.num_frames * cfg.token_grid ** 2
        self.head = nn.Sequential(nn.LayerNorm(d_in), nn.Linear(d_in, cfg.hidden), nn.GELU(),
                                  nn.Linear(cfg.hidden, cfg.hidden), nn.GELU(),
                                  nn.Linear(cfg.hidden, len(COMMANDS) * cfg.num_waypoints * 3))
        self.register_buffer("scale", torch.tensor(cfg.target_scale, dtype=torch.float32), persistent=False)

    def branches_normalised(self, video: torch.Tensor) -> torch.Tensor:
        """Every command's waypoints ``(B, 3, N, 3)`` in units of ``target_scale``."""
        tokens = self.encoder(video)
        return self.head(tokens.flatten(1)).view(video.shape[0], len(COMMANDS), self.cfg.num_waypoints, 3)

    def forward(self, video: torch.Tensor, command: torch.Tensor) -> torch.Tensor:
        out = self.branches_normalised(video)
        return out[torch.arange(out.shape[0], device=out.device), command.long()] * self.scale

    def loss(self, batch: dict) -> tuple[torch.Tensor, dict]:
        """Smooth L1 (in ``target_scale`` units) of the commanded branch against the recorded trajectory."""
        out = self.branches_normalised(batch["video"])
        pred = out[torch.arange(out.shape[0], device=out.device), batch["command"].long()]
        traj = batch["trajectory"].float()
        loss = F.smooth_l1_loss(pred, traj / self.scale)
        with torch.no_grad():
            d = (pred * self.scale - traj)[..., :2].norm(dim=-1)
            logs = {"ade_m": d.mean(), "fde_m": d[:, -1].mean()}
        return loss, logs


def build_policy(model_cfg: dict, *, device: str | torch.device = "cpu") -> DrivingPolicy:
    """Registry builder (``resim.models.registry``): ``{"preset": name, **overrides}`` or a resolved config."""
    cfg = dict(model_cfg)
    preset = cfg.pop("preset", None)
    pcfg = policy_preset(preset, **cfg) if preset else from_dict(PolicyConfig, cfg, prefix="model")
    with torch.device(device):
        return DrivingPolicy(pcfg)

