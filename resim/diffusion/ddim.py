"""Deterministic DDIM (eta = 0) over CogVideoX's noise schedule, as pure functions.

CogVideoX-2b samples with diffusers' ``CogVideoXDDIMScheduler`` configured as
``beta_schedule="scaled_linear"`` (0.00085 … 0.012), ``snr_shift_scale=3.0``, ``rescale_betas_zero_snr=True``,
``prediction_type="v_prediction"``, ``timestep_spacing="trailing"``, ``set_alpha_to_one=True`` and
``clip_sample=False``. ReSim (App. B.3) samples with DDIM in 50 steps; Vid2World (Table 3) with DDIM, trailing.

Notation: ``a_t`` = ``alphas_cumprod[t]`` (ᾱ_t). With v-prediction
``x0 = sqrt(a_t) x_t - sqrt(1-a_t) v`` and ``eps = sqrt(a_t) v + sqrt(1-a_t) x_t``; DDIM (eta = 0) moves to
``x_prev = sqrt(a_prev) x0 + sqrt(1-a_prev) eps``. Zero terminal SNR gives ``a_{N-1} == 0`` (N =
``num_train_timesteps``, the length of ``alphas_cumprod``: 1000 for CogVideoX, whatever the model's
``objective.schedule`` says otherwise): the first step then reads ``x0 = -v`` and ``eps = x_t`` (no division by
``sqrt(a_t)`` anywhere, so it stays finite).

Step count: any ``num_steps`` in [1, N]. We step from each timestep to the *next timestep of the list*
(the last one to "t = -1", i.e. ``a_prev = 1``). diffusers instead steps to ``t - N // num_steps``; the two
agree whenever ``num_steps`` divides N (10, 20, 25, 50, 100, … for 1000) and differ by ≤ 1 train step otherwise
(diffusers' trailing list is rounded but its ``prev`` is not). Tests check equality with diffusers at 50 steps
(N = 1000, and N = 500).

Shapes: latents ``(B, T, C, h, w)`` float; ``a_t``/``a_prev`` are Python floats or tensors broadcastable to
the latents (e.g. ``(B, T, 1, 1, 1)`` for per-frame levels).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Sequence

import torch

from resim.diffusion.schedule import alphas_cumprod

if TYPE_CHECKING:
    from resim.diffusion.config import ScheduleConfig

NUM_TRAIN_TIMESTEPS = 1000   # CogVideoX's (ScheduleConfig's default); schedules carry their own N


def cogvideox_alphas_cumprod(schedule: "ScheduleConfig | None" = None) -> torch.Tensor:
    """ᾱ_t of CogVideoX's schedule, ``(num_train_timesteps,)`` float64, ``ᾱ_0 ≈ 0.9975``, ``ᾱ_{N-1} = 0``.

    The one definition lives with the training objective (``resim.diffusion.schedule.alphas_cumprod``:
    scaled-linear betas → cumprod → SNR shift by 3 → zero-terminal-SNR rescale); sampling must use exactly
    the schedule the model was trained with, so pass the model's ``objective.schedule`` where it has one.
    """
    return alphas_cumprod(schedule)


def ddim_timesteps(num_steps: int, num_train_timesteps: int = NUM_TRAIN_TIMESTEPS) -> list[int]:
    """Trailing spacing: ``round(arange(N_train, 0, -N_train/num_steps)) - 1``; 50 of 1000 → [999, 979, …, 19],
    50 of 500 → [499, 489, …, 9] (diffusers' ``timestep_spacing="trailing"``)."""
    if not 1 <= num_steps <= num_train_timesteps:
        raise ValueError(f"num_steps must be in [1, {num_train_timesteps}], got {num_steps}")
    ratio = num_train_timesteps / num_steps
    ts = [int(round(num_train_timesteps - i * ratio)) - 1 for i in range(num_steps)]
    # float rounding can never make two trailing steps equal for num_steps <= N_train, but check: a repeated
    # timestep would make a DDIM step with a_prev == a_t, silently doing nothing.
    if len(set(ts)) != len(ts):  # our bug if it happens
        raise AssertionError(f"duplicate DDIM timesteps for num_steps={num_steps}: {ts}")
    return ts


@dataclass(frozen=True)
class DDIMStep:
    """One step of the sampling loop: denoise from level ``t`` to ``t_prev`` (``-1`` = clean, ᾱ = 1)."""
    index: int
    t: int
    t_prev: int
    a_t: float
    a_prev: float


class DDIMSchedule:
    """The steps of a ``num_steps`` DDIM run over ``alphas_cumprod`` (default: CogVideoX's).

    Iterating yields :class:`DDIMStep` from the noisiest (``t = N - 1``) to the last (``t_prev = -1``), with
    ``N = len(alphas_cumprod)``. ``include``: further levels to stop at (``num_steps`` then counts them too).
    """

    def __init__(self, num_steps: int, alphas_cumprod: torch.Tensor | None = None, include: Sequence[int] = ()):
        self.alphas_cumprod = (cogvideox_alphas_cumprod() if alphas_cumprod is None
                               else alphas_cumprod.to(torch.float64).cpu())
        self.num_train_timesteps = int(self.alphas_cumprod.shape[0])
        ts = ddim_timesteps(num_steps, self.num_train_timesteps)
        bad = [t for t in include if not 0 <= int(t) < self.num_train_timesteps]
        if bad:
            raise ValueError(f"levels to include {bad} not in [0, {self.num_train_timesteps})")
        # ``include``: levels the run must also stop at (distillation records the teacher's trajectory at the
        # student's levels, resim/train/tasks/distill.py); DDIM's update holds for any decreasing sequence of levels
        self.timesteps = sorted(set(ts) | {int(t) for t in include}, reverse=True)
        self.num_steps = len(self.timesteps)
        prevs = self.timesteps[1:] + [-1]
        self.steps = [
            DDIMStep(i, t, tp, float(self.alphas_cumprod[t]), 1.0 if tp < 0 else float(self.alphas_cumprod[tp]))
            for i, (t, tp) in enumerate(zip(self.timesteps, prevs))
        ]

    def __iter__(self):
        return iter(self.steps)

    def __len__(self) -> int:
        return len(self.steps)

    def alpha(self, t: int | torch.Tensor) -> torch.Tensor:
        """ᾱ at integer level(s) ``t`` (float64)."""
        return self.alphas_cumprod[torch.as_tensor(t, dtype=torch.long)]


def _f(a, like: torch.Tensor) -> torch.Tensor:
    return torch.as_tensor(a, dtype=torch.float64, device=like.device)


def v_to_x0_eps(x_t: torch.Tensor, v: torch.Tensor, a_t, float64: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Clean estimate and noise from a v-prediction at ``alpha_bar = a_t`` (a number or a tensor broadcasting to
    ``x_t``): ``x0 = sqrt(a) x_t - sqrt(1-a) v``, ``eps = sqrt(a) v + sqrt(1-a) x_t``. Computed in float64;
    returned in ``x_t``'s dtype, or in float64 with ``float64=True`` (for the next step's arithmetic). The one
    v-prediction conversion of the code base."""
    a = _f(a_t, x_t)
    x, vv = x_t.double(), v.double()
    x0 = a.sqrt() * x - (1 - a).sqrt() * vv
    eps = a.sqrt() * vv + (1 - a).sqrt() * x
    return (x0, eps) if float64 else (x0.to(x_t.dtype), eps.to(x_t.dtype))


def ddim_step(x_t: torch.Tensor, v: torch.Tensor, a_t, a_prev) -> tuple[torch.Tensor, torch.Tensor]:
    """One deterministic DDIM step with a v-prediction → ``(x_prev, x0_pred)``, both in ``x_t``'s dtype.

    ``x_prev = sqrt(a_prev) x0 + sqrt(1 - a_prev) eps`` (DDIM eq. 12 with σ = 0).
    """
    ap = _f(a_prev, x_t)
    x0, eps = v_to_x0_eps(x_t, v, a_t, float64=True)
    x_prev = ap.sqrt() * x0 + (1 - ap).sqrt() * eps
    return x_prev.to(x_t.dtype), x0.to(x_t.dtype)


def forward_noise(x0: torch.Tensor, noise: torch.Tensor, a_t) -> torch.Tensor:
    """Forward process ``sqrt(a) x0 + sqrt(1-a) noise`` (used to noise history frames to a small level)."""
    a = _f(a_t, x0)
    return (a.sqrt() * x0.double() + (1 - a).sqrt() * noise.double()).to(x0.dtype)
