"""The synthetic world's infraction score, in the spirit of the CARLA leaderboard.

``score_penalty`` (our *infraction score*) starts at 1.0 and is multiplied per
infraction, with the Leaderboard-2.0 coefficients where one exists:

==========================  ============================================  =====================
category                    when                                          factor
==========================  ============================================  =====================
``collisions_vehicle``      ego collision circle touches a car            x 0.60 each
``collisions_layout``       ego touches a tree, bush or post              x 0.65 each
``outside_route_lanes``     ego centre > 1.0 m outside its lane           x (1 - pct / 100),
                            (i.e. > 2.75 m from the lane centre: other    pct = % of the driven
                            lane, shoulder, grass)                        distance spent there
``min_speed_infractions``   below 0.5 m/s for >= 3 s without a collision  x 0.70 each stop
                            having caused it (the LB2 min-speed factor;
                            Bench2Drive leaves it unused, we do not)
==========================  ============================================  =====================

``score_route`` is route completion in %: the progress along the route divided
by the progress the expert makes on the same world in the same time, capped at
100 (the expert scores 100). ``score_composed = score_route * score_penalty``.
An explorer episode that happens to stay clean is redrawn (see generate.py),
so every hazardous episode scores below 1.0 and every expert episode 1.0.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .drivers import Trace

PENALTY = {
    "collisions_vehicle": 0.60,
    "collisions_layout": 0.65,
    "min_speed_infractions": 0.70,
}
LANE_TOLERANCE_M = 2.75      # |deviation from lane centre| beyond which the ego is outside its lanes
STOP_SPEED_MPS = 0.5
STOP_MIN_S = 3.0


@dataclass
class Score:
    score_route: float
    score_penalty: float
    score_composed: float
    infractions: dict[str, list[str]] = field(default_factory=dict)
    status: str = "Perfect"

    def names(self) -> list[str]:
        return [k for k in sorted(self.infractions) for _ in self.infractions[k]]


def score_trace(tr: Trace, sim_hz: float, expert_progress_m: float | None = None) -> Score:
    inf: dict[str, list[str]] = {k: [] for k in (
        "collisions_layout", "collisions_pedestrian", "collisions_vehicle", "red_light", "stop_infraction",
        "outside_route_lanes", "min_speed_infractions", "yield_emergency_vehicle_infractions",
        "scenario_timeouts", "route_dev", "vehicle_blocked", "route_timeout")}
    penalty = 1.0
    for _, cat, msg in tr.collisions:
        inf[cat].append(msg)
        penalty *= PENALTY[cat]
    # outside route lanes: share of the driven distance
    step = np.r_[np.hypot(*np.diff(tr.poses[:, :2], axis=0).T), 0.0]
    driven = float(step.sum())
    outside = np.abs(tr.lane_dev_m) > LANE_TOLERANCE_M
    out_m = float(step[outside].sum())
    if driven > 0 and out_m > 0:
        pct = 100.0 * out_m / driven
        inf["outside_route_lanes"].append(
            f"Agent went outside its route lanes for about {out_m:.3f} meters ({pct:.2f}% of the completed route)")
        penalty *= 1 - pct / 100
    # long stops not caused by a crash
    crash_step = tr.collisions[0][0] if tr.collisions else len(tr.t_s)
    slow = tr.speed_mps[:crash_step] < STOP_SPEED_MPS
    need = int(round(STOP_MIN_S * sim_hz))
    for a, b in _runs(slow):
        if b - a >= need:
            mean_v = float(tr.speed_mps[:crash_step].mean()) if crash_step else 0.0
            inf["min_speed_infractions"].append(
                f"Stopped for {(b - a) / sim_hz:.1f} s; average speed {mean_v:.2f} m/s")
            penalty *= PENALTY["min_speed_infractions"]
    progress = float(tr.route_s_m[-1] - tr.route_s_m[0])
    if expert_progress_m is None or expert_progress_m <= 0:
        route = 100.0
    else:
        route = float(np.clip(100.0 * progress / expert_progress_m, 0.0, 100.0))
    n_inf = sum(len(v) for v in inf.values())
    status = "Perfect" if n_inf == 0 else ("Failed" if tr.collisions else "Completed")
    return Score(score_route=round(route, 6), score_penalty=round(penalty, 6),
                 score_composed=round(max(route * penalty, 0.0), 6), infractions=inf, status=status)


def _runs(mask: np.ndarray):
    m = np.r_[False, mask, False].astype(np.int8)
    d = np.diff(m)
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)))
