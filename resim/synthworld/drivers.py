"""Drivers of the synthetic world: an expert and hazardous explorers.

The ego is a kinematic unicycle driven by a curvature command ``k`` (1/m,
left +, |k| <= 1/5) and an acceleration; each step integrates exact arcs, so
the heading stored per frame is exactly the heading the poses imply (the chord
between consecutive poses points along their mean yaw).

* ``expert``: pure pursuit on the ego-lane centre with a speed-adaptive
  look-ahead; target speed limited by the curvature ahead (lateral acceleration
  <= 2.2 m/s^2) and by a lead car; it drives the route cleanly (the analogue of
  PDM-Lite in ReSim's CARLA data).
* explorers (ReSim: "rule-based hazardous explorations"), one pattern per
  episode, drawn from ``EXPLORER_PATTERNS``:
  ``drift``   after 1-4 s a constant steering bias either way (leaves the lane, hits scenery);
  ``swerve``  the expert's steering plus a large sinusoid;
  ``random``  piecewise-constant random steering and throttle/brake every 0.5-1.5 s;
  ``stop``    brakes to a standstill and waits 4-8 s (low speed), then goes on;
  ``speeding``twice the expert's speed, ignores curves (runs wide in turns, rear-ends the lead car).
After a collision the ego stops for good (the episode is cut 2 s later).

``Ego`` is the vehicle all of them drive (and an external policy, through closed_loop.py): it moves,
tracks its lane, collides and records the trace, whoever chooses the curvature and acceleration.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .pace import speed_factor
from .world import LANE_OFFSET_M, World

K_MAX = 0.2            # 1/m, about a 5 m turning radius
A_MAX, A_MIN = 2.5, -6.0
A_LAT_MAX = 2.2
EGO_RADIUS_M = 1.0     # collision circles: two of them, at +-1.2 m along the car
EXPLORER_PATTERNS = ("drift", "swerve", "random", "stop", "speeding")


@dataclass
class Trace:
    """What happened, sampled at the simulation rate."""

    t_s: np.ndarray         # (N,)
    poses: np.ndarray       # (N, 3) x, y, yaw (unwrapped, rad)
    speed_mps: np.ndarray   # (N,)
    curvature: np.ndarray   # (N,) commanded curvature, 1/m
    accel_mps2: np.ndarray  # (N,)
    throttle: np.ndarray
    brake: np.ndarray
    route_s_m: np.ndarray   # (N,) progress along the route (projected)
    lane_dev_m: np.ndarray  # (N,) signed lateral distance from the ego-lane centre (left +)
    road_dist_m: np.ndarray  # (N,) distance to the nearest road centreline
    collisions: list[tuple[int, str, str]] = field(default_factory=list)  # (step, category, message)
    driver: str = "expert"
    pattern: str | None = None


def _arc_step(x, y, yaw, v, k, dt):
    ds = v * dt
    dyaw = k * ds
    chord = ds * (np.sinc(dyaw / 2 / np.pi))
    hm = yaw + dyaw / 2
    return x + chord * math.cos(hm), y + chord * math.sin(hm), yaw + dyaw


class _LaneTracker:
    def __init__(self, world: World):
        self.lane = world.lane_path()
        self.route = world.route
        self.i = int(round(world.start_s_m / (world.route.s[1] - world.route.s[0])))

    def locate(self, x, y):
        lo, hi = max(0, self.i - 20), min(len(self.lane), self.i + 60)
        d2 = ((self.lane[lo:hi] - (x, y)) ** 2).sum(1)
        j = lo + int(d2.argmin())
        if d2.min() < 36.0:  # only follow the lane while near it (explorers may leave it)
            self.i = j
        h = self.route.heading[j]
        dev = -(x - self.lane[j, 0]) * math.sin(h) + (y - self.lane[j, 1]) * math.cos(h)
        return j, float(dev)


def _pure_pursuit(world: World, lane, j, x, y, yaw, v):
    ds = world.route.s[1] - world.route.s[0]
    look = max(5.0, 0.9 * v)
    tgt = lane[min(len(lane) - 1, j + int(look / ds))]
    dx, dy = tgt[0] - x, tgt[1] - y
    alpha = math.atan2(dy, dx) - yaw
    Ld = max(1.0, math.hypot(dx, dy))
    return 2 * math.sin(alpha) / Ld


def _curve_speed(world: World, j, v_max):
    ds = world.route.s[1] - world.route.s[0]
    plan = world.route.curvature if world.speed_curvature is None else world.speed_curvature
    k = np.abs(plan[j: j + int(30 / ds)])
    kmax = float(k.max()) if k.size else 0.0
    return min(v_max, math.sqrt(A_LAT_MAX / kmax)) if kmax > 1e-6 else v_max


def _segment(changes: np.ndarray, t: float) -> int:
    """Index of the random explorer's segment at time t; past the last change the segments repeat."""
    return int(np.searchsorted(changes, t % changes[-1]))


class Ego:
    """The ego vehicle in a world, stepped at ``sim_hz``: the kinematic unicycle, its place in the lane, its
    collisions, and the record of what happened (``trace()``). Whoever drives it (the built-in drivers of
    ``simulate``, or an external policy through ``closed_loop``) chooses a curvature and an acceleration at
    every step; the vehicle's physics and the rules that score it are the same for all of them."""

    def __init__(self, world: World, sim_hz: float):
        self.world, self.sim_hz, self.dt = world, sim_hz, 1.0 / sim_hz
        self.tracker = _LaneTracker(world)
        (x, y), yaw = world.route.at(world.start_s_m, LANE_OFFSET_M)
        self.x, self.y, self.yaw = float(x), float(y), float(yaw)
        self.v = 0.8 * _curve_speed(world, self.tracker.i, world.nominal_speed_mps)
        self.step_index = 0
        self.rows: list[tuple] = []
        self.collisions: list[tuple[int, str, str]] = []
        self.hit: set = set()
        self.crashed_at: int | None = None
        self.end: int | None = None     # after a collision, the step the episode is cut at (2 s later)

    @property
    def t_s(self) -> float:
        return self.step_index * self.dt

    @property
    def crashed(self) -> bool:
        return self.crashed_at is not None

    def locate(self) -> tuple[int, float]:
        """(index of the nearest ego-lane sample, signed deviation from the lane centre in m, left +)."""
        return self.tracker.locate(self.x, self.y)

    def step(self, j: int, dev: float, k_cmd: float, acc: float) -> bool:
        """Record the current state with the command (curvature 1/m, left +; acceleration m/s^2), check for
        a collision there, then move one step. After a collision the ego stands still whatever it is told.
        Returns False once the episode is over (2 s after a collision)."""
        if self.crashed:
            k_cmd, acc, self.v = 0.0, 0.0, 0.0
        k_cmd = min(K_MAX, max(-K_MAX, float(k_cmd)))
        step, x, y, yaw, v = self.step_index, self.x, self.y, self.yaw, self.v
        self.rows.append((self.t_s, x, y, yaw, v, k_cmd, acc, self.world.route.s[j], dev))
        if not self.crashed:
            c = _collide(self.world, x, y, yaw, self.t_s, self.hit)
            if c is not None:
                self.collisions.append((step, *c))
                self.crashed_at = step
                self.end = step + int(round(2.0 * self.sim_hz)) + 1
        self.step_index += 1
        if self.end is not None and self.step_index >= self.end:
            return False
        self.x, self.y, self.yaw = _arc_step(x, y, yaw, v, k_cmd, self.dt)
        self.v = max(0.0, v + acc * self.dt)
        return True

    def trace(self, driver: str = "expert", pattern: str | None = None) -> Trace:
        arr = np.array(self.rows)
        poses = arr[:, 1:4]
        acc = arr[:, 6]
        return Trace(t_s=arr[:, 0], poses=poses, speed_mps=arr[:, 4], curvature=arr[:, 5], accel_mps2=acc,
                     throttle=np.clip(acc / A_MAX, 0, 1), brake=np.clip(-acc / -A_MIN, 0, 1),
                     route_s_m=arr[:, 7], lane_dev_m=arr[:, 8],
                     road_dist_m=self.world.distance_to_roads(poses[:, :2]), collisions=list(self.collisions),
                     driver=driver, pattern=pattern)


def expert_command(ego: Ego, j: int) -> tuple[float, float]:
    """The expert's (curvature 1/m, target speed m/s) for the ego at lane sample ``j``: pure pursuit on the
    ego-lane centre; speed limited by the curvature ahead and by a lead car."""
    world = ego.world
    k = _pure_pursuit(world, ego.tracker.lane, j, ego.x, ego.y, ego.yaw, ego.v)
    v_des = _curve_speed(world, j, world.nominal_speed_mps) * speed_factor(world, ego.t_s)   # pace forks: pace.py
    lead_gap = _lead_gap(world, ego.x, ego.y, ego.yaw, ego.t_s)
    if lead_gap is not None:
        v_des = min(v_des, max(0.0, (lead_gap - 8.0) * 0.5))
    return k, v_des


def speed_command(v_des: float, v: float) -> float:
    """Acceleration (m/s^2) towards the target speed, within the vehicle's limits."""
    return min(A_MAX, max(A_MIN, 1.2 * (v_des - v)))


def simulate(world: World, duration_s: float, sim_hz: float, rng: np.random.Generator,
             driver: str = "expert", pattern: str | None = None) -> Trace:
    n = int(round(duration_s * sim_hz))
    ego = Ego(world, sim_hz)
    v_max = world.nominal_speed_mps
    # explorer parameters
    p = {}
    if driver == "explorer":
        p["t0"] = float(rng.uniform(1.0, 4.0))
        p["bias"] = float(rng.choice([-1, 1]) * rng.uniform(0.02, 0.06))
        p["amp"] = float(rng.uniform(0.05, 0.12))
        p["period"] = float(rng.uniform(2.0, 4.0))
        p["stop_for"] = float(rng.uniform(4.0, 8.0))
        # 64 random segments (~64 s); longer episodes cycle through them again (``_segment``), which keeps
        # the random stream, hence every shorter episode, byte-identical to before
        p["changes"] = np.cumsum(rng.uniform(0.5, 1.5, 64))
        p["rand_k"] = rng.uniform(-0.12, 0.12, 64)
        p["rand_a"] = rng.uniform(-3.0, 2.5, 64)
    for _ in range(n):
        t, x, y, yaw, v = ego.t_s, ego.x, ego.y, ego.yaw, ego.v
        j, dev = ego.locate()
        k_cmd, v_des = expert_command(ego, j)
        if driver == "explorer":
            if pattern == "drift" and t >= p["t0"]:
                k_cmd = p["bias"]
            elif pattern == "swerve":
                k_cmd = k_cmd + p["amp"] * math.sin(2 * math.pi * t / p["period"])
            elif pattern == "random":
                k_cmd = float(p["rand_k"][_segment(p["changes"], t)])
            elif pattern == "stop" and p["t0"] <= t < p["t0"] + p["stop_for"]:
                v_des = 0.0
            elif pattern == "speeding":
                v_des = 2.0 * v_max
        if driver == "explorer" and pattern == "random" and not ego.crashed:
            idx = _segment(p["changes"], t)
            acc = float(p["rand_a"][idx]) if v > 0.5 or p["rand_a"][idx] > 0 else 0.0
        else:
            acc = speed_command(v_des, v)
        if not ego.step(j, dev, k_cmd, acc):
            break
    return ego.trace(driver, pattern)


def _lead_gap(world: World, x, y, yaw, t):
    """Distance to the nearest car ahead in a narrow corridor, or None."""
    if not world.cars:
        return None
    poses = world.car_poses(t)
    dx, dy = poses[:, 0] - x, poses[:, 1] - y
    fwd = dx * math.cos(yaw) + dy * math.sin(yaw)
    lat = -dx * math.sin(yaw) + dy * math.cos(yaw)
    ahead = (fwd > 0) & (fwd < 40) & (np.abs(lat) < 1.6)
    return float(fwd[ahead].min()) if ahead.any() else None


def _collide(world: World, x, y, yaw, t, hit: set):
    """(category, message) of the first new collision at this pose, else None."""
    ch, sh = math.cos(yaw), math.sin(yaw)
    centres = np.array([[x + 1.2 * ch, y + 1.2 * sh], [x - 1.2 * ch, y - 1.2 * sh]])
    p = world.props
    if len(p.xy):
        d = np.sqrt(((p.xy[None] - centres[:, None]) ** 2).sum(-1)).min(0)
        close = np.flatnonzero(d < EGO_RADIUS_M + p.radius_m)
        for i in close:
            if ("prop", int(i)) not in hit:
                hit.add(("prop", int(i)))
                kind = ("static.vegetation", "static.vegetation", "static.prop.post")[int(p.kind[i])]
                return "collisions_layout", _msg(kind, i, p.xy[i])
    if world.cars:
        poses = world.car_poses(t)
        for j, (car, pose) in enumerate(zip(world.cars, poses)):
            c2 = np.array([[pose[0] + 1.2 * math.cos(pose[2]), pose[1] + 1.2 * math.sin(pose[2])],
                           [pose[0] - 1.2 * math.cos(pose[2]), pose[1] - 1.2 * math.sin(pose[2])]])
            d = np.sqrt(((centres[:, None] - c2[None]) ** 2).sum(-1)).min()
            if d < 2 * EGO_RADIUS_M and ("car", j) not in hit:
                hit.add(("car", j))
                return "collisions_vehicle", _msg("vehicle.synthetic.box", 1000 + j, pose[:2])
    return None


def _msg(type_id: str, ident, xy) -> str:
    # the leaderboard's message format, in CARLA coordinates (y flipped)
    return (f"Agent collided against object with type={type_id} and id={int(ident)} "
            f"at (x={float(xy[0]):.3f}, y={-float(xy[1]):.3f}, z=0.0)")
