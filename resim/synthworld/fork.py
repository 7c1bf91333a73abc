"""Counterfactual forks: one history, three futures (left / straight / right) at the same intersection.

A world model learns to follow a command only where the command is what decides the future. On ordinary
drives the history already shows where the car goes (the road's curve is in view, the yaw rate is in the
last frames), so the loss never needs the text (measured: docs/lab/2026-11-26-synth-world-stage-chain.md). A
*fork* is three episodes of one world that are the same, frame for frame, until the ego reaches a four-way
intersection, where it turns left, goes straight or turns right. A clip whose history ends before the split
pairs one history with three futures, and only the command tells them apart.

What makes the three drives identical up to the split (and what a test checks byte for byte):
* one world for all three: the roads are the three branch routes in a fixed order, so the scenery, the
  ground texture and the traffic are drawn once, from the same generator state, whatever the branch;
* only the ego's route differs (``World.route``, what the driver follows and the labels read);
* the driver plans its speed on the sharpest curvature of the three branches up to the end of the turn
  (``World.speed_curvature``), so every branch slows for the intersection the same way, as a driver does
  before deciding, and the speed in the history does not give the branch away;
* the expert draws nothing at random.
The drives part only where the pure-pursuit look-ahead (~5 m) first reaches the branches, ~1 s before the
turn starts.
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from .world import (DS_M, TURN_RADIUS_M, World, Segment, _place_cars, _scatter_props, road_from_curvature,
                    sample_appearance)

FORK_BRANCHES = ("left", "straight", "right")
# when the ego reaches the junction, as a share of the episode (roughly: it slows down before it), so that
# clips of 0.9 s history + 4 s future find the split in a 16-s episode with room after it
FORK_AT = (0.35, 0.5)


def _prefix(rng: np.random.Generator, length_m: float) -> list[Segment]:
    """Straights and gentle curves (no intersections: the fork is the only one) of at least ``length_m``."""
    segs = [Segment("straight", float(rng.uniform(20, 30)), 0.0)]
    sign = 1 if rng.random() < 0.5 else -1
    while sum(s.length_m for s in segs) < length_m:
        if rng.random() < 0.5:
            segs.append(Segment("straight", float(rng.uniform(10, 25)), 0.0))
        else:
            ang, rad = math.radians(rng.uniform(20, 45)), float(rng.uniform(30, 55))
            segs.append(Segment("curve", rad * ang, sign / rad))
            sign = -sign
    # the last stretch before the intersection is straight, as an approach to a junction is
    segs.append(Segment("straight", 15.0, 0.0))
    return segs


def _after(rng: np.random.Generator, length_m: float) -> list[Segment]:
    segs = [Segment("straight", float(rng.uniform(15, 25)), 0.0)]
    while sum(s.length_m for s in segs) < length_m:
        if rng.random() < 0.5:
            segs.append(Segment("straight", float(rng.uniform(15, 35)), 0.0))
        else:
            ang, rad = math.radians(rng.uniform(30, 75)), float(rng.uniform(25, 55))
            segs.append(Segment("curve", rad * ang, (1 if rng.random() < 0.5 else -1) / rad))
    return segs


def _branch_segments(prefix: list[Segment], after: list[Segment], branch: str) -> list[Segment]:
    if branch == "straight":
        # through the intersection: from the turn's start to as far past the centre (2 turn radii)
        mid = Segment("cross", 2 * TURN_RADIUS_M, 0.0)
    else:
        sign = 1.0 if branch == "left" else -1.0
        mid = Segment("turn", TURN_RADIUS_M * math.pi / 2, sign / TURN_RADIUS_M)
    segs = [replace(sg) for sg in prefix + [mid] + after]
    s = 0.0
    for sg in segs:   # starts on the sampled grid, as build_road anchors them
        sg.s_start = s
        s += max(1, int(round(sg.length_m / DS_M))) * DS_M
    return segs


def _curvature(segs: list[Segment]) -> np.ndarray:
    return np.concatenate([np.full(max(1, int(round(sg.length_m / DS_M))), sg.curvature) for sg in segs])


def build_fork_world(rng: np.random.Generator, duration_s: float, nominal_speed_mps: float, branch: str) -> World:
    """The world of a fork, driven along ``branch`` (one of ``FORK_BRANCHES``).

    Every draw from ``rng`` is the same whatever the branch, so the three calls with one generator state
    build one world (same roads, scenery, traffic, appearance) and leave ``rng`` in the same state (the
    renderer draws its textures next)."""
    if branch not in FORK_BRANCHES:
        raise ValueError(f"fork branch must be one of {FORK_BRANCHES}, got {branch!r}")
    start_s_m = 10.0
    fork_m = start_s_m + nominal_speed_mps * duration_s * float(rng.uniform(*FORK_AT))
    prefix = _prefix(rng, fork_m - 15.0)
    after = _after(rng, 2.0 * nominal_speed_mps * duration_s + 80.0 - fork_m)
    heading0 = float(rng.uniform(-math.pi, math.pi))
    segs = {b: _branch_segments(prefix, after, b) for b in FORK_BRANCHES}
    ks = {b: _curvature(segs[b]) for b in FORK_BRANCHES}
    routes = {b: road_from_curvature(np.zeros(2), heading0, ks[b]) for b in FORK_BRANCHES}
    i_fork = len(_curvature(prefix))                         # first sample of the intersection
    p0, h0 = routes["straight"].xy[i_fork], routes["straight"].heading[i_fork]
    centre = p0 + TURN_RADIUS_M * np.array([math.cos(h0), math.sin(h0)])
    # the world as the scenery and traffic see it: the straight branch is "the" road (cars drive on it), the
    # two turns are its crossings; roads in a fixed order, whatever the branch
    base = World(route=routes["straight"], segments=segs["straight"], crossings=[routes["left"], routes["right"]],
                 intersections=centre[None], props=None, cars=[],  # type: ignore[arg-type]
                 appearance=sample_appearance(rng), start_s_m=start_s_m, nominal_speed_mps=nominal_speed_mps)
    base.roads = [routes["straight"], routes["left"], routes["right"]]
    base.props = _scatter_props(rng, base)
    base.cars = _place_cars(rng, base)
    # speed plan: the sharpest of the three up to the end of the turn, the branch's own after it
    i_end = i_fork + len(_curvature([segs["left"][len(prefix)]]))
    plan = np.abs(routes[branch].curvature).copy()
    both = np.stack([np.abs(routes[b].curvature[:i_end]) for b in FORK_BRANCHES])
    plan[:i_end] = both.max(0)
    return replace(base, route=routes[branch], segments=segs[branch],
                   crossings=[routes[b] for b in FORK_BRANCHES if b != branch], speed_curvature=plan,
                   fork={"branch": branch, "route_s_m": float(i_fork * DS_M),
                         "centre_xy": [float(centre[0]), float(centre[1])]})
