"""Planning with imagined futures (ReSim's use of Video2Reward): roll out K candidate trajectories from the
same history, score each imagined future with the reward model, rank them.

Candidates are kinematic paths in the ego frame (x forward m, y left m, yaw left + rad) at 0.5 s … 4.0 s
(ReSim's 8 waypoints at 2 Hz): keep lane, turn left, turn right, brake, swerve. All K futures are sampled in
ONE batched rollout with the same noise draws for every candidate (common random numbers), so score
differences come from the trajectory/command, not from the noise.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np
import torch

from resim.sample.outputs import decode_rollout, temporal_compression
from resim.sample.reward_score import score_videos
from resim.sample.rollout import Condition, RolloutConfig, rollout
from resim.shards.schema import pixel_frame_count

CANDIDATE_NAMES = ("keep_lane", "turn_left", "turn_right", "brake", "swerve")


@dataclass
class Candidate:
    name: str
    trajectory: np.ndarray          # (8, 3) float32: x m, y m, yaw rad (ego frame, left +)
    command: str                    # one of resim.shards.schema.COMMANDS


def _integrate(speed_fn: Callable[[float], float], yaw_fn: Callable[[float], float], horizon_s: float,
               num_waypoints: int, dt_fine: float = 0.01) -> np.ndarray:
    """Waypoints at k·horizon/num_waypoints from a speed profile and a heading profile (Euler, fine steps)."""
    x = y = 0.0
    out, t, k = [], 0.0, 1
    step_s = horizon_s / num_waypoints
    n = int(round(horizon_s / dt_fine))
    for i in range(n):
        t = (i + 0.5) * dt_fine
        v, yaw = speed_fn(t), yaw_fn(t)
        x += v * math.cos(yaw) * dt_fine
        y += v * math.sin(yaw) * dt_fine
        if abs((i + 1) * dt_fine - k * step_s) < dt_fine / 2:
            out.append((x, y, yaw_fn((i + 1) * dt_fine)))
            k += 1
    return np.asarray(out[:num_waypoints], dtype=np.float32)


def make_candidate(name: str, speed_mps: float = 8.0, horizon_s: float = 4.0, num_waypoints: int = 8) -> Candidate:
    """One named kinematic candidate (see module docstring); turns sweep 60° over the horizon."""
    turn = math.radians(60.0)
    if name == "keep_lane":
        return Candidate(name, _integrate(lambda t: speed_mps, lambda t: 0.0, horizon_s, num_waypoints), "Moving forward")
    if name in ("turn_left", "turn_right"):
        sign = 1.0 if name == "turn_left" else -1.0
        v = 0.75 * speed_mps   # slow down for the turn
        traj = _integrate(lambda t: v, lambda t: sign * turn * t / horizon_s, horizon_s, num_waypoints)
        return Candidate(name, traj, "Turning left" if sign > 0 else "Turning right")
    if name == "brake":
        decel = speed_mps / horizon_s  # to a stop at the horizon
        return Candidate(name, _integrate(lambda t: max(0.0, speed_mps - decel * t), lambda t: 0.0, horizon_s,
                                          num_waypoints), "Moving forward")
    if name == "swerve":
        amp_m = 3.0  # one lane width to the left and back: y = A sin²(π t / T)
        # heading of the path y(x) with x ≈ v t: dy/dt = A π/T sin(2π t/T)
        yaw = lambda t: math.atan2(amp_m * math.pi / horizon_s * math.sin(2 * math.pi * t / horizon_s), speed_mps)  # noqa: E731
        return Candidate(name, _integrate(lambda t: speed_mps, yaw, horizon_s, num_waypoints), "Moving forward")
    raise ValueError(f"unknown candidate {name!r}; known: {', '.join(CANDIDATE_NAMES)}")


def default_candidates(speed_mps: float = 8.0, names: Sequence[str] = CANDIDATE_NAMES) -> list[Candidate]:
    return [make_candidate(n, speed_mps) for n in names]


@dataclass
class PlanRow:
    rank: int
    name: str
    command: str
    score: float
    trajectory: np.ndarray
    frames: np.ndarray | None = None      # (T, H, W, 3) uint8 decoded video (history + future)
    latents: np.ndarray | None = None     # (T_lat, C, h, w)


@dataclass
class PlanResult:
    rows: list[PlanRow]                   # best (highest reward) first
    num_history_px: int
    seconds: float
    info: dict = field(default_factory=dict)

    def table(self) -> str:
        lines = ["| rank | candidate | command | reward |", "|---:|---|---|---:|"]
        lines += [f"| {r.rank} | {r.name} | {r.command} | {r.score:.4f} |" for r in self.rows]
        return "\n".join(lines)


def plan(world_model: Any, reward_model: Any, vae: Any, history: torch.Tensor,
         text_for: Callable[[str | None], torch.Tensor], candidates: Sequence[Candidate],
         cfg: RolloutConfig, num_future_frames: int, *, seed: int = 0, policy_for: Callable | None = None,
         progress: Any = None, actions_from_trajectory: bool = False, schedule: Any = None,
         log: Callable[[str], None] | None = None) -> PlanResult:
    """Roll out every candidate from ``history`` (1, H, C, h, w), decode, score the futures, rank.

    ``text_for(command or None)`` → ``(1, L, D_text)`` prompt embedding (None = prefix alone, the CFG null).
    ``policy_for(trajectories (K, 8, 3))`` optionally returns a rollout policy (e.g. actions derived from the
    trajectories for action-conditioned models; then pass ``actions_from_trajectory=True`` so that guidance drops
    them with the trajectory, see ``rollout``). ``log(message)`` hears about the steps after the rollouts
    (decoding, scoring: minutes on a CPU, after a progress bar of the rollouts has reached its end).
    """
    if history.dim() != 5 or history.shape[0] != 1:
        raise ValueError(f"history must be (1, H, C, h, w), got {tuple(history.shape)}")
    if not candidates:
        raise ValueError("no candidate trajectories to plan over")
    k = len(candidates)
    dev = history.device
    trajs = torch.from_numpy(np.stack([c.trajectory for c in candidates])).to(dev)
    text = torch.cat([text_for(c.command) for c in candidates]).to(dev)
    null = text_for(None).to(dev).expand(k, -1, -1)
    cond = Condition(text=text, null_text=null, trajectory=trajs, label="plan")
    res = rollout(world_model, history.expand(k, -1, -1, -1, -1), cond, num_future_frames, cfg, seed=seed,
                  policy=policy_for(trajs) if policy_for else None, progress=progress, same_noise=True,
                  actions_from_trajectory=actions_from_trajectory, schedule=schedule)
    say = log or (lambda _m: None)
    say(f"decoding {k} imagined futures with the VAE ...")
    frames = decode_rollout(vae, res.latents, res.num_history_frames, cfg.frames_per_round,
                            cfg.history_frames, batch_size=min(k, 8))  # (K, F, H, W, 3)
    say(f"scoring {k} futures with Video2Reward ...")
    h0 = res.num_history_frames
    num_hist_px = pixel_frame_count(h0, temporal_compression(vae))
    futures = [f[num_hist_px:] for f in frames]
    scores = score_videos(reward_model, futures, names=[c.name for c in candidates])
    order = np.argsort(-scores, kind="stable")
    rows = [PlanRow(rank=r + 1, name=candidates[i].name, command=candidates[i].command, score=float(scores[i]),
                    trajectory=candidates[i].trajectory, frames=frames[i], latents=res.latents[i].cpu().numpy())
            for r, i in enumerate(order)]
    return PlanResult(rows, num_hist_px, res.seconds, {"kv_cache": res.kv_cache_used,
                                                       "model_forwards": res.model_forwards})
