"""Closed loop inside the world model: a policy drives, the world model answers with the next frames.

The counterpart of ``resim.synthworld.closed_loop.drive`` (the true world), with the world model in place of the
simulator (Vid2World's "Real2Sim" policy evaluation; DIAMOND lets one play inside its world model):

1. **History.** ``history_latents`` (the VAE's encoding of recorded frames: ReSim's 9 frames = 3 latent
   frames) and the same frames in pixels, which the policy sees first.
2. **Decision.** Every ``latents_per_decision`` latent frames (1 = 0.4 s at 10 Hz) the policy gets an
   ``Observation``: the last decoded frames, the speedometer (the speed its own last plan asked for; the
   first decision reads the recorded speed), and the itinerary's command. It answers 8 waypoints.
3. **World model.** The sampler (``resim.sample.rollout``, KV cache and guidance as configured) rolls
   ``latents_per_decision`` latent frames out from the last ``history_frames`` latent frames, conditioned on
   the plan as the trajectory and on the command's prompt (``command_to_world=False``: the null prompt, so
   the plan alone says where the car goes; the policy is still told the command), and the VAE decodes them.
   The window slides over the model's own output, as in a long rollout.

There is no pose: a policy that reads ``Observation.pose`` (the true simulator's privileged reference
planners) cannot drive here, by construction.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Sequence

import numpy as np
import torch

from resim.sample.outputs import decode_latents
from resim.sample.rollout import Condition, RolloutConfig, rollout
from resim.synthworld.closed_loop import Observation, check_plan


# With the null prompt the unconditional branch of ReSim's guidance drops only the trajectory, so the guidance is
# trajectory guidance alone. Started at 15 instead of ReSim's 7.5 (linear to 1, as in ReSim), it brought the
# world model's replay of a true drive's plans 0.78 m closer to the true path on the dev starting states (7.5 at
# every step: 0.44 m) and raised the rank agreement on a fresh seed (docs/closed_loop.md, "Trajectory guidance").
NULL_PROMPT_GUIDANCE_START = 15.0


def loop_guidance_start(guidance_scale: float | None, preset: str, no_guidance: bool, world_command: bool,
                        student_unguided: bool) -> float | None:
    """The start guidance scale a closed loop samples with: the command line's, else
    ``NULL_PROMPT_GUIDANCE_START`` when the world model gets the null prompt under ReSim's guidance (None = the
    preset's own: with the command in the prompt, with the vid2world preset's action guidance, with
    ``--no-guidance``, or for a distilled student that samples without guidance; none of them was measured)."""
    if guidance_scale is not None or preset != "resim" or no_guidance or world_command or student_unguided:
        return guidance_scale
    return NULL_PROMPT_GUIDANCE_START


@dataclass
class WorldLoopResult:
    frames: np.ndarray                 # (T, H, W, 3) uint8: the history frames, then every generated frame
    latents: torch.Tensor              # (1, H0 + F, C, h, w) float32: history then generated latent frames
    num_history_frames: int            # pixel frames of the history at the start of ``frames``
    plans: list[tuple[float, np.ndarray]] = field(default_factory=list)   # (t_s, (8, 3)) per decision
    commands: list[str | None] = field(default_factory=list)
    seconds: float = 0.0               # wall time (a batch's, shared out over its policies)


class WorldModelLoop:
    """``model`` (a world model, eval mode, on ``device``), ``vae`` (``resim.media.encoders.VideoVAE``),
    ``text_for(command | None) -> (1, L, D)`` prompt embeddings (None: the null prompt), the sampler's
    ``rollout_cfg`` (its ``history_frames``, DDIM steps and guidance are used; the round is one decision)."""

    def __init__(self, model: Any, vae: Any, text_for: Callable[[str | None], torch.Tensor],
                 rollout_cfg: RolloutConfig, *, latents_per_decision: int = 1, fps_hz: float = 10.0,
                 schedule: Any = None, device: str = "cpu", command_to_world: bool = True):
        if latents_per_decision < 1:
            raise ValueError(f"latents_per_decision must be >= 1, got {latents_per_decision}")
        self.model, self.vae, self.text_for, self.device = model, vae, text_for, device
        self.command_to_world = command_to_world
        self.k = latents_per_decision
        self.cfg = replace(rollout_cfg, frames_per_round=self.k, chunk_frames=self.k)
        self.schedule, self.fps_hz = schedule, fps_hz
        self.tc = int(getattr(getattr(vae, "info", None), "temporal_compression", 4))
        self.decision_s = self.k * self.tc / fps_hz

    def run(self, history_latents: torch.Tensor, history_frames: np.ndarray, speed_mps: float,
            policy: Callable[[Observation], np.ndarray], seconds: float, *,
            command_at: Callable[[float], str] | None = None, t0_s: float = 0.0, seed: int = 0,
            observe_frames: int = 9, name: str | None = None,
            on_decision: Callable[[int, int], None] | None = None) -> WorldLoopResult:
        """One policy: :meth:`run_batch` with a batch of one."""
        return self.run_batch(history_latents, history_frames, speed_mps, [policy], seconds, command_at=command_at,
                              t0_s=t0_s, seeds=[seed], observe_frames=observe_frames,
                              names=[name] if name else None, on_decision=on_decision)[0]

    def run_batch(self, history_latents: torch.Tensor, history_frames: np.ndarray, speed_mps: float,
                  policies: Sequence[Callable[[Observation], np.ndarray]], seconds: float, *,
                  command_at: Callable[[float], str] | None = None, t0_s: float = 0.0,
                  seeds: Sequence[int] | None = None, observe_frames: int = 9, names: Sequence[str] | None = None,
                  on_decision: Callable[[int, int], None] | None = None) -> list[WorldLoopResult]:
        """Drive each of ``policies`` for ``seconds`` after the same history, the world-model rollouts of all of
        them batched (one sampler call and one VAE decode per decision: several times cheaper than one by one
        on a CPU). ``history_latents`` ``(1, H0, C, h, w)`` (× the VAE's scaling factor); ``history_frames``
        ``(1 + tc (H0 - 1), H, W, 3)`` uint8, the same history in pixels; ``t0_s``: the episode time of the last
        history frame (the itinerary's clock); ``seeds``: one per policy (default 0, 1, ...), decision ``i``
        drawing its noise from ``seed + i``, so a policy's rollout does not depend on its batch;
        ``on_decision(i, n)``: progress."""
        if history_latents.dim() != 5 or history_latents.shape[0] != 1:
            raise ValueError(f"history_latents must be (1, H0, C, h, w), got {tuple(history_latents.shape)}")
        b = len(policies)
        seeds = list(seeds) if seeds is not None else list(range(b))
        names = list(names) if names is not None else [type(p).__name__ for p in policies]
        if len(seeds) != b or len(names) != b:
            raise ValueError(f"one seed and one name per policy ({b}), got {len(seeds)} and {len(names)}")
        t_start = time.perf_counter()
        latents = history_latents.float().to(self.device).expand(b, -1, -1, -1, -1).contiguous()
        frames = [[f for f in np.asarray(history_frames)] for _ in range(b)]
        n_hist_px = len(frames[0])
        n_dec = max(1, int(np.ceil(seconds / self.decision_s - 1e-9)))
        plans: list[list] = [[] for _ in range(b)]
        commands: list[str | None] = []
        speed = [float(speed_mps)] * b
        null = self.text_for(None).to(self.device)
        for i in range(n_dec):
            t_s = t0_s + i * self.decision_s
            command = command_at(t_s) if command_at is not None else None
            commands.append(command)
            step_plans = []
            for j, policy in enumerate(policies):
                obs = Observation(frames=np.stack(frames[j][-observe_frames:]), speed_mps=speed[j], t_s=t_s,
                                  command=command)
                plan = check_plan(policy(obs), names[j])
                plans[j].append((t_s, plan))
                step_plans.append(plan)
            text = self.text_for(command if self.command_to_world else None).to(self.device)
            cond = Condition(text=text.expand(b, -1, -1), null_text=null.expand(b, -1, -1),
                             trajectory=torch.from_numpy(np.stack(step_plans)).float().to(self.device),
                             label=command or "")
            window = latents[:, -self.cfg.history_frames:]
            res = rollout(self.model, window, cond, self.k, self.cfg, schedule=self.schedule,
                          seeds=[s + i for s in seeds])
            latents = torch.cat([latents, res.future.to(self.device)], dim=1)
            # decode the window with the new frames (the causal VAE's first frame of a decode is a key frame;
            # the new frames are its last tc * k), not the whole rollout: constant cost per decision
            ctx = latents[:, -(self.cfg.history_frames + self.k):]
            px = decode_latents(self.vae, ctx, batch_size=b)
            for j in range(b):
                frames[j].extend(px[j, -self.tc * self.k:])
                # the speedometer: the speed this plan asked for over its first waypoint
                speed[j] = float(np.hypot(*step_plans[j][0, :2]) / 0.5)
            if on_decision is not None:
                on_decision(i + 1, n_dec)
        wall = time.perf_counter() - t_start
        return [WorldLoopResult(frames=np.stack(frames[j]), latents=latents[j:j + 1].cpu(), num_history_frames=n_hist_px,
                                plans=plans[j], commands=list(commands), seconds=wall / b) for j in range(b)]
