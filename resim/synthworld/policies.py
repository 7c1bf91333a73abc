"""Reference policies for the closed loop, and degradations that grade any policy by design.

* :class:`RoutePlanner` (privileged: reads the true pose) plans what the expert would drive over the next
  4 s. It is the loop's upper reference and the check of the loop itself: followed through
  ``WaypointFollower`` it must drive as cleanly as the expert does.
* :class:`ConstantVelocity` keeps the current speed straight ahead (needs only the speedometer): clean on
  straights, off the road in curves and turns. The usual lower baseline of planning benchmarks.
* :class:`SteeringBias` and :class:`SteeringNoise` wrap any policy and bend its plans by a constant or a
  random curvature: graded quality whose order is known before any run (Vid2World ranks policies of graded
  quality in this way).
"""
from __future__ import annotations

import math

import numpy as np

from .closed_loop import NUM_WAYPOINTS, WAYPOINT_DT_S, Observation
from .drivers import Ego, expert_command, speed_command
from .world import World


def to_ego_frame(poses: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """World poses (N, 3) -> (N, 3) (x forward, y left, yaw) relative to ``origin`` (x, y, yaw)."""
    c, s = math.cos(origin[2]), math.sin(origin[2])
    dx, dy = poses[:, 0] - origin[0], poses[:, 1] - origin[1]
    yaw = np.arctan2(np.sin(poses[:, 2] - origin[2]), np.cos(poses[:, 2] - origin[2]))
    return np.c_[dx * c + dy * s, -dx * s + dy * c, yaw]


def bend(plan: np.ndarray, dk_per_m: float) -> np.ndarray:
    """The plan with ``dk_per_m`` (1/m, left +) added to its curvature all along: each segment's direction
    turns by ``dk * s`` at its mid arc length ``s``, and the points are re-chained; yaw turns by ``dk * s``."""
    pts = np.vstack([[0.0, 0.0], plan[:, :2]])
    d = np.diff(pts, axis=0)
    seg = np.hypot(d[:, 0], d[:, 1])
    arc = np.r_[0.0, np.cumsum(seg)]
    heading = np.arctan2(d[:, 1], d[:, 0]) + dk_per_m * 0.5 * (arc[:-1] + arc[1:])
    xy = np.cumsum(np.c_[seg * np.cos(heading), seg * np.sin(heading)], axis=0)
    return np.c_[xy, plan[:, 2] + dk_per_m * arc[1:]]


class RoutePlanner:
    """Privileged reference: the expert's next 4 s from the ego's true pose and speed (a scratch copy of the
    ego, driven by the expert's controller with the world's traffic at the same clock)."""

    def __init__(self, world: World, sim_hz: float = 20.0):
        self.world, self.sim_hz = world, sim_hz

    def __call__(self, obs: Observation) -> np.ndarray:
        if obs.pose is None:
            raise ValueError("RoutePlanner is privileged: it needs Observation.pose (the true simulator's)")
        ego = Ego(self.world, self.sim_hz)
        ego.x, ego.y, ego.yaw, ego.v = (float(v) for v in (*obs.pose[:3], obs.speed_mps))
        ego.step_index = int(round(obs.t_s * self.sim_hz))
        d2 = ((ego.tracker.lane - obs.pose[:2]) ** 2).sum(1)
        ego.tracker.i = int(d2.argmin())
        every = int(round(WAYPOINT_DT_S * self.sim_hz))
        out = []
        for step in range(1, NUM_WAYPOINTS * every + 1):
            j, dev = ego.locate()
            k, v_des = expert_command(ego, j)
            ego.step(j, dev, k, speed_command(v_des, ego.v))
            if step % every == 0:
                out.append((ego.x, ego.y, ego.yaw))
        return to_ego_frame(np.array(out), np.asarray(obs.pose, float))


class ConstantVelocity:
    """Straight ahead at the current speed."""

    def __call__(self, obs: Observation) -> np.ndarray:
        t = np.arange(1, NUM_WAYPOINTS + 1) * WAYPOINT_DT_S
        return np.c_[obs.speed_mps * t, np.zeros_like(t), np.zeros_like(t)]


class SteeringBias:
    """``policy``'s plans bent by a constant curvature ``dk_per_m`` (1/m, left +)."""

    def __init__(self, policy, dk_per_m: float):
        self.policy, self.dk_per_m = policy, dk_per_m

    def __call__(self, obs: Observation) -> np.ndarray:
        return bend(np.asarray(self.policy(obs), float), self.dk_per_m)


class SteeringNoise:
    """``policy``'s plans bent by a random curvature, N(0, ``std_per_m``) per decision. The draw is a function
    of (seed, decision time), not of a running generator, so an episode replays exactly."""

    def __init__(self, policy, std_per_m: float, seed: int = 0):
        self.policy, self.std_per_m, self.seed = policy, std_per_m, seed

    def __call__(self, obs: Observation) -> np.ndarray:
        rng = np.random.default_rng([self.seed, int(round(obs.t_s * 1000))])
        return bend(np.asarray(self.policy(obs), float), float(rng.normal(0.0, self.std_per_m)))
