"""`resim simulate`: one policy driving inside the world model for a long time, the true world beside it.

Two kinds of start:

* **A synthetic starting state** (default; ``--state-seed``/``--state``): a fork world, as in
  ``resim eval closed-loop``. The expert drives the first 0.8 s, the VAE encodes those frames, and the policy
  drives on inside the world model, told the itinerary's command. The same policy drives the true world from
  the same start, so the two videos and the true score sit side by side.
* **A recorded history** (``--history VIDEO|SHARD_KEY``): the last 9 frames of a video file or a shard clip's
  history. There is no true world to compare with; the command is ``--command`` (default: the clip's own, or
  "Moving forward" for a video) and the speedometer starts at ``--speed-mps`` (default: read off the clip's
  trajectory, else 8 m/s, the synthetic world's cruising speed).

With ``--reward RUN``, Video2Reward scores the drive over time: one window ending every second, so a
drive that goes wrong shows where.
"""
from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np
import torch

from resim.config import ConfigError
from resim.eval.drive import PixelPolicy, itinerary
from resim.eval.policy_ranking import (ClosedLoopConfig, ClosedLoopInputError, graded_policies, history_of,
                                       loop_guidance, starting_states)
from resim.media.frames import cover_crop
from resim.models.policy.variants import VARIANTS
from resim.models.reward.checkpoint import load_checkpoint as load_reward
from resim.sample.load import SamplingInputError, history_from_shard, history_from_video, trained_size_hw
from resim.sample.outputs import decode_latents, write_rollout
from resim.sample.reward_score import score_videos
from resim.sample.simulate import WorldModelLoop
from resim.synthworld.closed_loop import drive
from resim.synthworld.drivers import simulate
from resim.train.tasks.policy import load_policy

DEFAULT_SPEED_MPS = 8.0        # the synthetic world's cruising speeds are 7-10 m/s


@dataclass
class SimulateRun:
    """`resim simulate`'s settings beyond its flags (``--set simulate.KEY=VALUE``)."""
    state: int = 0                    # which starting state of state_seed (0, 1, ...)
    state_seed: int = 5000            # seed of the starting-state fork worlds
    variant: str = "policy"           # which version of the policy drives (resim.models.policy.variants)
    world_command: bool = False       # prompt the world model with the navigation command too (default: null)
    speed_mps: Optional[float] = None   # with --history: the speedometer at the start (default: the clip's, else 8)

    def __post_init__(self) -> None:
        if self.state < 0:
            raise ConfigError(f"state={self.state}: must be >= 0")
        if self.variant not in VARIANTS:
            raise ConfigError(f"variant={self.variant!r}: one of {', '.join(VARIANTS)}")
        if self.speed_mps is not None and not 0 <= self.speed_mps < 60:
            raise ConfigError(f"speed_mps={self.speed_mps}: must be in [0, 60)")


def reward_over_time(reward: Any, frames: np.ndarray, first: int, fps_hz: float, every_s: float = 1.0,
                     name: str = "video") -> list[dict]:
    """Video2Reward on windows of ``frames`` (T, H, W, 3) uint8 that end every ``every_s`` after frame ``first``
    (the last history frame), from the first window that fits: ``[{"t_s": end of the window after first,
    "score": predicted infraction score in (0, 1)}]``; empty when the video is shorter than one window."""
    w = reward.cfg.window_frames
    step = max(1, int(round(every_s * fps_hz)))
    ends = [e for e in range(first + step + 1, len(frames) + 1, step) if e >= w]   # exclusive ends
    if not ends:
        return []
    scores = score_videos(reward, [frames[e - w:e] for e in ends], names=[f"{name} to frame {e}" for e in ends])
    return [{"t_s": round((e - 1 - first) / fps_hz, 2), "score": round(float(s), 4)} for e, s in zip(ends, scores)]


def plot_reward_over_time(series: dict[str, list[dict]], path, title: str):
    # matplotlib is slow to import and only the plot needs it
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 3.2))
    for label, pts in series.items():
        if pts:
            ax.plot([p["t_s"] for p in pts], [p["score"] for p in pts], marker="o", ms=3, label=label)
    ax.set_xlabel("seconds after the history")
    ax.set_ylabel("Video2Reward (1 = clean)")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _recorded_history(args: Any, vae: Any, clip_hw: tuple[int, int], fps_hz: float):
    """(latents (1, 3, C, h, w), frames (9, h, w, 3) uint8, speed m/s, command, source) of ``--history``."""
    try:
        if Path(args.history).is_file():
            h = history_from_video(args.history, vae, 3, clip_hw, fps_hz)
        else:
            h = history_from_shard(args.shards, args.history, 3)
    except SamplingInputError as e:
        raise ClosedLoopInputError(str(e)) from None
    if abs(h.fps_hz - fps_hz) > 1e-6:   # the loop decides every latent frame = 0.4 s at the training clips' rate
        raise ClosedLoopInputError(f"history {args.history}: its clip is at {h.fps_hz:g} Hz; the closed loop drives "
                                   f"{fps_hz:g}-Hz clips (a NAVSIM key at 2 Hz cannot start it)")
    frames = h.frames
    if frames is None:    # a shard written without frames.mp4: what the VAE makes of the latents
        frames = decode_latents(vae, h.latents, batch_size=1)[0]
    speed = args.settings.section("simulate").speed_mps
    if speed is None:   # the first waypoint is 0.5 s ahead
        speed = float(np.hypot(*h.trajectory[0, :2]) / 0.5) if h.trajectory is not None else DEFAULT_SPEED_MPS
    command = args.command or (h.meta or {}).get("command") or "Moving forward"
    return h.latents.float(), np.asarray(frames, np.uint8), speed, command, h.source


def run_simulate(args: Any, make_runner: Callable) -> str:
    """``resim simulate``: ``args`` as parsed (``resim/eval/simulate_cli.py``), ``make_runner(args)`` builds the world
    model, its VAE and prompts. Writes OUT/world_model.* (and, from a synthetic state, OUT/true_world.*): mp4,
    gif, contact sheet, meta with the per-decision plans and commands; OUT/simulate.json; with ``--reward``,
    OUT/reward_over_time.png. Returns the summary text."""
    try:
        run = args.settings.section("simulate")
        cfg = ClosedLoopConfig(seed=run.state_seed, states=max(2, run.state + 1), seconds=max(4.0, args.seconds))
        policy_model, pinfo = load_policy(args.policy, args.device)
        reward = load_reward(args.reward, args.device) if args.reward else None
    except (ValueError, FileNotFoundError) as e:
        raise ClosedLoopInputError(str(e)) from None
    label, policy = next(iter(graded_policies(PixelPolicy(policy_model, args.device), [run.variant]).items()))
    clip_hw = trained_size_hw(args.checkpoint, args.shards) or tuple(policy_model.cfg.frame_hw)
    loop_guidance(args, run.world_command)
    runner, meta = make_runner(args)
    loop = WorldModelLoop(runner.model, runner.vae, runner.text_for, runner.cfg, schedule=runner.schedule,
                          device=args.device, command_to_world=run.world_command)
    st = expert = None
    if args.history:
        latents, frames, speed, command, where = _recorded_history(args, runner.vae, clip_hw, cfg.fps_hz)
        command_at, t0 = (lambda t: command), 0.0    # noqa: E731
    else:
        st = starting_states(cfg)[run.state]
        total = cfg.history_s + args.seconds
        command_at, t0, where = itinerary(st.world, total, cfg.sim_hz), cfg.history_s, st.name
        expert = simulate(st.world, total, cfg.sim_hz, np.random.default_rng(0), "expert")
        latents, frames, speed = history_of(st, cfg, runner.vae, clip_hw, expert)
    out = Path(args.out)
    t_start = time.perf_counter()
    n_dec = int(np.ceil(args.seconds / cfg.decision_s - 1e-9))
    say = lambda i, n: print(f"[resim simulate] decision {i}/{n} ({time.perf_counter() - t_start:.0f} s)",  # noqa: E731
                             file=sys.stderr) if i % 5 == 0 or i == n else None
    print(f"[resim simulate] {where}, policy {label!r}, {args.seconds:g} s = {n_dec} decisions of "
          f"{cfg.decision_s:g} s, {runner.cfg.num_steps} DDIM steps each ...", file=sys.stderr)
    w = loop.run(latents, frames, speed, policy, args.seconds, command_at=command_at, t0_s=t0, seed=args.seed,
                 name=label, on_decision=say)
    plans = [{"t_s": round(t, 3), "command": c, "waypoints": p.round(3).tolist()}
             for (t, p), c in zip(w.plans, w.commands)]
    nh, first = w.num_history_frames, w.num_history_frames - 1
    write_rollout(out, "world_model", w.frames, w.latents[0].numpy(), num_history_px=nh, fps_hz=cfg.fps_hz,
                  title=f"world model: {label} ({where})", meta={"plans": plans})
    summary = {"start": where, "policy": pinfo, "variant": label, "seconds": args.seconds,
               "world_command": run.world_command,
               "decisions": len(w.plans), "wall_s": round(w.seconds, 1),
               "wall_s_per_generated_s": round(w.seconds / args.seconds, 2), "world_model": meta,
               "device": args.device, "torch_threads": torch.get_num_threads()}
    series = {}
    if reward is not None:
        series["world model"] = reward_over_time(reward, w.frames, first, cfg.fps_hz, name="world model")
    lines = [f"{where}: {len(w.plans)} decisions, {w.seconds:.0f} s ({summary['wall_s_per_generated_s']:g} s per "
             f"generated second on {args.device})"]
    if st is not None:
        r = drive(st.world, policy, st.renderer(cfg), cfg.loop_cfg(cfg.history_s + args.seconds), label,
                  command_at=command_at, expert=expert)
        true_frames = np.stack([cover_crop(f, clip_hw) for f in r.frames])
        write_rollout(out, "true_world", true_frames, np.zeros((0,), np.float32), num_history_px=nh,
                      fps_hz=cfg.fps_hz, title=f"true world: {label} ({where})",
                      meta={"plans": [{"t_s": round(t, 3), "waypoints": p.round(3).tolist()} for t, p in r.plans],
                            "score": r.score.score_composed, "infractions": r.score.names()})
        summary.update(true_world_score=r.score.score_composed, true_world_infractions=r.score.names())
        lines[0] += f"; true world score {r.score.score_composed:.1f} {r.score.names() or ''}"
        if reward is not None:
            series["true world"] = reward_over_time(reward, true_frames, first, cfg.fps_hz, name="true world")
    if series:
        summary["video2reward_over_time"] = {**series, "reward": str(args.reward)}
        plot_reward_over_time(series, out / "reward_over_time.png", f"{label}, {where}")
        lines.append("Video2Reward over time (1 = clean): " + "; ".join(
            k + " " + " ".join(f"{p['score']:.2f}" for p in v[::max(1, len(v) // 8)]) for k, v in series.items()))
    (out / "simulate.json").write_text(json.dumps(summary, indent=1, default=str))
    lines.append(f"wrote {out}/world_model.mp4" + (", true_world.mp4" if st is not None else "")
                 + " (+ gif, sheets, plans in *_meta.json)" + (", reward_over_time.png" if series else "")
                 + " and simulate.json")
    return "\n".join(lines)
