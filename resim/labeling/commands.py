"""Heading change or trajectory -> driving command (pure functions).

Commands are the strings of ``resim.shards.schema.COMMANDS``: "Turning left", "Moving
forward", "Turning right" (ReSim's three text conditions).

* From flow: the heading change over the future window (degrees, left +) against
  ``turn_threshold_deg`` (calibrated on the synthetic world over 4-s windows, docs/labeling.md),
  scaled to the window's length: a steady yaw rate gets the same command at any window.
* From a trajectory (ego frame at the current frame, x forward, y left, yaw left +):
  common practice of planning datasets (ST-P3 / UniAD / VAD on nuScenes, cited by
  ReSim as "following common practice"): the lateral offset of the last waypoint,
  >= +2 m left, <= -2 m right, else forward. Options in ``CommandConfig`` switch
  to the heading change at the horizon, or to "either".
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from resim.labeling.config import CommandConfig, LabelerConfig
from resim.shards.schema import COMMANDS

LEFT, FORWARD, RIGHT = COMMANDS


@dataclass(frozen=True)
class FlowLabel:
    """The flow labeler's verdict on one window."""

    command: str        # one of resim.shards.schema.COMMANDS
    yaw_deg: float      # heading change over the window, degrees, left +
    confidence: float   # 0..1: distance from the threshold x flow quality
    quality: float = 1.0  # 0..1: share of pairs/points the robust fit kept


def _command_cfg(cfg: CommandConfig | LabelerConfig) -> CommandConfig:
    return cfg.command if isinstance(cfg, LabelerConfig) else cfg


def command_from_yaw(yaw_deg: float, cfg: CommandConfig | LabelerConfig,
                     window_s: float | None = None) -> tuple[str, float]:
    """Heading change over a window of ``window_s`` (default: the config's window_s; deg, left +) ->
    (command, confidence in [0.5, 1)).

    The threshold is ``turn_threshold_for(window_s)``: ``turn_threshold_deg`` per 4 s, scaled to the window.
    Confidence is 0.5 exactly at the threshold (a coin flip) and approaches 1 as the heading change moves
    away from it: ``0.5 + 0.5 * tanh(d / confidence_scale_deg)``, the scale scaled to the window likewise.
    """
    c = _command_cfg(cfg)
    y = float(yaw_deg)
    if not math.isfinite(y):
        raise ValueError(f"yaw_deg must be finite, got {yaw_deg!r}")
    k = c.window_factor(window_s)
    thr = c.turn_threshold_deg * k
    if y >= thr:
        cmd = LEFT
    elif y <= -thr:
        cmd = RIGHT
    else:
        cmd = FORWARD
    d = abs(abs(y) - thr)
    return cmd, 0.5 + 0.5 * math.tanh(d / (c.confidence_scale_deg * k))


def command_from_trajectory(traj: np.ndarray, cfg: CommandConfig | LabelerConfig) -> tuple[str, float]:
    """Future trajectory (K, 3) [x fwd m, y left m, yaw rad left +] in the ego frame -> (command, yaw_deg).

    ``yaw_deg`` is the heading change at the last waypoint (degrees, left +).
    """
    c = _command_cfg(cfg)
    t = np.asarray(traj, dtype=np.float64)
    if t.ndim != 2 or t.shape[1] != 3 or len(t) == 0:
        raise ValueError(f"trajectory must have shape (K, 3), got {t.shape}")
    if not np.isfinite(t).all():
        raise ValueError("trajectory has non-finite values")
    lateral = float(t[-1, 1])
    # heading change along the waypoints, unwrapped: the yaw column is wrapped to [-pi, pi], so a tight
    # left U-turn past 180 deg read as a right turn from the last waypoint alone
    yaw_deg = math.degrees(float(np.unwrap(np.r_[0.0, t[:, 2]])[-1]))
    by_offset = LEFT if lateral >= c.lateral_threshold_m else RIGHT if lateral <= -c.lateral_threshold_m else FORWARD
    # the command window's threshold: the waypoints' horizon is at most that window (pipelines checks it), equal by default
    by_heading = command_from_yaw(yaw_deg, c)[0]
    if c.trajectory_rule == "lateral_offset":
        cmd = by_offset
    elif c.trajectory_rule == "heading":
        cmd = by_heading
    else:  # "either": a turn by one rule is a turn; contradicting turns fall back to the heading
        cmd = by_heading if by_heading != FORWARD else by_offset
    return cmd, yaw_deg
