"""Per-frame fidelity metrics: PSNR and SSIM on (generated, ground truth) video pairs.

Inputs are videos ``(B, T, C, H, W)``; the caller states the value range explicitly
(``value_range="uint8"`` for 0..255 integers, ``"unit"`` for floats in [0, 1]) because
guessing it from the data is how evaluations silently go wrong.

SSIM follows Wang et al. (2004) as scikit-image implements it with
``gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1``:
an 11x11 Gaussian window (sigma 1.5, truncated at 3.5 sigma), K1 = 0.01, K2 = 0.03,
the SSIM map averaged over the *valid* region (scikit-image crops (11-1)/2 = 5 px at
each border) and over channels. PSNR is ``10 log10(1 / MSE)`` on [0, 1] values, capped at
``PSNR_CAP_DB`` when the frames are identical (MSE = 0), so means stay finite.
"""
from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F

ValueRange = Literal["uint8", "unit"]
PSNR_CAP_DB = 100.0
SSIM_SIGMA = 1.5
SSIM_TRUNCATE = 3.5
SSIM_K1, SSIM_K2 = 0.01, 0.03


def to_unit(video: torch.Tensor, value_range: ValueRange) -> torch.Tensor:
    """Video ``(B, T, C, H, W)`` in the stated range → float64 in [0, 1]."""
    if video.ndim != 5:
        raise ValueError(f"expected a video (B, T, C, H, W), got shape {tuple(video.shape)}")
    if value_range == "uint8":
        if video.is_floating_point():
            raise ValueError("value_range='uint8' but the video is floating point")
        return video.to(torch.float64) / 255.0
    if value_range == "unit":
        if not video.is_floating_point():
            raise ValueError("value_range='unit' but the video is integer; pass value_range='uint8'")
        lo, hi = float(video.min()), float(video.max())
        if lo < -1e-6 or hi > 1 + 1e-6:
            raise ValueError(f"value_range='unit' but values span [{lo:.3g}, {hi:.3g}]")
        return video.to(torch.float64)
    raise ValueError(f"value_range must be 'uint8' or 'unit', got {value_range!r}")


def _check_pair(gen: torch.Tensor, ref: torch.Tensor) -> None:
    if gen.shape != ref.shape:
        raise ValueError(f"generated {tuple(gen.shape)} and reference {tuple(ref.shape)} differ in shape")


def psnr(gen: torch.Tensor, ref: torch.Tensor, value_range: ValueRange, cap_db: float = PSNR_CAP_DB) -> torch.Tensor:
    """Per-frame PSNR in dB, ``(B, T)`` float64; identical frames give ``cap_db``."""
    _check_pair(gen, ref)
    g, r = to_unit(gen, value_range), to_unit(ref, value_range)
    mse = (g - r).pow(2).flatten(2).mean(-1)  # (B, T)
    out = 10.0 * torch.log10(1.0 / mse.clamp_min(1e-300))
    return out.clamp(max=cap_db)


def gaussian_window_1d(sigma: float = SSIM_SIGMA, truncate: float = SSIM_TRUNCATE) -> torch.Tensor:
    """The normalised 1-D Gaussian scipy.ndimage uses: radius int(truncate*sigma + 0.5) (11 taps for 1.5)."""
    radius = int(truncate * sigma + 0.5)
    x = torch.arange(-radius, radius + 1, dtype=torch.float64)
    w = torch.exp(-0.5 * (x / sigma) ** 2)
    return w / w.sum()


def ssim(gen: torch.Tensor, ref: torch.Tensor, value_range: ValueRange) -> torch.Tensor:
    """Per-frame SSIM, ``(B, T)`` float64 (Gaussian 11x11, sigma 1.5, valid region, channel mean)."""
    _check_pair(gen, ref)
    g, r = to_unit(gen, value_range), to_unit(ref, value_range)
    b, t, c, h, w = g.shape
    win = gaussian_window_1d().to(g.device)
    k = win.numel()
    if h < k or w < k:
        raise ValueError(f"frames of {h}x{w} are smaller than the {k}x{k} SSIM window")
    x = g.reshape(b * t * c, 1, h, w)  # (N, 1, H, W), one channel per row
    y = r.reshape(b * t * c, 1, h, w)

    def filt(z: torch.Tensor) -> torch.Tensor:  # separable 'valid' Gaussian filter
        z = F.conv2d(z, win.view(1, 1, k, 1))
        return F.conv2d(z, win.view(1, 1, 1, k))

    ux, uy = filt(x), filt(y)
    vx = filt(x * x) - ux * ux
    vy = filt(y * y) - uy * uy
    vxy = filt(x * y) - ux * uy
    c1, c2 = SSIM_K1**2, SSIM_K2**2  # data range 1
    s = ((2 * ux * uy + c1) * (2 * vxy + c2)) / ((ux * ux + uy * uy + c1) * (vx + vy + c2))
    per_channel = s.flatten(1).mean(-1)  # (B*T*C,)
    return per_channel.view(b, t, c).mean(-1)


def psnr_summary(values: torch.Tensor) -> dict:
    """Mean/std of per-frame PSNR with the cap stated (inf never enters a mean)."""
    v = values.flatten().double()
    return {"mean_db": float(v.mean()), "std_db": float(v.std()) if v.numel() > 1 else 0.0,
            "frames": int(v.numel()), "cap_db": PSNR_CAP_DB,
            "capped_frames": int((v >= PSNR_CAP_DB - 1e-9).sum())}
