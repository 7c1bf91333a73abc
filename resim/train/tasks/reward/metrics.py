"""Held-out metrics for Video2Reward: MAE, Spearman rank correlation, hazard-vs-clean AUC.

Pure numpy (tested against scipy and brute force in tests/reward/test_metrics.py).
"""
from __future__ import annotations

import numpy as np


def mae(pred, true) -> float:
    pred, true = np.asarray(pred, np.float64), np.asarray(true, np.float64)
    if pred.shape != true.shape or pred.size == 0:
        raise ValueError(f"mae needs two non-empty arrays of one shape, got {pred.shape} and {true.shape}")
    return float(np.abs(pred - true).mean())


def rankdata(x) -> np.ndarray:
    """Average ranks (1-based), ties share the mean rank (scipy.stats.rankdata 'average')."""
    x = np.asarray(x, np.float64)
    order = np.argsort(x, kind="mergesort")
    ranks = np.empty(len(x), np.float64)
    xs = x[order]
    i = 0
    while i < len(x):
        j = i
        while j + 1 < len(x) and xs[j + 1] == xs[i]:
            j += 1
        ranks[order[i:j + 1]] = (i + j) / 2.0 + 1.0
        i = j + 1
    return ranks


def spearman(pred, true) -> float:
    """Spearman's rho = Pearson correlation of average ranks.

    nan (undefined, not an error) when either side is constant or there are fewer than 2 items: a held-out
    split of one clip is a legitimate, if useless, outcome of a small dataset, and the run that produced it
    must still write its checkpoint (docs/reward.md). Arrays of different shapes are a caller bug and raise.
    """
    pred, true = np.asarray(pred, np.float64), np.asarray(true, np.float64)
    if pred.shape != true.shape:
        raise ValueError(f"spearman needs two arrays of one shape, got {pred.shape}, {true.shape}")
    if pred.size < 2:
        return float("nan")
    a, b = rankdata(pred), rankdata(true)
    a, b = a - a.mean(), b - b.mean()
    den = np.sqrt((a * a).sum() * (b * b).sum())
    return float((a * b).sum() / den) if den > 0 else float("nan")


def auc(scores, positive) -> float:
    """ROC AUC of ``scores`` for labels ``positive`` (bool): P(score_pos > score_neg) + 0.5 P(tie).

    Mann-Whitney U / (n_pos * n_neg). For hazard detection pass ``scores = -predicted_score``
    (a low predicted infraction score means hazardous).
    """
    s = np.asarray(scores, np.float64)
    y = np.asarray(positive, bool)
    n_pos, n_neg = int(y.sum()), int((~y).sum())
    if s.shape != y.shape or n_pos == 0 or n_neg == 0:
        raise ValueError(f"auc needs both classes present (got {n_pos} positive, {n_neg} negative)")
    r = rankdata(s)
    u = r[y].sum() - n_pos * (n_pos + 1) / 2.0
    return float(u / (n_pos * n_neg))


def reward_metrics(pred, true, hazard) -> dict[str, float]:
    """{"mae", "spearman", "hazard_auc", "n", "n_hazard"} for predicted vs true infraction scores.

    Spearman is nan for fewer than 2 clips (or a constant side), hazard AUC nan unless both classes are
    present; JSON writers turn nan into null (resim.models.reward.checkpoint.json_safe)."""
    pred, true, hazard = np.asarray(pred), np.asarray(true), np.asarray(hazard, bool)
    out = {"n": int(len(pred)), "n_hazard": int(hazard.sum()), "mae": mae(pred, true),
           "spearman": spearman(pred, true)}
    out["hazard_auc"] = auc(-pred, hazard) if 0 < hazard.sum() < len(hazard) else float("nan")
    return out
