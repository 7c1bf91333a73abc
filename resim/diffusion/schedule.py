"""CogVideoX's noise schedule and the v-parameterisation, as pure functions.

``alphas_cumprod`` reproduces ``diffusers.CogVideoXDDIMScheduler(beta_schedule="scaled_linear",
rescale_betas_zero_snr=True, snr_shift_scale=3.0).alphas_cumprod`` (THUDM/CogVideoX-2b's scheduler config):

1. scaled-linear betas: ``β_i = (√β_start + i/(N-1)·(√β_end − √β_start))²`` in float64;
2. ``ᾱ = cumprod(1 − β)``;
3. SNR shift (CogVideoX): ``ᾱ ← ᾱ / (s + (1 − s) ᾱ)`` with s = 3, i.e. SNR divided by s;
4. zero-terminal-SNR rescale (Lin et al. 2024, Alg. 1) of ``√ᾱ``: shift so the last is 0, scale so the
   first is unchanged.

Noising: ``x_t = √ᾱ_t x0 + √(1−ᾱ_t) ε``; v-target: ``v = √ᾱ_t ε − √(1−ᾱ_t) x0``; hence
``x0 = √ᾱ_t x_t − √(1−ᾱ_t) v`` and ``ε = √(1−ᾱ_t) x_t + √ᾱ_t v``. ``t`` may be per frame: for video
``(B, T, C, h, w)`` pass ``t`` of shape ``(B, T)`` (or ``(B,)``): coefficients broadcast over trailing dims.
"""
from __future__ import annotations

import torch

from resim.diffusion.config import ScheduleConfig


def scaled_linear_betas(num_steps: int, beta_start: float, beta_end: float) -> torch.Tensor:
    """``(num_steps,)`` float64."""
    return torch.linspace(beta_start ** 0.5, beta_end ** 0.5, num_steps, dtype=torch.float64) ** 2


def rescale_zero_terminal_snr(alphas_cumprod: torch.Tensor) -> torch.Tensor:
    """Lin et al. (2024) Alg. 1 on ``√ᾱ``: last value → 0, first unchanged, affine in between."""
    s = alphas_cumprod.sqrt()
    s0, sT = s[0].clone(), s[-1].clone()
    s = (s - sT) * (s0 / (s0 - sT))
    return s ** 2


def alphas_cumprod(cfg: ScheduleConfig | None = None) -> torch.Tensor:
    """``ᾱ`` of CogVideoX's training schedule, ``(num_train_timesteps,)`` float64 (see module docstring)."""
    cfg = cfg or ScheduleConfig()
    ac = torch.cumprod(1.0 - scaled_linear_betas(cfg.num_train_timesteps, cfg.beta_start, cfg.beta_end), dim=0)
    ac = ac / (cfg.snr_shift_scale + (1 - cfg.snr_shift_scale) * ac)
    if cfg.rescale_zero_terminal_snr:
        ac = rescale_zero_terminal_snr(ac)
    return ac


def _coef(ac: torch.Tensor, t: torch.Tensor, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """√ᾱ_t, √(1−ᾱ_t) gathered at integer ``t`` and shaped to broadcast against ``like`` (float64 → like.dtype)."""
    t = torch.as_tensor(t, device=ac.device).long()
    if t.numel() and (t.min() < 0 or t.max() >= len(ac)):
        raise ValueError(f"noise levels must be in [0, {len(ac) - 1}], got [{int(t.min())}, {int(t.max())}]")
    a = ac[t]
    a = a.reshape(*a.shape, *([1] * (like.dim() - a.dim()))).to(like.device)
    return a.sqrt().to(like.dtype), (1 - a).sqrt().to(like.dtype)


def add_noise(x0: torch.Tensor, noise: torch.Tensor, t: torch.Tensor, ac: torch.Tensor) -> torch.Tensor:
    sa, s1a = _coef(ac, t, x0)
    return sa * x0 + s1a * noise


def v_target(x0: torch.Tensor, noise: torch.Tensor, t: torch.Tensor, ac: torch.Tensor) -> torch.Tensor:
    sa, s1a = _coef(ac, t, x0)
    return sa * noise - s1a * x0


