"""Classifier-free guidance for the world model, as pure functions plus one batched-forward helper.

* **Schedules** (:func:`guidance_scales`): the scale ``w_i`` used at DDIM step ``i`` of ``N``.
  ReSim (App. B.3, following CogVideoX) decreases the scale linearly from 7.5 to 1 over the steps; Vid2World
  (Table 3) uses a constant 2.5. ``cosine`` goes from ``start`` to ``end`` along a half cosine.
* **Combination** (:func:`cfg_combine`): ``v = v_u + w (v_c - v_u)``.
* **Guidance rescale** (:func:`rescale_guidance`, Lin et al. 2024 "Common diffusion noise schedules and sample
  steps are flawed", Sec. 3.4): match the per-sample std of the guided prediction to the conditional one,
  ``v_r = v_cfg · std(v_c) / std(v_cfg)``, then ``v = φ v_r + (1 - φ) v_cfg`` (Vid2World: φ = 0.7).
* **Branches** (:func:`combine_branches`): the conditional and the unconditional inputs are concatenated
  along the batch and go through the model in ONE forward (2B samples), never two (the rollout builds the
  batch, ``rollout._Roller._branch_inputs``); ``combine_branches`` splits and guides the output.

What the unconditional branch drops is a :class:`GuidanceConfig` choice: the text command (the prompt becomes
the fixed prefix alone, ReSim), the trajectory (ReSim trains with both dropped at p = 0.5), and/or the actions of
the frames being generated — Vid2World's *causal action guidance*: "conditional" vs. "the most recent action
masked". A dropped trajectory/action is fed as the model's ``trajectory_keep``/``action_keep`` = False (its
null embedding), as in training's condition dropout. Dropping the trajectory also drops actions derived from it
(``rollout(..., actions_from_trajectory=True)``): training drops them together.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch

from resim.config import ConfigError, check_positive, from_dict

ScheduleKind = Literal["constant", "linear", "cosine"]


def guidance_scales(kind: ScheduleKind, num_steps: int, start: float, end: float = 1.0) -> list[float]:
    """Per-step guidance scales ``[w_0, …, w_{N-1}]`` (step 0 is the noisiest).

    * ``constant``: ``w_i = start``
    * ``linear``:   ``w_i = start + (end - start) · i / (N - 1)``  (ReSim: 7.5 → 1)
    * ``cosine``:   ``w_i = end + (start - end) · (1 + cos(π i / (N - 1))) / 2``
    With ``N = 1`` every kind gives ``[start]``.
    """
    if num_steps < 1:
        raise ValueError(f"num_steps must be >= 1, got {num_steps}")
    if kind == "constant" or num_steps == 1:
        if kind not in ("constant", "linear", "cosine"):
            raise ValueError(f"unknown guidance schedule {kind!r}")
        return [float(start)] * num_steps
    n = num_steps - 1
    if kind == "linear":
        return [start + (end - start) * i / n for i in range(num_steps)]
    if kind == "cosine":
        return [end + (start - end) * (1 + math.cos(math.pi * i / n)) / 2 for i in range(num_steps)]
    raise ValueError(f"unknown guidance schedule {kind!r}; expected constant, linear or cosine")


def cfg_combine(v_cond: torch.Tensor, v_uncond: torch.Tensor, scale: float) -> torch.Tensor:
    """``v_u + w (v_c - v_u)``; ``w = 1`` returns ``v_c``, ``w = 0`` returns ``v_u``."""
    return v_uncond + scale * (v_cond - v_uncond)


def rescale_guidance(v_cfg: torch.Tensor, v_cond: torch.Tensor, phi: float) -> torch.Tensor:
    """Lin et al.'s guidance rescale: ``φ · v_cfg·std(v_c)/std(v_cfg) + (1-φ) · v_cfg``.

    The std is per sample over every non-batch dimension (unbiased, as diffusers' ``rescale_noise_cfg``),
    computed in float32 at least. ``φ = 0`` returns ``v_cfg`` unchanged.
    """
    if not 0.0 <= phi <= 1.0:
        raise ValueError(f"guidance rescale phi must be in [0, 1], got {phi}")
    if phi == 0.0:
        return v_cfg
    dims = list(range(1, v_cfg.ndim))
    work = torch.promote_types(v_cfg.dtype, torch.float32)
    std_c = v_cond.to(work).std(dim=dims, keepdim=True)
    std_g = v_cfg.to(work).std(dim=dims, keepdim=True)
    rescaled = v_cfg.to(work) * (std_c / std_g)
    return (phi * rescaled + (1 - phi) * v_cfg.to(work)).to(v_cfg.dtype)


@dataclass
class GuidanceConfig:
    """What guidance to apply at sampling time. Presets: :data:`GUIDANCE_PRESETS`."""
    schedule: ScheduleKind = "linear"
    scale_start: float = 7.5
    scale_end: float = 1.0
    rescale_phi: float = 0.0
    drop_text: bool = True              # unconditional branch: prompt = prefix alone (command dropped)
    drop_trajectory: bool = True        # unconditional branch: trajectory dropped (and actions derived from it)
    drop_recent_actions: bool = False   # unconditional branch: actions of the frames being generated dropped
    enabled: bool = True                # False: conditional branch only (one forward of B samples)

    def __post_init__(self) -> None:
        if self.schedule not in ("constant", "linear", "cosine"):
            raise ConfigError(f"guidance.schedule={self.schedule!r} not in constant/linear/cosine")
        if not 0.0 <= self.rescale_phi <= 1.0:
            raise ConfigError(f"guidance.rescale_phi={self.rescale_phi} not in [0, 1]")
        for name in ("scale_start", "scale_end"):
            check_positive(f"guidance.{name}", getattr(self, name), allow_zero=True)
        if self.enabled and not (self.drop_text or self.drop_trajectory or self.drop_recent_actions):
            raise ConfigError("guidance is enabled but the unconditional branch drops nothing "
                              "(set drop_text, drop_trajectory or drop_recent_actions, or enabled=false)")

    def scales(self, num_steps: int) -> list[float]:
        if not self.enabled:
            return [1.0] * num_steps
        return guidance_scales(self.schedule, num_steps, self.scale_start, self.scale_end)


GUIDANCE_PRESETS: dict[str, dict] = {
    # ReSim App. B.3: text-command CFG decreasing 7.5 -> 1 (trajectory dropped with the command)
    "resim": dict(schedule="linear", scale_start=7.5, scale_end=1.0, rescale_phi=0.0,
                  drop_text=True, drop_trajectory=True, drop_recent_actions=False),
    # Vid2World Sec. 4.2 / Table 3: causal action guidance 2.5 with rescale 0.7
    "vid2world": dict(schedule="constant", scale_start=2.5, scale_end=2.5, rescale_phi=0.7,
                      drop_text=False, drop_trajectory=False, drop_recent_actions=True),
    "none": dict(enabled=False, drop_text=False, drop_trajectory=False),
}


def guidance_preset(name: str, **overrides) -> GuidanceConfig:
    if name not in GUIDANCE_PRESETS:
        raise ConfigError(f"unknown guidance preset {name!r}; known: {sorted(GUIDANCE_PRESETS)}")
    return from_dict(GuidanceConfig, {**GUIDANCE_PRESETS[name], **overrides})


def guidance_from_cli(name: str, scale_start: float | None = None, schedule: ScheduleKind | None = None) -> GuidanceConfig:
    """The guidance of a sampling command (`resim sample/plan/eval`, ``rollout.guidance.*`` of its settings, or a
    distillation's teacher): preset ``name`` with a start scale and a schedule. A constant preset (vid2world)
    keeps its scale at every step,
    so the scale sets its end too; ``none`` ignores both."""
    if name == "none":
        return guidance_preset(name)
    g: dict = {}
    if scale_start is not None:
        g["scale_start"] = scale_start
        if GUIDANCE_PRESETS[name].get("schedule") == "constant":
            g["scale_end"] = scale_start
    if schedule is not None:
        g["schedule"] = schedule
    return guidance_preset(name, **g)


def combine_branches(v_both: torch.Tensor, scale: float, phi: float) -> torch.Tensor:
    """Split a batched ``[cond; uncond]`` prediction ``(2B, …)`` and guide it → ``(B, …)``.

    With ``scale == 1`` the result is exactly the conditional half (rescale of ``v_c`` by its own std is a no-op).
    """
    if v_both.shape[0] % 2:
        raise ValueError(f"batched CFG prediction must have an even batch, got {v_both.shape[0]}")
    v_c, v_u = v_both.chunk(2, dim=0)
    if scale == 1.0:
        return v_c
    return rescale_guidance(cfg_combine(v_c, v_u, scale), v_c, phi)
