"""How much of a turn survives a transformation of the video: the **heading kept** statistic, with bootstrap
intervals over clips.

Used where a heading read off processed video (a VAE's reconstruction, a model's one-step prediction) is compared
with the heading of a reference (the original, the recorded future through the VAE): ``resim eval vae`` and
``resim eval detail``. The heading kept is the least-squares slope, through the origin, of the processed headings on
the reference headings over the clips: 1 when the turns survive whole, 0 when they are gone. It weighs each clip by
its reference heading squared, so clips driving straight barely count. Intervals are percentile bootstraps over
clips; a paired difference resamples the same clips for both readings, so what the clips share cancels.
"""
from __future__ import annotations

import numpy as np


def slope(pred: np.ndarray, ref: np.ndarray, idx: np.ndarray) -> float:
    """Least-squares slope through the origin of ``pred[idx]`` on ``ref[idx]``; NaN where those ``ref`` are all 0."""
    den = float(np.sum(ref[idx] ** 2))
    return float(np.sum(pred[idx] * ref[idx]) / den) if den > 0 else float("nan")


def interval(boot: np.ndarray) -> list[float]:
    """The 2.5 / 97.5 percentiles of the finite bootstrap values (NaN, NaN when none is finite)."""
    boot = boot[np.isfinite(boot)]
    return [float(v) for v in np.percentile(boot, [2.5, 97.5])] if boot.size else [float("nan"), float("nan")]


def _check(*arrays: np.ndarray) -> None:
    if any(a.ndim != 1 or a.shape != arrays[0].shape for a in arrays):
        raise ValueError(f"headings must be 1-D of one length, got {[a.shape for a in arrays]}")


def kept_slope(pred, ref, n_boot: int = 2000, seed: int = 0) -> dict:
    """Slope through the origin of ``pred`` on ``ref`` (headings in degrees, one per clip) with a 95 % bootstrap
    interval over clips; NaN where the references are all zero (nothing to keep)."""
    p, r = np.asarray(pred, np.float64), np.asarray(ref, np.float64)
    _check(p, r)
    est = slope(p, r, np.arange(len(r)))
    rng = np.random.default_rng(seed)
    boot = np.array([slope(p, r, rng.integers(0, len(r), len(r))) for _ in range(n_boot)]) if len(r) > 1 \
        else np.array([est])
    return {"slope": est, "ci95": interval(boot)}


def paired_slope_difference(mine, other, ref, n_boot: int = 2000, seed: int = 0) -> dict:
    """Heading kept of ``mine`` minus that of ``other``, both read against the same ``ref`` on the same clips, with
    a 95 % paired bootstrap interval (each resample takes the same clips from both)."""
    m, o, r = (np.asarray(a, np.float64) for a in (mine, other, ref))
    _check(m, o, r)
    rng = np.random.default_rng(seed)
    every = np.arange(len(r))
    boot = np.array([slope(m, r, i) - slope(o, r, i) for i in (rng.integers(0, len(r), len(r)) for _ in range(n_boot))])
    return {"difference": slope(m, r, every) - slope(o, r, every), "ci95": interval(boot)}


def paired_mean_difference(mine, other, n_boot: int = 2000, seed: int = 0) -> dict:
    """Mean of ``mine − other`` (one value per clip: a PSNR, a 0/1 correct label) with a 95 % paired bootstrap
    interval over clips."""
    d = np.asarray(mine, np.float64) - np.asarray(other, np.float64)
    _check(d)
    rng = np.random.default_rng(seed)
    boot = np.array([d[rng.integers(0, len(d), len(d))].mean() for _ in range(n_boot)])
    return {"difference": float(d.mean()), "ci95": interval(boot)}
