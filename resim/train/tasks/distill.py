"""Guidance + step distillation of a world model into a few-step student (registry name ``distill``;
``resim train distill``).

**Method: ODE-trajectory regression** (CausVid, Yin et al. 2025, §4.3 "student initialization"; Self-Forcing
starts from the same). For each training clip the *teacher* (another run's world model, frozen) rolls the
clip's future out from its history under the clip's prompt (and its trajectory, when kept), with its guided
DDIM (ReSim: 50 steps, CFG 7.5 → 1), stopping also at the student's levels: the trailing grid of
``student_steps`` (4 steps: 999, 749, 499, 249). The *student* (the teacher's architecture, started from its
weights) learns to map the teacher's state at each of those levels straight to the teacher's final frames:
``|x̂0_student(x_tk, tk) − x0_teacher|²`` over the future frames, the history clean as in sampling. Sampling the
student is plain DDIM at its 4 levels with the conditional branch only (the guidance is distilled in): where the
student is exact, each DDIM step lands on the teacher's trajectory at the next level.

Why this method and not the others the anchors use: DMD (CausVid, Self-Forcing) needs a second, "fake" score
network trained alongside and a real-score teacher at every step, and it starts from this regression anyway;
progressive distillation needs log2(50/4) ≈ 4 rounds of training; consistency distillation needs a target
network and a skip schedule. The regression is one network and one loss, its targets are deterministic (so a
resumed run is exact), and it is the first stage of DMD should the student need more.

**Pairs** are made on the fly and cached: a clip's teacher trajectory is drawn the first time the clip is seen
(its noise, and whether it keeps its trajectory or uses the null prompt, seeded by the clip's key alone) and kept
in host memory (float16, ``(K + 1) × F`` latent frames per clip; 150 kB for the synthetic world's 10 × 16 × 8 × 12
futures). The first epoch costs the teacher's sampling; later epochs cost one student step. A resumed run makes
the same pairs again. At real size (a 13 × 16 × 60 × 90 latent clip is ~40× larger) a dataset of pairs written
once would replace the cache; that is not built.

The run's ``final/`` is a plain world-model export (``model_name: world``, the teacher's model config, the
student's weights) with a ``sampling`` section (``num_steps``, ``guidance: none``): ``resim sample``, ``resim
plan`` and ``resim eval`` read it and sample the student at its own steps without guidance.
"""
from __future__ import annotations

import copy
import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable

import torch

from resim.config import ConfigError, from_dict, safe_yaml, save as save_config
from resim.diffusion.ddim import ddim_timesteps
from resim.diffusion.guidance import GUIDANCE_PRESETS, guidance_preset
from resim.diffusion.schedule import alphas_cumprod
from resim.models.exported import CONFIG_FILE, FINAL, ExportError, find_export, read_config
from resim.sample.load import SAMPLING_KEY, SamplingInputError, load_world_model
from resim.sample.rollout import Condition, RolloutConfig, rollout
from resim.train.tasks.world_model import TrainableWorldModel, build_world

@dataclass
class DistillConfig:
    """The ``model:`` section of a ``resim train distill`` run."""
    teacher: Path | None = None          # a world-model export: a run folder, its final/, or a shipped name
    student_steps: int = 4               # the student's DDIM steps: the trailing grid (4: 999, 749, 499, 249)
    teacher_steps: int = 50              # the teacher's DDIM steps (ReSim: 50); the student's levels are added
    guidance: str = "resim"              # the teacher's guidance preset (resim.diffusion.guidance)
    guidance_scale: float | None = None  # the preset's start scale, overridden
    teacher_ema: bool = True             # the teacher's EMA weights where its export has them
    null_prompt_prob: float = 0.1        # share of clips distilled under the null prompt (the student's "no command")
    trajectory_keep_prob: float = 0.5    # share of the clips with a trajectory that are distilled with it
    seed: int = 0                        # the pairs' seed (with each clip's key)

    def __post_init__(self) -> None:
        if self.teacher is None:
            raise ConfigError("model.teacher is required: the world model to distil (a run folder, its final/, "
                              "or a shipped name such as synth-world)")
        if not 1 <= self.student_steps < self.teacher_steps:
            raise ConfigError(f"model.student_steps={self.student_steps} must be in [1, teacher_steps="
                              f"{self.teacher_steps})")
        if self.guidance not in GUIDANCE_PRESETS:
            raise ConfigError(f"model.guidance={self.guidance!r} not one of {sorted(GUIDANCE_PRESETS)}")
        for name in ("null_prompt_prob", "trajectory_keep_prob"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ConfigError(f"model.{name}={getattr(self, name)} must be in [0, 1]")

    def rollout_config(self, history_frames: int, future_frames: int, num_train_timesteps: int) -> RolloutConfig:
        """The teacher's sampler for one clip: one round, all future frames in one chunk (ReSim), clean history."""
        g = {} if self.guidance_scale is None else {"scale_start": self.guidance_scale}
        return RolloutConfig(num_steps=self.teacher_steps, history_frames=history_frames,
                             frames_per_round=future_frames, chunk_frames=future_frames, history_noise_level=0,
                             guidance=guidance_preset(self.guidance, **g),
                             include_levels=tuple(self.student_levels(num_train_timesteps)))

    def student_levels(self, num_train_timesteps: int) -> list[int]:
        return ddim_timesteps(self.student_steps, num_train_timesteps)


def _unit(key: str, seed: int, what: str) -> tuple[float, int]:
    """A uniform number in [0, 1) and a 31-bit seed, from the clip's key alone (not its batch)."""
    h = hashlib.sha256(f"{seed}:{what}:{key}".encode()).digest()
    return int.from_bytes(h[:4], "little") / 2 ** 32, int.from_bytes(h[4:8], "little") & 0x7FFFFFFF


class TeacherPairs:
    """The teacher's trajectories of clips, by key: ``(states (K, F, C, h, w), x0 (F, C, h, w), null, keep_traj)``."""

    def __init__(self, teacher: Any, cfg: DistillConfig):
        self.teacher, self.cfg = teacher, cfg
        self.cache: dict[str, tuple[torch.Tensor, torch.Tensor, bool, bool]] = {}
        self.made = 0

    def draws(self, key: str, has_trajectory: bool) -> tuple[bool, bool, int]:
        """(null prompt?, trajectory kept?, noise seed) of a clip: a function of its key and the config's seed."""
        u_null, noise_seed = _unit(key, self.cfg.seed, "null")
        u_traj, _ = _unit(key, self.cfg.seed, "trajectory")
        takes = getattr(self.teacher, "trajectory_encoder", None) is not None   # a model without one refuses it
        keep = takes and has_trajectory and u_traj < self.cfg.trajectory_keep_prob
        return u_null < self.cfg.null_prompt_prob, keep, noise_seed

    @torch.no_grad()
    def make(self, history: torch.Tensor, text: torch.Tensor, null_text: torch.Tensor, trajectory: torch.Tensor | None,
             seeds: list[int], future_frames: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Teacher rollouts of a group sharing a trajectory's presence → (states (B, K, F, ...), x0 (B, F, ...)),
        float32. ``history`` (B, H, C, h, w) clean latents; ``text``/``null_text`` (B, L, D)."""
        schedule = self.teacher.objective.schedule
        rc = self.cfg.rollout_config(history.shape[1], future_frames, schedule.num_train_timesteps)
        levels = set(self.cfg.student_levels(schedule.num_train_timesteps))
        states: dict[int, torch.Tensor] = {}

        def record(x: torch.Tensor, step: Any) -> None:
            if step.t in levels:
                states[step.t] = x.detach().float().clone()

        dtype = next(self.teacher.parameters()).dtype
        res = rollout(self.teacher, history.to(dtype=torch.float32), Condition(text=text.to(dtype),
                      null_text=null_text.to(dtype), trajectory=trajectory), future_frames, rc, schedule=schedule,
                      on_step=record, seeds=seeds)
        if set(states) != levels:   # our bug: the schedule must stop at every student level
            raise AssertionError(f"teacher trajectory missed levels {sorted(levels - set(states))}")
        order = sorted(levels, reverse=True)
        return torch.stack([states[t] for t in order], dim=1), res.future.float()

    def get(self, batch: Any, history_frames: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """For a training batch: (states (B, K, F, C, h, w), x0 (B, F, C, h, w), null (B,) bool, keep_traj (B,) bool)
        on the batch's device, float32; clips not yet seen are rolled out by the teacher first."""
        lat = batch.latents
        b, t = lat.shape[:2]
        f = t - history_frames
        has = torch.as_tensor(batch.has_trajectory).bool().cpu()
        draws = [self.draws(k, bool(has[i])) for i, k in enumerate(batch.keys)]
        # the stream draws with replacement: a key may come twice in one batch, and is rolled out once
        first = {k: i for i, k in reversed(list(enumerate(batch.keys)))}
        todo = sorted(i for k, i in first.items() if k not in self.cache)
        if todo:
            text, null = batch.text, batch.null_text
            for with_traj in (False, True):
                group = [i for i in todo if draws[i][1] == with_traj]
                if not group:
                    continue
                idx = torch.tensor(group, device=lat.device)
                txt = torch.where(torch.tensor([draws[i][0] for i in group], device=lat.device)[:, None, None],
                                  null[idx], text[idx])
                traj = batch.trajectory[idx].float() if with_traj else None
                st, x0 = self.make(lat[idx, :history_frames].float(), txt, null[idx], traj,
                                   [draws[i][2] for i in group], f)
                for j, i in enumerate(group):
                    self.cache[batch.keys[i]] = (st[j].half().cpu(), x0[j].half().cpu(), draws[i][0], draws[i][1])
                self.made += len(group)
        rows = [self.cache[k] for k in batch.keys]
        dev = lat.device
        return (torch.stack([r[0] for r in rows]).to(dev).float(), torch.stack([r[1] for r in rows]).to(dev).float(),
                torch.tensor([r[2] for r in rows], device=dev), torch.tensor([r[3] for r in rows], device=dev))


def distill_losses(student: Any, history: torch.Tensor, states: torch.Tensor, x0_teacher: torch.Tensor,
                   levels: list[int], alphas: torch.Tensor, text: torch.Tensor,
                   trajectory: torch.Tensor | None, trajectory_keep: torch.Tensor | None,
                   generator: torch.Generator | None = None) -> tuple[torch.Tensor, dict[str, float]]:
    """The ODE-regression loss on one batch: each sample at one of the student's levels (drawn uniformly).

    ``history`` (B, H, C, h, w) clean latents; ``states`` (B, K, F, C, h, w) the teacher's frames at ``levels``
    (K levels, noisiest first); ``alphas`` (N,) the schedule's ᾱ; ``x0_teacher`` (B, F, C, h, w) its final
    frames; ``text`` (B, L, D) the prompt the teacher had (the null prompt where it had that); ``trajectory``
    (B, N, 3) with ``trajectory_keep`` (B,) bool.
    Loss: mean squared error between the student's clean estimate and the teacher's, over the future frames."""
    b, k = states.shape[:2]
    h = history.shape[1]
    pick = torch.randint(0, k, (b,), generator=generator).to(states.device)
    x_t = states[torch.arange(b, device=states.device), pick]                       # (B, F, C, h, w)
    lv = torch.tensor(levels, device=states.device)[pick]                            # (B,)
    f = x_t.shape[1]
    t = torch.cat([torch.zeros(b, h, dtype=torch.long, device=states.device), lv[:, None].expand(b, f)], dim=1)
    x_in = torch.cat([history, x_t], dim=1)
    v = student(x_in, t, text, trajectory, None, trajectory_keep=trajectory_keep)[:, h:].float()
    a = alphas.to(states.device, torch.float32)[lv].view(b, 1, 1, 1, 1)
    x0_hat = a.sqrt() * x_t - (1 - a).sqrt() * v                                     # v-prediction → x0
    per = ((x0_hat - x0_teacher) ** 2).mean(dim=(1, 2, 3, 4))                        # (B,)
    loss = per.mean()
    with torch.no_grad():
        logs = {"loss": float(loss.detach())}
        for j, level in enumerate(levels):
            sel = pick == j
            if sel.any():
                logs[f"loss_t{level}"] = float(per[sel].mean())
    return loss, logs


class DistilledWorldModel(TrainableWorldModel):
    """The student: the teacher's network, trained by :func:`distill_losses` on the teacher's trajectories. Same
    parameter names as the teacher (its state dict is a world model's); the teacher is held outside the module
    tree, so it is neither trained, checkpointed nor exported."""

    def __init__(self, cfg: Any, objective: Any, distill: DistillConfig, teacher_model_cfg: dict):
        super().__init__(cfg, objective)
        self.distill = distill
        self.teacher_model_cfg = teacher_model_cfg
        self._teacher: list[Any] = []       # a list: an nn.Module attribute would register it
        self._pairs: TeacherPairs | None = None

    def attach_teacher(self, teacher: Any) -> None:
        self._teacher[:] = [teacher]
        self._pairs = TeacherPairs(teacher, self.distill)

    def loss(self, batch: Any) -> tuple[torch.Tensor, dict[str, float]]:
        if self._pairs is None:   # our bug: build_distill attaches it
            raise RuntimeError("the student has no teacher attached (resim.train.tasks.distill.build_distill attaches it)")
        teacher = self._teacher[0]
        dev = batch.latents.device
        if next(teacher.parameters()).device != dev:
            teacher.to(dev)
        h = batch.num_history_latent_frames or self.objective.num_history_frames
        states, x0, null, keep = self._pairs.get(batch, h)
        text = torch.where(null[:, None, None], batch.null_text, batch.text)
        # the trajectory always goes in, with its keep mask: a batch where every row drops it still gives the
        # encoder a (zero) gradient, so the optimizer holds a state for every trained parameter (exact resume)
        levels = self.distill.student_levels(self.objective.schedule.num_train_timesteps)
        traj = batch.trajectory.float() if self.trajectory_encoder is not None else None
        loss, logs = distill_losses(self, batch.latents[:, :h].float(), states, x0, levels,
                                    alphas_cumprod(self.objective.schedule), text, traj,
                                    keep if traj is not None else None)
        logs["teacher_clips"] = float(self._pairs.made)
        return loss, logs

    def export_run(self, run_dir: str | Path, data: Iterable) -> Path:
        """Turn ``RUN/final`` into a world-model export of the student (``model_name: world``, the teacher's model
        config) with its ``sampling`` section; the distillation's own config goes to ``final/distill.yaml``."""
        final = Path(run_dir) / FINAL
        run_cfg = safe_yaml((final / CONFIG_FILE).read_text())
        save_config(run_cfg, final / "distill.yaml")
        world = {k: v for k, v in run_cfg.items() if k not in ("model_name", "model")}
        world["model_name"] = "world"
        world["model"] = {**self.teacher_model_cfg, "init_weights": None}
        world[SAMPLING_KEY] = {"num_steps": self.distill.student_steps, "guidance": "none",
                               "distilled_from": str(self.distill.teacher),
                               "teacher_steps": self.distill.teacher_steps, "teacher_guidance": self.distill.guidance}
        save_config(world, final / CONFIG_FILE)
        return final


def build_distill(model_cfg: dict, *, device: str | torch.device = "cpu") -> DistilledWorldModel:
    cfg = from_dict(DistillConfig, model_cfg, prefix="model")
    try:
        folder = find_export(cfg.teacher, shipped=True)
        teacher_cfg = read_config(folder, default_name="world")
    except ExportError as e:
        raise ConfigError(f"model.teacher: {e}") from None
    if teacher_cfg.model_name != "world":
        raise ConfigError(f"model.teacher={cfg.teacher}: a {teacher_cfg.model_name!r} export, not a world model's")
    if SAMPLING_KEY in teacher_cfg.raw:
        raise ConfigError(f"model.teacher={cfg.teacher}: already a distilled student (its config has a "
                          f"'{SAMPLING_KEY}' section); distil its teacher instead")
    if (teacher_cfg.model.get("lora_rank") or 0) > 0:
        raise ConfigError(f"model.teacher={cfg.teacher}: has LoRA adapters; merge them into its weights first")
    if str(device) == "meta":   # the launcher's dry run: the student's shape only
        proto = build_world({**teacher_cfg.model, "init_weights": None}, device="meta")
        with torch.device("meta"):
            return DistilledWorldModel(copy.deepcopy(proto.cfg), proto.objective, cfg, dict(teacher_cfg.model))
    try:
        teacher, _ = load_world_model(folder, "cpu", prefer_ema=cfg.teacher_ema)
    except SamplingInputError as e:
        raise ConfigError(f"model.teacher: {e}") from None
    student = DistilledWorldModel(copy.deepcopy(teacher.cfg), teacher.objective, cfg, dict(teacher_cfg.model))
    student.load_state_dict(teacher.state_dict())
    student.requires_grad_(True).train()
    for name, param in student.named_parameters():
        # no per-frame actions go in (the teacher's rollouts carry none, as `resim eval` rolls out): only the
        # action encoder's null embedding is used, and a parameter that never gets a gradient would have no
        # optimizer state to checkpoint
        if name.startswith("action_encoder.") and name != "action_encoder.null":
            param.requires_grad_(False)
    student.ddp_find_unused_parameters = True   # e.g. the trajectory encoder in a batch that drops every trajectory
    student.attach_teacher(teacher)
    return student
