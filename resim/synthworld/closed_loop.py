"""Closed loop in the true synthetic world: an external policy drives the ego from what the camera sees.

This is the ground truth that a world model's closed loop is checked against (Vid2World's "Real2Sim": a
policy's success inside the world model should rank it as the real world does). The same ``Ego`` as the
built-in drivers (drivers.py) moves and collides; the same rules (score.py) score the episode.

One episode:

1. **History.** The expert drives the first ``handover_s`` seconds, so the policy starts from the kind of
   recorded history a world-model rollout starts from (ReSim conditions on past frames, not on a still
   image), and the camera fills the policy's frame buffer.
2. **Loop.** Every ``1 / replan_hz`` seconds the policy sees an :class:`Observation` (the last frames at
   ``fps_hz`` and the speedometer) and answers a plan: 8 waypoints ``(x m forward, y m left, yaw rad)``
   every 0.5 s in the ego frame, the world model's trajectory input (ReSim App. B.2). Between plans a
   :class:`WaypointFollower` (pure pursuit on the plan, speed from its spacing) turns the latest plan into
   curvature and acceleration at ``sim_hz``.
3. **Score.** The trace is scored like every synthetic episode: the infraction score, and route completion
   against the expert's progress on the same world in the same time.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Protocol

import numpy as np

from .drivers import Ego, Trace, expert_command, simulate, speed_command
from .render import Renderer
from .score import Score, score_trace
from .world import World

NUM_WAYPOINTS = 8
WAYPOINT_DT_S = 0.5


class PolicyError(ValueError):
    """A policy answered something that is not a plan (our caller's bug or a broken policy: fail loudly)."""


@dataclass
class Observation:
    """What a policy sees at one decision.

    frames:    (T, H, W, 3) uint8 RGB, the last ``T`` camera frames at the loop's ``fps_hz``, oldest first
               (fewer at the very start of an episode).
    speed_mps: the ego's speedometer.
    t_s:       time since the episode began.
    command:   the navigation command ("Turning left", "Moving forward", "Turning right": ReSim's text
               conditions) from the caller's itinerary (``drive(command_at=...)``), or None. At a junction
               the frames do not say which way the route goes; a route planner does.
    pose:      privileged: the true (x m, y m, yaw rad) in the world frame. Only the true simulator has it,
               for reference planners (``policies.RoutePlanner``); a policy that is to run inside a world
               model must not read it (the world model has no such thing).
    """

    frames: np.ndarray
    speed_mps: float
    t_s: float
    command: str | None = None
    pose: np.ndarray | None = None


class Policy(Protocol):
    def __call__(self, obs: Observation) -> np.ndarray:
        """(8, 3) float waypoints ``(x m forward, y m left, yaw rad left +)`` at 0.5, 1.0, ..., 4.0 s, in the
        ego frame of the observation."""


def check_plan(plan, who: str) -> np.ndarray:
    """The plan as (8, 3) float64, or a PolicyError naming the policy and the reason."""
    p = np.asarray(plan, dtype=np.float64)
    if p.shape != (NUM_WAYPOINTS, 3):
        raise PolicyError(f"policy {who}: plan has shape {p.shape}, expected ({NUM_WAYPOINTS}, 3)")
    if not np.isfinite(p).all():
        raise PolicyError(f"policy {who}: plan has non-finite values")
    return p


class WaypointFollower:
    """Turns a plan into (curvature, acceleration) at every simulation step.

    The plan is fixed in the world frame when it is made, so the ego keeps following it between decisions.
    Steering: pure pursuit on the plan's polyline (the expert's controller), look-ahead
    ``max(lookahead_min_m, lookahead_s * v)`` along the path from the ego's nearest point; past the plan's end
    the last segment is extended. Speed: the plan's own speed ``lead_s`` ahead of now (the distance between
    the waypoints around that time over their 0.5 s), reached with the vehicle's acceleration limits.
    """

    def __init__(self, lookahead_min_m: float = 4.0, lookahead_s: float = 0.9, lead_s: float = 0.5,
                 step_m: float = 0.25):
        self.lookahead_min_m, self.lookahead_s, self.lead_s, self.step_m = lookahead_min_m, lookahead_s, lead_s, step_m
        self.path: np.ndarray | None = None     # (P, 2) world-frame points every step_m
        self.knots: np.ndarray | None = None    # (9, 2) world-frame origin + waypoints
        self.t0_s = 0.0

    def set_plan(self, plan: np.ndarray, pose: np.ndarray, t_s: float) -> None:
        x0, y0, yaw0 = (float(v) for v in pose[:3])
        c, s = math.cos(yaw0), math.sin(yaw0)
        local = np.vstack([[0.0, 0.0], plan[:, :2]])
        self.knots = np.c_[x0 + local[:, 0] * c - local[:, 1] * s, y0 + local[:, 0] * s + local[:, 1] * c]
        seg = np.hypot(*np.diff(self.knots, axis=0).T)
        arc = np.r_[0.0, np.cumsum(seg)]
        n = max(2, int(arc[-1] / self.step_m) + 1)
        at = np.linspace(0.0, arc[-1], n)
        self.path = np.c_[np.interp(at, arc, self.knots[:, 0]), np.interp(at, arc, self.knots[:, 1])]
        self.t0_s = t_s

    def command(self, x: float, y: float, yaw: float, v: float, t_s: float) -> tuple[float, float]:
        """(curvature 1/m, acceleration m/s^2) for the ego at (x, y, yaw) with speed v at time t_s."""
        if self.path is None:
            raise RuntimeError("WaypointFollower.command before any plan")
        # speed: the plan's segment speed at lead_s from now
        i = int(np.clip((t_s - self.t0_s + self.lead_s) / WAYPOINT_DT_S, 0, NUM_WAYPOINTS - 1))
        v_des = float(np.hypot(*(self.knots[i + 1] - self.knots[i]))) / WAYPOINT_DT_S
        acc = speed_command(v_des, v)
        # steering: pure pursuit on the plan
        d2 = ((self.path - (x, y)) ** 2).sum(1)
        near = int(d2.argmin())
        look = max(self.lookahead_min_m, self.lookahead_s * v)
        ahead = near + int(round(look / self.step_m))
        if ahead < len(self.path):
            tx, ty = self.path[ahead]
        else:
            end, prev = self.knots[-1], self.knots[-2]
            seg = float(np.hypot(*(end - prev)))
            if seg < 1e-6:                      # a plan that stops: hold the wheel straight
                return 0.0, acc
            extra = (ahead - len(self.path) + 1) * self.step_m
            tx, ty = end + (end - prev) / seg * extra
        dx, dy = tx - x, ty - y
        alpha = math.atan2(dy, dx) - yaw
        return 2.0 * math.sin(alpha) / max(1.0, math.hypot(dx, dy)), acc


@dataclass
class LoopConfig:
    """One closed-loop episode in the true world."""

    seconds: float = 16.0         # episode length, history included
    handover_s: float = 1.0       # the expert drives this long first (the recorded history)
    sim_hz: float = 20.0
    fps_hz: float = 10.0          # camera rate (the world model's clip rate)
    replan_hz: float = 2.0        # policy decisions per second
    history_frames: int = 9       # frames in each observation (ReSim: 9 history frames at 10 Hz)

    def __post_init__(self):
        for name in ("seconds", "sim_hz", "fps_hz", "replan_hz"):
            if not getattr(self, name) > 0:
                raise ValueError(f"LoopConfig.{name} must be > 0, got {getattr(self, name)}")
        if not 0 <= self.handover_s < self.seconds:
            raise ValueError(f"LoopConfig.handover_s must be in [0, seconds), got {self.handover_s}")
        for name in ("fps_hz", "replan_hz"):
            k = self.sim_hz / getattr(self, name)
            if abs(k - round(k)) > 1e-9:
                raise ValueError(f"LoopConfig.{name} {getattr(self, name)} must divide sim_hz {self.sim_hz}")
        if self.history_frames < 1:
            raise ValueError("LoopConfig.history_frames must be >= 1")


@dataclass
class LoopResult:
    trace: Trace                     # at sim_hz
    score: Score
    frames: np.ndarray               # (N, H, W, 3) uint8 RGB at fps_hz, what the camera saw
    plans: list[tuple[float, np.ndarray]] = field(default_factory=list)   # (t_s, (8, 3) plan) per decision
    expert_progress_m: float = 0.0


def drive(world: World, policy: Callable[[Observation], np.ndarray], renderer: Renderer,
          cfg: LoopConfig | None = None, name: str | None = None,
          command_at: Callable[[float], str] | None = None, expert: Trace | None = None) -> LoopResult:
    """Drive ``policy`` in ``world`` for ``cfg.seconds`` and score it. Deterministic for a deterministic
    policy (the world moves on its own clock and the renderer draws nothing at random per frame).
    ``command_at(t_s)``: the navigation command the policy is given at each decision (None: none).
    ``expert``: the expert's drive of ``world`` for ``cfg.seconds`` (``simulate``), the route completion's
    reference; simulated here when not given (a caller driving many policies in one world passes it once)."""
    cfg = cfg or LoopConfig()
    who = name or type(policy).__name__
    ego = Ego(world, cfg.sim_hz)
    follower = WaypointFollower()
    cam_every = int(round(cfg.sim_hz / cfg.fps_hz))
    plan_every = int(round(cfg.sim_hz / cfg.replan_hz))
    handover = int(round(cfg.handover_s * cfg.sim_hz))
    frames: list[np.ndarray] = []
    plans: list[tuple[float, np.ndarray]] = []
    for step in range(int(round(cfg.seconds * cfg.sim_hz))):
        pose = np.array([ego.x, ego.y, ego.yaw])
        if step % cam_every == 0:
            frames.append(renderer.render(pose, ego.t_s))
        j, dev = ego.locate()
        if step < handover:
            k, v_des = expert_command(ego, j)
            acc = speed_command(v_des, ego.v)
        else:
            if (step - handover) % plan_every == 0:
                obs = Observation(frames=np.stack(frames[-cfg.history_frames:]), speed_mps=ego.v, t_s=ego.t_s,
                                  command=command_at(ego.t_s) if command_at is not None else None, pose=pose)
                plan = check_plan(policy(obs), who)
                plans.append((ego.t_s, plan))
                follower.set_plan(plan, pose, ego.t_s)
            k, acc = follower.command(ego.x, ego.y, ego.yaw, ego.v, ego.t_s)
        if not ego.step(j, dev, k, acc):
            break
    trace = ego.trace(driver="policy", pattern=who)
    if expert is None:
        expert = simulate(world, cfg.seconds, cfg.sim_hz, np.random.default_rng(0), "expert")
    expert_progress = float(expert.route_s_m[-1] - expert.route_s_m[0])
    return LoopResult(trace=trace, score=score_trace(trace, cfg.sim_hz, expert_progress), frames=np.stack(frames),
                      plans=plans, expert_progress_m=expert_progress)
