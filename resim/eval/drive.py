"""A trained pixel policy at the wheel, and the itinerary that gives it its navigation commands.

* :class:`PixelPolicy` wraps a :class:`~resim.models.policy.model.DrivingPolicy` as a closed-loop policy
  (``resim.synthworld.closed_loop.Policy``): frames in, 8 waypoints out. Frames of any size are brought to the
  clip geometry the policy was trained on (``resim.media.frames.cover_crop``, the pipeline's own), so the true
  simulator's camera frames and a world model's decoded frames reach it alike.
* :func:`itinerary`: the navigation command at time ``t`` of an episode is the trajectory command
  (``resim.labeling.commands.command_from_trajectory``, the rule that labelled the training clips) of the
  expert's drive of the same world from ``t``. The same function of time is given to the policy in the
  true world and inside a world model, where there is no pose to plan a route from.
"""
from __future__ import annotations

from typing import Callable

import numpy as np
import torch

from resim.labeling.commands import command_from_trajectory
from resim.labeling.config import preset as labeler_preset
from resim.labeling.trajectory import trajectory_from_poses
from resim.media.frames import cover_crop
from resim.models.policy.model import DrivingPolicy, command_index
from resim.synthworld.closed_loop import Observation
from resim.synthworld.drivers import simulate
from resim.synthworld.world import World
from resim.train.smallfit import frames_to_tensor
from resim.train.tasks.idm import resize_frames


class PixelPolicy:
    """``obs.frames`` (T, H, W, 3) uint8 and ``obs.command`` → (8, 3) waypoints. With fewer than the policy's
    span of frames (the first decision of a short history) the oldest frame is repeated."""

    def __init__(self, model: DrivingPolicy, device: str = "cpu"):
        self.model, self.device = model.eval().to(device), device
        self.cfg = model.cfg

    def window(self, frames: np.ndarray) -> np.ndarray:
        cfg = self.cfg
        if len(frames) < cfg.span_frames:
            frames = np.concatenate([np.repeat(frames[:1], cfg.span_frames - len(frames), 0), frames])
        picked = frames[len(frames) - cfg.span_frames::cfg.frame_step]
        clip = np.stack([cover_crop(f, cfg.frame_hw) for f in picked])
        return resize_frames(clip, cfg.input_hw)

    @torch.no_grad()
    def __call__(self, obs: Observation) -> np.ndarray:
        if obs.command is None:
            raise ValueError("PixelPolicy needs a navigation command (drive(command_at=itinerary(...)))")
        video = frames_to_tensor(self.window(obs.frames))[None].to(self.device)
        cmd = torch.tensor([command_index(obs.command)], device=self.device)
        return self.model(video, cmd)[0].cpu().numpy().astype(np.float64)


def itinerary(world: World, seconds: float, sim_hz: float = 20.0, labeler: str = "default") -> Callable[[float], str]:
    """``t_s -> command``: the trajectory command of the expert's drive of ``world`` from ``t_s`` (8 waypoints
    over the next 4 s; the expert is simulated 4 s past ``seconds`` so every decision has its future)."""
    expert = simulate(world, seconds + 4.5, sim_hz, np.random.default_rng(0), "expert")
    cfg = labeler_preset(labeler)
    last = len(expert.poses) - 1 - int(round(4.0 * sim_hz))
    cache: dict[int, str] = {}

    def command_at(t_s: float) -> str:
        i = min(last, max(0, int(round(t_s * sim_hz))))
        if i not in cache:
            cache[i] = command_from_trajectory(trajectory_from_poses(expert.poses, i, sim_hz), cfg)[0]
        return cache[i]

    return command_at
