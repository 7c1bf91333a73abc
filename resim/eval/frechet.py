"""Streaming Gaussian feature statistics and the Fréchet distance (FID, FVD).

FID/FVD compare the Gaussian fit (mean, covariance) of network features of generated
samples with that of real samples:

    d^2 = |mu_1 - mu_2|^2 + tr(S_1 + S_2 - 2 (S_1 S_2)^{1/2})

Features are accumulated as float64 sums so thousands of clips never sit in memory.
The matrix square-root term is computed from the eigenvalues of
``sqrt(S_1) S_2 sqrt(S_1)`` (symmetric PSD, so ``eigh`` is stable), which equals
``tr((S_1 S_2)^{1/2})``; tests check it against scipy's ``sqrtm`` in float64.

Estimates from few samples are biased upwards; ``MIN_SAMPLES_UNBIASED`` (1,000) is the
threshold below which a warning is raised (a score from fewer samples is not comparable to published ones).
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch

MIN_SAMPLES_UNBIASED = 1000


class FeatureStats:
    """Running sum and sum of outer products of feature vectors, in float64."""

    def __init__(self, dim: int):
        self.dim = dim
        self.n = 0
        self.sum = torch.zeros(dim, dtype=torch.float64)
        self.sum_outer = torch.zeros(dim, dim, dtype=torch.float64)

    def update(self, features: torch.Tensor) -> None:
        """Add features ``(N, dim)``."""
        if features.ndim != 2 or features.shape[1] != self.dim:
            raise ValueError(f"expected features (N, {self.dim}), got {tuple(features.shape)}")
        f = features.detach().to("cpu", torch.float64)
        self.n += f.shape[0]
        self.sum += f.sum(0)
        self.sum_outer += f.T @ f

    def merge(self, other: "FeatureStats") -> None:
        """Add another accumulator's statistics (e.g. from another rank)."""
        if other.dim != self.dim:
            raise ValueError("feature dimensions differ")
        self.n += other.n
        self.sum += other.sum
        self.sum_outer += other.sum_outer

    def mean_cov(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean ``(dim,)`` and unbiased covariance ``(dim, dim)`` (needs n >= 2)."""
        if self.n < 2:
            raise ValueError(f"need at least 2 samples for a covariance, have {self.n}")
        mu = self.sum / self.n
        cov = (self.sum_outer - self.n * torch.outer(mu, mu)) / (self.n - 1)
        return mu, cov


def _sqrtm_psd(a: torch.Tensor) -> torch.Tensor:
    vals, vecs = torch.linalg.eigh((a + a.T) / 2)
    return (vecs * vals.clamp_min(0).sqrt()) @ vecs.T


def frechet_distance(mu1: torch.Tensor, cov1: torch.Tensor, mu2: torch.Tensor, cov2: torch.Tensor) -> float:
    """Fréchet distance between N(mu1, cov1) and N(mu2, cov2), computed in float64."""
    mu1, mu2 = mu1.double(), mu2.double()
    cov1, cov2 = cov1.double(), cov2.double()
    s1 = _sqrtm_psd(cov1)
    m = s1 @ cov2 @ s1
    tr_sqrt = torch.linalg.eigvalsh((m + m.T) / 2).clamp_min(0).sqrt().sum()
    d2 = (mu1 - mu2).pow(2).sum() + torch.trace(cov1) + torch.trace(cov2) - 2 * tr_sqrt
    return float(d2.clamp_min(0))


@dataclass
class FrechetResult:
    value: float
    n_generated: int
    n_reference: int
    feature_dim: int
    biased_warning: bool


def frechet_from_stats(gen: FeatureStats, ref: FeatureStats, name: str = "FID") -> FrechetResult:
    """Fréchet distance of two accumulators; warns when either has < 1,000 samples."""
    n_min = min(gen.n, ref.n)
    biased = n_min < MIN_SAMPLES_UNBIASED
    if biased:
        warnings.warn(
            f"{name} from {gen.n} generated / {ref.n} reference samples: below {MIN_SAMPLES_UNBIASED} "
            "the estimate is biased upwards and not comparable with published numbers",
            stacklevel=2,
        )
    mu1, c1 = gen.mean_cov()
    mu2, c2 = ref.mean_cov()
    return FrechetResult(frechet_distance(mu1, c1, mu2, c2), gen.n, ref.n, gen.dim, biased)
