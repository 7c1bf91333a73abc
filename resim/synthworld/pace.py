"""Pace forks: one history, three futures that differ only in speed (slower / same / faster).

A world model learns to follow a condition only where that condition is what decides the future (fork.py
says why for the command). The trajectory ReSim gives the world model carries two things: where the car
goes and how fast. Junction forks make the first decide the future; nothing so far made the second: on an
ordinary drive the history already shows the speed (how fast the scenery flows in the last frames), and the
expert keeps it, so the given trajectory's speed is redundant and a model can learn to ignore it (before pace
forks the rollouts followed the given distance only in part: docs/lab/2026-11-26-synth-world-stage-chain.md,
finding 4).

A *pace fork* is three episodes of one world, driven by the expert along one route, identical frame for
frame until a split time, after which the expert's cruising speed is multiplied by 0.5, 1 or 1.5
(``PACE_FACTORS``: the expert's whole speed plan, curve limits included, is scaled; reached within the
vehicle's acceleration limits, and a lead car still makes it slow down).
A clip whose history ends before the split pairs one history with three recorded futures and three
trajectories that differ only in speed: only the trajectory tells them apart.

What keeps the three drives identical up to the split: the world and the split time are drawn from the same
generator state whatever the branch (``pace_fork`` draws first, then labels the branch), and the expert
draws nothing at random.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from .world import World

PACE_BRANCHES = ("slower", "same", "faster")
PACE_FACTORS = {"slower": 0.5, "same": 1.0, "faster": 1.5}
# the split, as a share of the episode: late enough for a 0.9-s history and early enough for a 4-s future after it
PACE_AT = (0.3, 0.6)


def pace_fork(world: World, rng: np.random.Generator, duration_s: float, branch: str) -> World:
    """``world`` driven at its nominal speed until a split time drawn from ``rng``, then at ``PACE_FACTORS[branch]``
    times it. Draws the same from ``rng`` whatever the branch."""
    if branch not in PACE_BRANCHES:
        raise ValueError(f"pace branch must be one of {PACE_BRANCHES}, got {branch!r}")
    split_t_s = float(duration_s * rng.uniform(*PACE_AT))
    return replace(world, pace={"branch": branch, "factor": PACE_FACTORS[branch], "split_t_s": split_t_s})


def speed_factor(world: World, t_s: float) -> float:
    """What the expert's planned speed (nominal, limited by the curves ahead) is multiplied by at ``t_s``: 1 but
    after a pace fork's split. Scaling the whole plan rather than the cruising speed alone keeps the branches
    apart on curvy roads, where the curve limit would otherwise cap "faster" at "same" (a faster driver
    accepts a higher lateral acceleration: 1.5x the speed is 2.25x the expert's 2.2 m/s^2)."""
    p = world.pace
    if p is None or t_s < p["split_t_s"]:
        return 1.0
    return float(p["factor"])
