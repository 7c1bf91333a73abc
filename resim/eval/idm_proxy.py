"""The IDM proxy: a world model's verdict on a drive, read off its video where there is no simulator state.

The IDM (``resim.models.idm``) reads the ego motion off the frames, 4 s (one IDM window) at a time
(:func:`idm_path`); the path is laid on the world's map from the true starting pose and scored by the true rules
that need no pixels of the world (:func:`path_score`: route completion × share of the path inside the lane,
``resim.synthworld.score.LANE_TOLERANCE_M``). Used by ``resim eval closed-loop`` (``resim.eval.policy_ranking``) on the
true loop's frames and on the world model's.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from resim.media.frames import cover_crop
from resim.synthworld.score import LANE_TOLERANCE_M
from resim.synthworld.world import World
from resim.train.smallfit import frames_to_tensor
from resim.train.tasks.idm import resize_frames


def idm_path(idm: Any, frames: np.ndarray, first: int, fps_hz: float, clip_hw: tuple[int, int]) -> np.ndarray:
    """Ego poses ``(K, 3)`` (x, y, yaw in the ego frame of frame ``first``) every 0.5 s, read by ``idm`` from
    ``frames`` (T, H, W, 3) uint8 from ``first`` on, 4 s (one IDM window) at a time; a last partial window is
    read from a window started earlier by whole waypoints, and only its part past the previous window is kept."""
    cfg = idm.cfg
    span = cfg.future_frames                          # 40 frames = 4 s at 10 Hz
    per_wp = span // cfg.num_waypoints                # frames per waypoint (5)
    clip = np.stack([cover_crop(f, clip_hw) for f in frames])
    clip = resize_frames(clip, cfg.input_hw)
    poses = [np.zeros(3)]
    a = first
    while a + per_wp <= len(clip) - 1:              # at least one more waypoint to read
        # a window that would run past the last frame starts earlier, by whole waypoints
        start = a - per_wp * math.ceil(max(0, a + span - (len(clip) - 1)) / per_wp)
        if start < 0:
            break
        w = clip[start:start + span + 1:cfg.frame_step]
        with torch.no_grad():
            wp = idm(frames_to_tensor(w)[None].to(next(idm.parameters()).device))[0].cpu().numpy().astype(float)
        wp = np.vstack([np.zeros(3), wp])             # poses at 0, 0.5, ..., 4 s after `start`
        skip = (a - start) // per_wp                  # waypoints already covered by the previous window
        base, origin = poses[-1], wp[skip]
        for p in wp[skip + 1:]:
            poses.append(_compose(base, _relative(origin, p)))
        a = start + span
    return np.array(poses)


def _relative(origin: np.ndarray, p: np.ndarray) -> np.ndarray:
    c, s = math.cos(origin[2]), math.sin(origin[2])
    dx, dy = p[0] - origin[0], p[1] - origin[1]
    return np.array([c * dx + s * dy, -s * dx + c * dy, p[2] - origin[2]])


def _compose(base: np.ndarray, rel: np.ndarray) -> np.ndarray:
    c, s = math.cos(base[2]), math.sin(base[2])
    return np.array([base[0] + c * rel[0] - s * rel[1], base[1] + s * rel[0] + c * rel[1], base[2] + rel[2]])


def path_score(world: World, start_pose: np.ndarray, path_ego: np.ndarray, expert_progress_m: float) -> dict:
    """Score a path (ego-frame poses from ``start_pose``) on the world's map: route completion (progress along
    the route over the expert's in the same time, capped at 100) × the share of the path's length within
    ``LANE_TOLERANCE_M`` of the ego-lane centre. No collisions: they are not on a map."""
    world_xy = np.array([_compose(start_pose, p)[:2] for p in path_ego])
    lane = world.lane_path()
    d2 = ((world_xy[:, None] - lane[None]) ** 2).sum(-1)
    j = d2.argmin(1)
    dev = np.sqrt(d2[np.arange(len(j)), j])
    step = np.r_[np.hypot(*np.diff(world_xy, axis=0).T), 0.0]
    driven = float(step.sum())
    inside = 1.0 - (float(step[dev > LANE_TOLERANCE_M].sum()) / driven if driven > 0 else 0.0)
    progress = float(world.route.s[j[-1]] - world.route.s[j[0]])
    route = float(np.clip(100.0 * progress / max(expert_progress_m, 1e-6), 0.0, 100.0))
    return {"score": route * inside, "route": route, "inside": inside, "max_dev_m": float(dev.max())}
