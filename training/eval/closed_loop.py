"""`resim eval closed-loop`: does the world model rank driving policies as the true world does?

Vid2World's "Real2Sim" check, on the synthetic world, where the true world can be run:

* **Starting states.** Fork worlds (``synthworld.fork``: a junction the route turns left at, crosses or turns
  right at) of a seed never trained on. The expert drives the first ``history_s`` (ReSim's 9 history frames);
  then the policy drives for ``seconds``, told the itinerary's command (``training.policy.drive.itinerary``).
* **True loop.** ``synthworld.closed_loop.drive``: the score is the episode's composed score (route completion
  × infraction score, ``synthworld.score``).
* **World-model loop.** ``training.sampling.simulate.WorldModelLoop`` from the same history (the true frames
  encoded by the VAE), with a decision every latent frame, as in the true loop. The world model's verdict is
  read from the video it generated, by the **IDM proxy**: the IDM (``training.eval.idm``) reads the ego motion
  off the generated frames, 4 s at a time; the path is laid on the world's map from the true starting pose,
  and scored by the true rules that need no pixels of the world (route completion × share of the path inside
  the lane, ``score.LANE_TOLERANCE_M``). The same proxy on the true loop's own frames says how much of any
  disagreement is the proxy's.
* **Ranking.** Per policy, the mean score over states in each loop; Spearman's rank correlation across
  policies, with a bootstrap over starting states (states resampled with replacement, 1,000 times).
"""
from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch
from PIL import Image

from media.frames import cover_crop
from synthworld.policies import ConstantVelocity, SteeringBias, SteeringNoise
from synthworld.closed_loop import LoopConfig, drive
from synthworld.drivers import Trace, simulate
from synthworld.fork import FORK_BRANCHES, build_fork_world
from synthworld.render import Camera, Renderer
from synthworld.score import LANE_TOLERANCE_M
from synthworld.world import World
from training.eval.commands_report import _label
from training.eval.idm_train import load_idm, resize_frames
from training.policy.drive import PixelPolicy, itinerary
from training.policy.train import load_policy
from training.policy.variants import VARIANTS
from training.reward.checkpoint import load_checkpoint as load_reward
from training.reward.metrics import spearman
from training.reward.score import score_videos
from training.sampling.load import trained_size_hw
from training.sampling.outputs import write_rollout
from training.sampling.simulate import WorldModelLoop
from training.smallfit import frames_to_tensor


@dataclass
class ClosedLoopConfig:
    seed: int = 5000                  # starting-state worlds (use a seed no training data was made with)
    states: int = 6
    seconds: float = 8.0              # driven by the policy, after the history
    history_s: float = 0.8            # driven by the expert first: 9 frames at 10 Hz = 3 latent frames
    sim_hz: float = 20.0
    fps_hz: float = 10.0
    camera_hw: tuple[int, int] = (128, 224)   # the synthetic world's render size (synth preset "demo")
    hfov_deg: float = 80.0
    nominal_speed_mps: tuple[float, float] = (7.0, 10.0)
    decision_s: float = 0.4           # one latent frame at 10 Hz
    bootstrap: int = 1000

    def __post_init__(self):
        if self.states < 2 or not self.decision_s > 0:
            raise ValueError("states must be >= 2 and decision_s > 0")
        if self.seconds < 4.0:
            raise ValueError(f"seconds must be >= 4 (the IDM proxy reads 4-s windows), got {self.seconds}")

    def loop_cfg(self, total_s: float) -> LoopConfig:
        """The true loop of an episode of ``total_s``: the expert for ``history_s``, a decision every ``decision_s``."""
        return LoopConfig(seconds=total_s, handover_s=self.history_s, sim_hz=self.sim_hz, fps_hz=self.fps_hz,
                          replan_hz=1.0 / self.decision_s, history_frames=9)


@dataclass
class StartState:
    name: str
    world: World
    render_seed: tuple[int, ...]

    def renderer(self, cfg: ClosedLoopConfig) -> Renderer:
        return Renderer(self.world, Camera(*cfg.camera_hw, cfg.hfov_deg), np.random.default_rng(list(self.render_seed)))


def starting_states(cfg: ClosedLoopConfig) -> list[StartState]:
    """``cfg.states`` fork worlds, the route's branch cycling left / straight / right."""
    out = []
    for i in range(cfg.states):
        branch = FORK_BRANCHES[i % len(FORK_BRANCHES)]
        rng = np.random.default_rng([cfg.seed, i, 3])
        world = build_fork_world(rng, 16.0, float(rng.uniform(*cfg.nominal_speed_mps)), branch)
        out.append(StartState(f"s{cfg.seed}-{i}-{branch}", world, (cfg.seed, i, 1)))
    return out


# ---- the IDM proxy ------------------------------------------------------------------------------------------

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


# ---- the two loops ----------------------------------------------------------------------------------------

def history_of(state: StartState, cfg: ClosedLoopConfig, vae: Any, clip_hw: tuple[int, int],
               expert: Trace) -> tuple[torch.Tensor, np.ndarray, float]:
    """The expert's first ``history_s`` in the true world, where every policy's true loop starts (the loop's
    handover drives the same poses): (latents ``(1, H0, C, h, w)`` from ``vae``, the frames at the world model's
    clip size ``(1 + 4 (H0 - 1), h, w, 3)`` uint8, the speed at the last one). ``expert``: ``simulate``'s trace."""
    renderer = state.renderer(cfg)
    h_step = int(round(cfg.history_s * cfg.sim_hz))
    steps = range(0, h_step + 1, int(round(cfg.sim_hz / cfg.fps_hz)))
    frames = np.stack([cover_crop(renderer.render(expert.poses[i], expert.t_s[i]), clip_hw) for i in steps])
    latents = torch.from_numpy(np.asarray(vae.encode(frames[None], seeds=[0]), np.float32))
    return latents, frames, float(expert.speed_mps[h_step])


def rank_agreement(true: np.ndarray, model: np.ndarray, names: Sequence[str], bootstrap: int = 1000,
                   seed: int = 0) -> dict:
    """``true``, ``model``: scores ``(policies, states)``. Spearman of the per-policy means, its bootstrap over
    states (resampled with replacement; the 2.5 / 97.5 % quantiles), and the largest rank disagreements."""
    t, m = true.mean(1), model.mean(1)
    rho = spearman(t, m)
    rng = np.random.default_rng(seed)
    boots = []
    for _ in range(bootstrap):
        idx = rng.integers(0, true.shape[1], true.shape[1])
        r = spearman(true[:, idx].mean(1), model[:, idx].mean(1))
        if not math.isnan(r):
            boots.append(r)
    rt = np.argsort(np.argsort(-t))
    rm = np.argsort(np.argsort(-m))
    order = np.argsort(-np.abs(rt - rm))
    return {"spearman": rho,
            "ci95": [float(np.quantile(boots, 0.025)), float(np.quantile(boots, 0.975))] if boots else None,
            "bootstrap_valid": len(boots),
            "per_policy": {n: {"true": float(t[i]), "model": float(m[i]), "true_rank": int(rt[i]) + 1,
                               "model_rank": int(rm[i]) + 1} for i, n in enumerate(names)},
            "largest_disagreements": [names[i] for i in order[:2] if rt[i] != rm[i]]}


READINGS = {   # report key: (label, short label for tables, the score array it ranks by)
    "proxy_vs_true_on_true_frames": ("IDM proxy on the true frames", "proxy, true frames", "true_proxy"),
    "world_model_vs_true": ("world model (IDM proxy on its video)", "proxy, world model", "wm_proxy"),
    "reward_vs_true_on_true_frames": ("Video2Reward x100 on the true frames", "V2R, true frames", "true_reward"),
    "world_model_reward_vs_true": ("world model (Video2Reward x100 on its video)", "V2R, world model", "wm_reward"),
}


def reward_score(reward: Any, frames: np.ndarray, first: int, name: str) -> float:
    """Video2Reward's predicted infraction score × 100 (100 = clean, as the composed score) of the drive from
    frame ``first`` on (``frames`` (T, H, W, 3) uint8): the mean over its sliding windows (``score_videos``). A
    drive that ended early (the true world cuts an episode 2 s after a collision) holds its last frame up to one
    window, as the reward's training clips of such routes do (configs/pipeline/carla-reward.yaml)."""
    clip = frames[first:]
    short = reward.cfg.window_frames - len(clip)
    if short > 0:
        clip = np.concatenate([clip, np.repeat(clip[-1:], short, axis=0)])
    return 100.0 * float(score_videos(reward, [clip], names=[name])[0])


def closed_loop_eval(policies: dict[str, Callable], cfg: ClosedLoopConfig, idm: Any, clip_hw: tuple[int, int], *,
                     loop: WorldModelLoop | None = None, vae: Any = None, reward: Any = None, seed: int = 0,
                     say: Callable[[str], None] = lambda m: None) -> dict:
    """Every policy from every starting state in the true world (and, with ``loop`` and ``vae``, inside the world
    model). Each drive is read by the IDM proxy and, with ``reward`` (a ``Video2Reward``), by Video2Reward.
    Returns per-state rows, per-policy means, and the rank agreement of each reading with the true score
    (``READINGS``); ``_videos``: the first state's frames, ``{("true" | "world model", policy): (T, h, w, 3)
    uint8}`` (the true world's cover-cropped to the clip size)."""
    states = starting_states(cfg)
    names = list(policies)
    shape = (len(names), len(states))
    true_score = np.zeros(shape)
    score = {k: np.full(shape, np.nan) for *_, k in READINGS.values()}
    rows, videos = [], {}
    h_step = int(round(cfg.history_s * cfg.sim_hz))
    first = int(round(cfg.history_s * cfg.fps_hz))            # index of the last history frame
    for si, st in enumerate(states):
        total = cfg.history_s + cfg.seconds + 1.0 / cfg.fps_hz    # + one frame: the IDM's last window ends there
        expert = simulate(st.world, total, cfg.sim_hz, np.random.default_rng(0), "expert")
        expert_m = float(expert.route_s_m[-1] - expert.route_s_m[h_step])
        command_at = itinerary(st.world, total, cfg.sim_hz)
        lcfg = cfg.loop_cfg(total)
        start_pose = expert.poses[h_step]                      # the expert drove the history in every loop
        world_runs = None
        if loop is not None:
            # every policy from this state in one batch (one sampler call and one decode per decision)
            latents, frames, speed = history_of(st, cfg, vae, clip_hw, expert)
            world_runs = loop.run_batch(latents, frames, speed, [policies[n] for n in names], cfg.seconds,
                                        command_at=command_at, t0_s=cfg.history_s, names=names,
                                        seeds=[seed + 1000 * si] * len(names))
        for pi, name in enumerate(names):
            r = drive(st.world, policies[name], st.renderer(cfg), lcfg, name, command_at=command_at, expert=expert)
            true_score[pi, si] = r.score.score_composed
            tp = path_score(st.world, start_pose, idm_path(idm, r.frames, first, cfg.fps_hz, clip_hw), expert_m)
            score["true_proxy"][pi, si] = tp["score"]
            true_clip = np.stack([cover_crop(f, clip_hw) for f in r.frames])
            if si == 0:
                videos[("true", name)] = true_clip
            row = {"state": st.name, "policy": name, "true": {"score": r.score.score_composed,
                                                              "route": r.score.score_route,
                                                              "penalty": r.score.score_penalty,
                                                              "infractions": r.score.names()},
                   "true_frames_idm_proxy": tp}
            if reward is not None:
                score["true_reward"][pi, si] = row["true_frames_reward"] = reward_score(reward, true_clip, first, name)
            if world_runs is not None:
                w = world_runs[pi]
                wp = path_score(st.world, start_pose, idm_path(idm, w.frames, first, cfg.fps_hz, clip_hw), expert_m)
                score["wm_proxy"][pi, si] = wp["score"]
                row["world_model_idm_proxy"] = {**wp, "seconds": w.seconds}
                if reward is not None:
                    score["wm_reward"][pi, si] = row["world_model_reward"] = reward_score(reward, w.frames, first,
                                                                                        f"world model: {name}")
                if si == 0:
                    videos[("world model", name)] = w.frames
            rows.append(row)
            say(f"{st.name} {name}: true {true_score[pi, si]:.1f}  proxy on true frames {tp['score']:.1f}"
                + (f"  world model {score['wm_proxy'][pi, si]:.1f} ({row['world_model_idm_proxy']['seconds']:.0f} s)"
                   if loop is not None else "")
                + (f"  Video2Reward true {score['true_reward'][pi, si]:.1f}" if reward is not None else "")
                + (f" / world model {score['wm_reward'][pi, si]:.1f}" if reward is not None and loop else ""))
    rep = {"states": [s.name for s in states], "policies": names, "rows": rows, "readings": {}}
    for key, (label, _, arr) in READINGS.items():
        if not np.isnan(score[arr]).all():
            rep[key] = rank_agreement(true_score, score[arr], names, cfg.bootstrap)
            rep["readings"][key] = label
    rep["_videos"] = videos
    return rep


def format_closed_loop(rep: dict) -> str:
    readings = [(key, label) for key, (label, *_) in READINGS.items() if key in rep]
    names = rep["policies"]
    head = f"{'policy':34s} {'true score':>10s}" + "".join(f" {READINGS[key][1]:>22s}" for key, _ in readings)
    lines = [f"closed loop: {len(names)} policies x {len(rep['states'])} starting states "
             "(mean composed score, 100 = the expert; rank in brackets)", head]
    for n in names:
        t = rep[readings[0][0]]["per_policy"][n]
        row = f"{n:34s} {t['true']:6.1f} [{t['true_rank']}]"
        for key, _ in readings:
            m = rep[key]["per_policy"][n]
            row += f" {m['model']:18.1f} [{m['model_rank']}]"
        lines.append(row)
    for key, label in readings:
        a = rep[key]
        ci = f"[{a['ci95'][0]:.2f}, {a['ci95'][1]:.2f}]" if a["ci95"] else "n/a"
        lines.append(f"Spearman, {label} vs true: {a['spearman']:.2f} (95% bootstrap over states {ci})"
                     + (f"; largest disagreements: {', '.join(a['largest_disagreements'])}"
                        if a["largest_disagreements"] else ""))
    return "\n".join(lines)


def plot_closed_loop(rep: dict, path):
    # matplotlib is slow to import and only the plot needs it
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [k for k in READINGS if k in rep]
    fig, axes = plt.subplots(1, len(keys), figsize=(5.0 * len(keys), 4.4), squeeze=False)
    for ax, key in zip(axes[0], keys):
        a = rep[key]
        for n, v in a["per_policy"].items():   # one colour per policy, the same in every panel
            ax.scatter(v["true"], v["model"], s=40, label=n)
        ax.plot([0, 100], [0, 100], color="0.7", lw=0.8)
        ax.set_xlabel("true score (simulator)")
        ax.set_ylabel("Video2Reward x 100" if "reward" in key else "IDM proxy score")
        ax.set_title(f"{READINGS[key][0]}:\nSpearman {a['spearman']:.2f}", fontsize=9)
    axes[0][0].legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


class ClosedLoopInputError(ValueError):
    """A run folder or setting the evaluation cannot use (one line for the CLI)."""


def graded_policies(pixel: PixelPolicy, variants: Sequence[str] = tuple(VARIANTS)) -> dict[str, Callable]:
    """The policy and its versions degraded by design (Vid2World ranks policies of graded quality), keyed by their
    labels (``VARIANTS``; ``variants``: which, by short name): the order of the degradations is known before any
    run; where they land against constant velocity is what the true world says."""
    make = {"policy": lambda: pixel, "noise": lambda: SteeringNoise(pixel, 0.08, seed=1),
            "bias": lambda: SteeringBias(pixel, 0.05), "bias2": lambda: SteeringBias(pixel, 0.1),
            "cv": ConstantVelocity}
    return {VARIANTS[v]: make[v]() for v in variants}


def run_closed_loop(args: Any, make_runner: Callable | None) -> tuple[dict, str]:
    """``resim eval closed-loop``: parsed ``args``; ``make_runner(args) -> (WorldRollouts, meta)`` builds the
    world model, its VAE and prompts (None: the true world only). Returns (report, text)."""
    try:
        cfg = ClosedLoopConfig(seed=args.state_seed, states=args.states, seconds=args.seconds)
        pixel, pinfo = load_policy(args.policy, args.device)
        extra = {Path(r).name: load_policy(r, args.device)[0] for r in args.also}
        idm, _ = load_idm(args.idm, args.device)
        reward = load_reward(args.reward, args.device) if args.reward else None
    except (ValueError, FileNotFoundError) as e:
        raise ClosedLoopInputError(str(e)) from None
    policies = {**graded_policies(PixelPolicy(pixel, args.device), args.variants),
                **{name: PixelPolicy(m, args.device) for name, m in extra.items()}}
    clip_hw = trained_size_hw(args.checkpoint, args.shards) or tuple(pixel.cfg.frame_hw)
    loop, vae, meta = None, None, {}
    if make_runner is not None:
        runner, meta = make_runner(args)
        vae = runner.vae
        loop = WorldModelLoop(runner.model, vae, runner.text_for, runner.cfg, schedule=runner.schedule,
                              device=args.device)
    n = len(policies) * cfg.states
    print(f"[resim eval closed-loop] {len(policies)} policies x {cfg.states} starting states x {cfg.seconds:g} s, "
          f"{'true world only' if loop is None else 'true world and world model'} ...", file=sys.stderr)
    t0 = time.perf_counter()
    done = [0]

    def say(msg: str) -> None:
        done[0] += 1
        print(f"[{done[0]}/{n}, {time.perf_counter() - t0:.0f} s] {msg}", file=sys.stderr)

    rep = closed_loop_eval(policies, cfg, idm, clip_hw, loop=loop, vae=vae, reward=reward, seed=args.seed, say=say)
    rep["protocol"] = {"policy": pinfo, "also": list(args.also), "idm": str(args.idm), "reward": args.reward,
                       "clip_hw": list(clip_hw),
                       "config": dict(vars(cfg)), "world_model": meta or None, "device": args.device,
                       "seconds": round(time.perf_counter() - t0, 1)}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    strip = closed_loop_strip(rep, out / "closed_loop_strip.png", int(round(cfg.history_s * cfg.fps_hz)), cfg.fps_hz,
                              [t for t in (0, 2, 4, 6, 8) if t <= cfg.seconds])
    text = format_closed_loop(rep) + (f"\nwrote {strip} (first starting state: true world and world model)"
                                      if strip else "")
    return rep, text


def closed_loop_strip(rep: dict, path, first_frame: int, fps_hz: float = 10.0, times_s=(0, 2, 4, 6, 8)):
    """The first starting state, one row per (policy, loop): frames at ``times_s`` after the last history frame,
    the true world's row above the world model's. A PNG; None when there are no videos."""
    videos = rep.get("_videos") or {}
    rows = []
    for name in rep["policies"]:
        for loop in ("true", "world model"):
            v = videos.get((loop, name))
            if v is None:
                continue
            tiles = [_label(v[first_frame + int(round(t * fps_hz))], f"{loop}: {name[:22]}" if i == 0 else f"+{t:g}s")
                     for i, t in enumerate(times_s) if first_frame + int(round(t * fps_hz)) < len(v)]
            rows.append(np.concatenate(tiles, axis=1))
    if not rows:
        return None
    w = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 0), (0, w - r.shape[1]), (0, 0))) for r in rows]
    Image.fromarray(np.concatenate(rows, axis=0)).save(path)
    return path
