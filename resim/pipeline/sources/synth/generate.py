"""``resim synth``: generate a synthetic driving dataset in the three real layouts.

Episode i (of N) gets its own ``numpy`` generator seeded with ``(seed, i)``, so a
seed fixes every byte written. Episodes are split round-robin over the parts
``opendv, navsim, carla``; OpenDV and NAVSIM episodes are expert drives, CARLA
episodes alternate expert and hazardous explorer (``carla_hazard_fraction``).
With ``fork_fraction`` > 0 the last episodes come in counterfactual triples (fork.py): one world and one
expert drive, identical until a four-way junction where they turn left, go straight and turn right; a
triple's three episodes are written to the same part, and ``ground_truth.json`` names each one's
``fork`` (group, branch, where it splits).
With ``pace_fork_fraction`` > 0, after those, triples of *pace forks* (resim/synthworld/pace.py): one world and one
expert drive, identical until a split time after which the expert cruises at 0.5, 1 or 1.5 times its speed;
always in the CARLA layout (the one with trajectories at 10 Hz: speed is told only by the trajectory), named in
``ground_truth.json`` as ``pace`` (group, branch, factor, split time).
Each part is written in its real layout (see writers.py), and
``ground_truth.json`` holds, per episode, the exact simulation-rate poses,
heading and speed, the outcome, and how each reader's frame k maps to a
simulation step (``reader_stride``: step = k * stride).
"""
from __future__ import annotations

import json
import math
import multiprocessing as mp
import shutil
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from resim.config import ConfigError, from_dict, to_dict

from resim.synthworld.drivers import EXPLORER_PATTERNS, Trace, simulate
from resim.synthworld.fork import FORK_BRANCHES, build_fork_world
from resim.synthworld.pace import PACE_BRANCHES, pace_fork
from .ground_truth import command_share
from resim.synthworld.render import Camera, Renderer
from resim.synthworld.score import Score, score_trace
from resim.synthworld.world import LANE_OFFSET_M, World, build_road
from . import writers

PARTS = ("opendv", "navsim", "carla")
READER_FPS_HZ = {"opendv": 10.0, "navsim": 2.0, "carla": 10.0}
TURN_LOOKAHEAD_M = 20.0


@dataclass
class SynthConfig:
    height_px: int = 128
    width_px: int = 224
    hfov_deg: float = 80.0
    episode_s: float = 16.0
    sim_hz: float = 20.0              # simulation / ground-truth rate; multiple of 10
    opendv_fps_hz: float = 20.0       # rate of the written OpenDV videos (the reader resamples to 10 Hz)
    nominal_speed_mps: tuple[float, float] = (7.0, 10.0)
    carla_hazard_fraction: float = 0.5
    jpeg_quality: int = 90
    navsim_split: str = "synth"
    fork_fraction: float = 0.0        # share of the episodes made as counterfactual triples (whole triples)
    pace_fork_fraction: float = 0.0   # share made as pace-fork triples (pace.py; whole triples, CARLA layout)

    def __post_init__(self):
        if self.height_px < 16 or self.width_px < 16:
            raise ConfigError("height_px and width_px must be >= 16")
        if self.sim_hz <= 0 or abs(self.sim_hz / 10 - round(self.sim_hz / 10)) > 1e-9:
            raise ConfigError(f"sim_hz must be a multiple of 10, got {self.sim_hz}")
        if self.opendv_fps_hz <= 0 or abs(self.sim_hz / self.opendv_fps_hz - round(self.sim_hz / self.opendv_fps_hz)) > 1e-9:
            raise ConfigError("opendv_fps_hz must divide sim_hz")
        if self.opendv_fps_hz < 10:
            raise ConfigError("opendv_fps_hz must be >= 10 (the reader resamples to 10 Hz)")
        if not 0 <= self.carla_hazard_fraction <= 1:
            raise ConfigError("carla_hazard_fraction must be in [0, 1]")
        if not 0 <= self.fork_fraction <= 1:
            raise ConfigError(f"fork_fraction must be in [0, 1], got {self.fork_fraction}")
        if not 0 <= self.pace_fork_fraction <= 1 or self.fork_fraction + self.pace_fork_fraction > 1:
            raise ConfigError(f"pace_fork_fraction must be in [0, 1 - fork_fraction], got {self.pace_fork_fraction} "
                              f"(fork_fraction {self.fork_fraction})")
        if self.episode_s < 2:
            raise ConfigError("episode_s must be >= 2")
        if not 0 < self.nominal_speed_mps[0] <= self.nominal_speed_mps[1]:
            raise ConfigError("nominal_speed_mps must be (low, high) with 0 < low <= high")


SYNTH_PRESETS = {
    "demo": {},
    "tiny": {"height_px": 64, "width_px": 112, "episode_s": 8.0},
}


def preset(name: str, **overrides) -> SynthConfig:
    if name not in SYNTH_PRESETS:
        raise ConfigError(f"unknown synth preset {name!r}; known: {sorted(SYNTH_PRESETS)}")
    return from_dict(SynthConfig, {**SYNTH_PRESETS[name], **overrides})


@dataclass
class EpisodePlan:
    index: int
    part: str
    driver: str
    pattern: str | None
    name: str
    fork_group: int | None = None     # counterfactual triple this episode belongs to (fork.py)
    fork_branch: str | None = None    # left / straight / right
    pace_group: int | None = None     # pace-fork triple (pace.py)
    pace_branch: str | None = None    # slower / same / faster


def plan_episodes(n: int, cfg: SynthConfig) -> list[EpisodePlan]:
    """Episode i's part and driver. Ordinary episodes first (their plans do not depend on ``fork_fraction``),
    then the fork triples, each triple in one part (parts in turn), expert-driven, then the pace-fork triples
    (CARLA layout, expert-driven)."""
    n_forks = int(n * cfg.fork_fraction) // 3
    n_pace = int(n * cfg.pace_fork_fraction) // 3
    plans, k_carla, k_expl = [], 0, 0
    for i in range(n - 3 * n_forks - 3 * n_pace):
        part = PARTS[i % 3]
        driver, pattern = "expert", None
        if part == "carla":
            # explorer whenever the running hazard share would fall below the target
            if math.floor((k_carla + 1) * cfg.carla_hazard_fraction) > math.floor(k_carla * cfg.carla_hazard_fraction):
                driver, pattern = "explorer", EXPLORER_PATTERNS[k_expl % len(EXPLORER_PATTERNS)]
                k_expl += 1
            k_carla += 1
        plans.append(EpisodePlan(i, part, driver, pattern, f"synth_{i:04d}"))
    for g in range(n_forks):
        for b in FORK_BRANCHES:
            i = len(plans)
            plans.append(EpisodePlan(i, PARTS[g % len(PARTS)], "expert", None, f"synth_{i:04d}", g, b))
    for g in range(n_pace):
        for b in PACE_BRANCHES:
            i = len(plans)
            plans.append(EpisodePlan(i, "carla", "expert", None, f"synth_{i:04d}", pace_group=g, pace_branch=b))
    return plans


def turn_labels(world: World, route_s: np.ndarray) -> list[str]:
    """Per sample: 'left'/'right' while an intersection turn starts within TURN_LOOKAHEAD_M or is under way."""
    out = []
    for s in route_s:
        lab = "straight"
        for sg in world.segments:
            if sg.kind == "turn" and sg.s_start - TURN_LOOKAHEAD_M <= s <= sg.s_start + sg.length_m:
                lab = "left" if sg.curvature > 0 else "right"
                break
        out.append(lab)
    return out


def _simulate_episode(plan: EpisodePlan, seed: int, cfg: SynthConfig):
    if plan.fork_group is not None:
        # a stream of its own per triple (the entropy [seed, group, 3] is no ordinary episode's [seed, index])
        rng = np.random.default_rng([seed, plan.fork_group, len(FORK_BRANCHES)])
        world = build_fork_world(rng, cfg.episode_s, float(rng.uniform(*cfg.nominal_speed_mps)), plan.fork_branch)
        trace = simulate(world, cfg.episode_s, cfg.sim_hz, rng, "expert")
        return rng, world, trace, None, score_trace(trace, cfg.sim_hz, None)
    if plan.pace_group is not None:
        # a stream of its own per triple ([seed, group, 3, 1]: no junction fork's, no ordinary episode's)
        rng = np.random.default_rng([seed, plan.pace_group, len(PACE_BRANCHES), 1])
        world = build_road(rng, cfg.episode_s, float(rng.uniform(*cfg.nominal_speed_mps)),
                           first_turn_sign=1 if plan.pace_group % 2 == 0 else -1)
        world = pace_fork(world, rng, cfg.episode_s, plan.pace_branch)
        trace = simulate(world, cfg.episode_s, cfg.sim_hz, rng, "expert")
        return rng, world, trace, None, score_trace(trace, cfg.sim_hz, None)
    rng = np.random.default_rng([seed, plan.index])
    v_nom = float(rng.uniform(*cfg.nominal_speed_mps))
    world = build_road(rng, cfg.episode_s, v_nom, first_turn_sign=1 if plan.index % 2 == 0 else -1)
    expert = simulate(world, cfg.episode_s, cfg.sim_hz, rng, "expert")
    expert_progress = float(expert.route_s_m[-1] - expert.route_s_m[0])
    trace, pattern = expert, None
    if plan.driver == "explorer":
        # an explorer that happened to drive cleanly is redrawn (patterns in turn), so hazard => penalty < 1
        order = [plan.pattern] + [p for p in EXPLORER_PATTERNS if p != plan.pattern]
        for pattern in order:
            trace = simulate(world, cfg.episode_s, cfg.sim_hz, rng, "explorer", pattern)
            if score_trace(trace, cfg.sim_hz, expert_progress).score_penalty < 1.0:
                break
    score = score_trace(trace, cfg.sim_hz, None if plan.driver == "expert" else expert_progress)
    return rng, world, trace, pattern, score


def generate(out: str | Path, episodes: int, seed: int, cfg: SynthConfig | None = None,
             overwrite: bool = False, progress: bool = True, workers: int = 1) -> dict:
    """Write the dataset to ``out`` (atomically: built beside it, then renamed). Returns the summary."""
    cfg = cfg or SynthConfig()
    out = Path(out)
    if episodes < 1:
        raise ConfigError("episodes must be >= 1")
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise FileExistsError(f"{out} exists and is not empty (use --overwrite)")
    tmp = out.with_name(out.name + ".partial")
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    K = Camera(cfg.height_px, cfg.width_px, cfg.hfov_deg).intrinsic()
    plans = plan_episodes(episodes, cfg)
    workers = max(1, min(workers, len(plans)))
    jobs = [(plan, seed, cfg, tmp) for plan in plans]
    if workers == 1:
        results = map(_make_episode, jobs)
    else:
        pool = ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"))
        results = pool.map(_make_episode, jobs)   # ordered: output does not depend on scheduling
    if progress:
        results = tqdm(results, total=len(plans), desc="synth episodes", unit="ep")
    gt_eps, csv_rows, records = [], [], []
    try:
        for gt_entry, csv_row, record in results:
            gt_eps.append(gt_entry)
            if csv_row:
                csv_rows.append(csv_row)
            if record:
                records.append(record)
    finally:
        if workers > 1:
            pool.shutdown()
    if csv_rows:
        writers.write_opendv_csv(tmp / "opendv" / "videos.csv", csv_rows)
    if records:
        (tmp / "carla").mkdir(exist_ok=True)
        (tmp / "carla" / "simulation_results.json").write_text(
            json.dumps(writers.results_json(records), indent=4), encoding="utf-8")

    share = command_share(gt_eps)
    gt = {"format": "resim-synth-ground-truth", "version": 1, "seed": seed, "episodes_requested": episodes,
          "config": to_dict(cfg), "camera": {"intrinsic": K.tolist(), "height_m": 1.5, "forward_m": 1.0,
                                             "hfov_deg": cfg.hfov_deg},
          "command_share": share, "episodes": gt_eps}
    (tmp / "ground_truth.json").write_text(json.dumps(gt), encoding="utf-8")
    (tmp / "synth_config.json").write_text(json.dumps({"seed": seed, "episodes": episodes, **to_dict(cfg)},
                                                      indent=2, sort_keys=True), encoding="utf-8")
    if out.exists():
        shutil.rmtree(out)
    tmp.rename(out)
    summary = {"out": str(out), "episodes": episodes, "parts": {p: sum(e["layout"]["reader"] == p for e in gt_eps)
                                                                 for p in PARTS},
               "hazardous": sum(e["driver"] == "explorer" for e in gt_eps),
               "fork_triples": len({e["fork"]["group"] for e in gt_eps if e["fork"]}),
               "pace_triples": len({e["pace"]["group"] for e in gt_eps if e.get("pace")}), "command_share": share}
    return summary


def render_episode(index: int, seed: int, cfg: SynthConfig, fps_hz: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """One expert drive of the world, in memory: what ``resim synth`` writes to files for episode ``index``
    (same world, same driver), without the layouts, for code that needs frames with exact poses and no
    pipeline run (tests of the IDM and of the evaluations).

    Returns frames (N, H, W, 3) uint8 RGB and poses (N, 3) float64 [x m, y m, yaw rad unwrapped, left +] in the
    world frame, both at ``fps_hz`` (which must divide ``cfg.sim_hz``)."""
    return render_planned(EpisodePlan(index, "carla", "expert", None, f"synth_{index:04d}"), seed, cfg, fps_hz)


def render_planned(plan: EpisodePlan, seed: int, cfg: SynthConfig,
                   fps_hz: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """:func:`render_episode` for any planned episode (``plan_episodes``: a fork's branch, a pace fork's), in memory."""
    step = cfg.sim_hz / fps_hz
    if not fps_hz > 0 or abs(step - round(step)) > 1e-9:
        raise ConfigError(f"fps_hz {fps_hz} must divide the simulation rate {cfg.sim_hz}")
    renderer, tr = episode_renderer(plan, seed, cfg)
    steps = list(range(0, len(tr.t_s), int(round(step))))
    frames = np.stack([renderer.render(tr.poses[s], tr.t_s[s]) for s in steps])
    return frames, tr.poses[steps].astype(np.float64)


def episode_renderer(plan: EpisodePlan, seed: int, cfg: SynthConfig) -> tuple[Renderer, Trace]:
    """A planned episode as ``resim synth`` made it: its renderer (any pose, any time) and the driven trace."""
    rng, world, tr, _, _ = _simulate_episode(plan, seed, cfg)
    return Renderer(world, Camera(cfg.height_px, cfg.width_px, cfg.hfov_deg), rng), tr


def _make_episode(job):
    """Simulate, render and write one episode; returns (ground-truth entry, OpenDV csv row, CARLA record)."""
    plan, seed, cfg, tmp = job
    cam = Camera(cfg.height_px, cfg.width_px, cfg.hfov_deg)
    K = cam.intrinsic()
    rng, world, tr, pattern, score = _simulate_episode(plan, seed, cfg)
    renderer = Renderer(world, cam, rng)
    sim_hz = cfg.sim_hz
    fps = cfg.opendv_fps_hz if plan.part == "opendv" else READER_FPS_HZ[plan.part]
    step = int(round(sim_hz / fps))
    steps = list(range(0, len(tr.t_s), step))
    frames = [renderer.render(tr.poses[s], tr.t_s[s]) for s in steps]
    turns = turn_labels(world, tr.route_s_m[steps])
    csv_row = record = None
    if plan.part == "opendv":
        rel = f"synth/{plan.name}.mp4"
        writers.write_opendv_video(tmp / "opendv" / rel, frames, cfg.opendv_fps_hz)
        csv_row = {"video_id": f"synth/{plan.name}", "start_discard_s": 0, "end_discard_s": 0,
                   "notes": f"synthetic, seed {seed}, {world.appearance.name}"}
        layout = {"reader": "opendv", "item_id": rel, "reader_stride": int(round(sim_hz / 10.0))}
    elif plan.part == "navsim":
        log = f"synth-s{seed}-{plan.name}"
        writers.write_navsim_log(tmp / "navsim", cfg.navsim_split, log, tr, steps, frames, turns, K, cfg.jpeg_quality)
        layout = {"reader": "navsim", "item_id": log, "reader_stride": step}
    else:
        scen = "SynthExpert" if plan.driver == "expert" else f"SynthExplorer{pattern.capitalize()}"
        wid = writers.WEATHERS[world.appearance.name][0]
        route_num = 90000 + plan.index
        folder = f"{scen}_Town90_Route{route_num}_Weather{wid}"
        lane = world.lane_path()
        targets = []
        for s in steps:
            j = min(len(lane) - 1, int(np.searchsorted(world.route.s, tr.route_s_m[s] + TURN_LOOKAHEAD_M)))
            targets.append((float(lane[j, 0]), float(lane[j, 1])))
        options = [t if t != "straight" else "lanefollow" for t in turns]
        writers.write_carla_route(tmp / "carla" / folder, tr, steps, frames, options, targets,
                                  world.appearance.name, K, cfg.jpeg_quality)
        length = float(np.hypot(*np.diff(tr.poses[:, :2], axis=0).T).sum())
        record = writers.route_record(route_num, folder, scen, wid, score, length, float(tr.t_s[-1]))
        layout = {"reader": "carla", "item_id": folder, "reader_stride": step}
    return _gt_entry(plan, pattern, tr, score, layout, world, sim_hz), csv_row, record


def _gt_entry(plan: EpisodePlan, pattern, tr: Trace, score: Score, layout: dict, world: World, sim_hz: float) -> dict:
    return {
        "episode": plan.name, "index": plan.index, "part": plan.part, "driver": plan.driver, "pattern": pattern,
        "sim_hz": sim_hz, "num_steps": int(len(tr.t_s)), "layout": layout,
        "appearance": world.appearance.name, "nominal_speed_mps": world.nominal_speed_mps,
        "route_segments": [[sg.kind, round(sg.s_start, 3), round(sg.length_m, 3), sg.curvature] for sg in world.segments],
        "fork": None if plan.fork_group is None else {
            "group": plan.fork_group, **world.fork,
            "reach_t_s": float(tr.t_s[min(len(tr.t_s) - 1, int(np.searchsorted(tr.route_s_m, world.fork["route_s_m"])))])},
        "pace": None if plan.pace_group is None else {"group": plan.pace_group, **world.pace},
        "t_s": tr.t_s.tolist(), "x_m": tr.poses[:, 0].tolist(), "y_m": tr.poses[:, 1].tolist(),
        "yaw_rad": tr.poses[:, 2].tolist(), "speed_mps": tr.speed_mps.tolist(),
        "outcome": {"hazard": plan.driver == "explorer", "infraction_score": score.score_penalty,
                    "infractions": score.names(), "score_route": score.score_route,
                    "score_composed": score.score_composed, "status": score.status},
    }
