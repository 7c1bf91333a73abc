"""Training and held-out evaluation of Video2Reward.

``train_reward`` = split by episode -> (optionally) stored features -> fit -> predict held-out
-> metrics (MAE, Spearman, hazard AUC) -> checkpoint + predictions + plot.

``fit`` runs the common ``resim.train.trainer.Trainer`` over ``model.loss(batch)``
(ReSim B.2: AdamW, lr 1e-3), one pass over the training clips per epoch. The split,
the epoch batches, the trainer run and the batched prediction are the small-model
harness's (``resim.train.smallfit``, shared with the IDM); what is the reward's own:
its stratified split, its batches (``data.collate``), its optimiser and its metrics.
"""
from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from resim.config import from_dict, to_dict
from resim.models.reward.checkpoint import save_checkpoint, write_json
from resim.models.reward.config import RewardModelConfig
from resim.train.tasks.reward.config import RewardTrainConfig
from resim.models.reward.model import Video2Reward
from resim.shards.split import DatasetSplit
from resim.train import smallfit
from resim.train.config import OptimConfig, RunConfig
from resim.train.tasks.reward.data import ClipError, RewardClip, collate, window_indices
from resim.train.tasks.reward.features import add_clip_features
from resim.train.tasks.reward.metrics import reward_metrics


def can_use_features(model: Video2Reward, clips: Sequence[RewardClip]) -> bool:
    return model.cfg.freeze_backbone and bool(clips) and all(
        c.dino is not None and c.dino_id == model.feature_id for c in clips)


def usable_clips(clips: Sequence[RewardClip], cfg: RewardTrainConfig) -> tuple[list[RewardClip], list[dict]]:
    """(clips the model can use, [{"key", "reason"}] of the others): bad clips (shorter than the window,
    unreadable frames) are reported and left out, the run goes on (bad input is named, never fatal)."""
    def check(c: RewardClip) -> None:
        if c.dino is None or not c.dino_id:  # a featurised clip was cut from its window already: not decoded
            window_indices(len(c.clip_frames()), cfg.model, cfg.data.clip_window)

    return smallfit.usable(clips, check, ClipError)


def build_reward(model_cfg: dict, *, device="cpu") -> Video2Reward:
    """Registry builder (``resim.models.registry``: "reward"): a Video2Reward from its config mapping."""
    return Video2Reward(from_dict(RewardModelConfig, model_cfg, prefix="model")).to(device)


def epoch_batches(clips: Sequence[RewardClip], cfg: RewardTrainConfig, use_features: bool) -> smallfit.EpochBatches:
    """Re-iterable batches over fixed clips for ``Trainer.fit``: each ``iter()`` is one epoch, shuffled with
    seed ``cfg.seed * 1000 + epoch``."""
    return smallfit.EpochBatches(clips, cfg.batch_size_per_gpu, cfg.seed,
                                 lambda cs: collate(cs, cfg.model, use_features, cfg.data.clip_window))


def run_config(cfg: RewardTrainConfig, steps: int, progress: bool = False) -> RunConfig:
    """The common trainer's RunConfig for a reward run (AdamW at cfg.optim, constant LR, fp32)."""
    return smallfit.run_config(
        "reward", to_dict(cfg.model), steps=steps, batch_size=cfg.batch_size_per_gpu, seed=cfg.seed,
        optim=cfg.optim.for_steps(steps),
        save_final_weights=False, preset="reward", progress=progress, load_frames=True, load_dino=True,
        reference={"resim_b2": "AdamW, lr 1e-3, 20 epochs, 35K CARLA samples, 224x224"})


def fit(model: Video2Reward, clips: Sequence[RewardClip], cfg: RewardTrainConfig, use_features: bool,
        run_dir: str | Path, progress: bool = False) -> dict:
    """Train ``model`` in place through the common ``resim.train.trainer.Trainer`` for ``cfg.epochs``
    epochs over ``clips``; returns ``resim.train.smallfit.fit``'s summary ("steps", "samples_per_s",
    "history": the per-step rows of RUN_DIR/metrics.jsonl, ...)."""
    return smallfit.fit(model, epoch_batches(clips, cfg, use_features), cfg.epochs,
                        lambda steps: run_config(cfg, steps, progress), run_dir)


def predict(model: Video2Reward, clips: Sequence[RewardClip], use_features: bool, batch_size: int = 32,
            where: str = "end") -> np.ndarray:
    """(N,) predicted infraction scores of ``clips``, in their order."""
    forward = (lambda m, b: m(features=b["dino"])) if use_features else (lambda m, b: m(video=b["video"]))
    return smallfit.predict(model, clips, lambda cs: collate(cs, model.cfg, use_features, where), forward,
                            batch_size)


class SplitError(ValueError):
    """The labelled clips cannot be split into train and held-out episodes (says why)."""


@dataclass
class PreparedRun:
    """What :func:`prepare_training` checked and built before any training step."""

    train: list[RewardClip]
    held: list[RewardClip]
    skipped: list[dict]
    model: Video2Reward
    notes: list[str]        # held-out metrics that will be undefined (nan), said before training
    split: DatasetSplit     # the dataset's, which decided the two sides


def prepare_training(clips: Sequence[RewardClip], cfg: RewardTrainConfig, split: DatasetSplit) -> PreparedRun:
    """Everything of a run that can fail on bad input, done before training: the model (its backbone
    folder), usable clips, their sides of the dataset's ``split`` (``resim.shards.split``: by episode, stratified
    by source and hazard). Raises :class:`SplitError` (no held-out or no training
    episode), ``resim.models.reward.backbone.BackboneError`` (backbone folder)."""
    # the model first: a bad backbone folder is a config error whatever the data
    torch.manual_seed(cfg.seed)
    model = Video2Reward(cfg.model)
    clips, skipped = usable_clips([c for c in clips if c.infraction_score is not None], cfg)
    try:
        train, held = smallfit.split_clips(clips, split, f"labelled clip ({len(clips)} usable)")
    except ValueError as e:
        raise SplitError(str(e)) from None
    notes = []
    if len(held) < 2:
        notes.append(f"the held-out set has {len(held)} clip: Spearman is undefined (nan); "
                     "more labelled episodes give a meaningful evaluation")
    if len({bool(c.hazard) for c in held}) < 2:
        notes.append("the held-out set holds only " + ("hazardous" if held[0].hazard else "clean")
                     + " episodes: hazard AUC is undefined (nan)")
    return PreparedRun(train, held, skipped, model, notes, split)


def train_reward(clips: Sequence[RewardClip], cfg: RewardTrainConfig, split: DatasetSplit,
                 out_dir: str | Path | None = None, progress: bool = False, prepared: PreparedRun | None = None) -> dict:
    """Split by the dataset's ``split``, train, evaluate on held-out episodes; write outputs when ``out_dir`` is
    given.

    ``prepared``: the result of :func:`prepare_training` on the same clips, config and split (callers that check
    the input first, e.g. the CLI, pass it on instead of repeating the work).

    Returns {"metrics": held-out metrics, "train_metrics", "history", "used_features", "n_train",
    "n_heldout", "heldout_items", "model", "notes"}. Metrics undefined on the held-out set (Spearman of
    one clip, AUC of one class) are nan, listed in "notes", and null in meta.json.
    """
    if prepared is None:
        prepared = prepare_training(clips, cfg, split)
    train, held, skipped, model = prepared.train, prepared.held, prepared.skipped, prepared.model
    use_features = False
    if cfg.use_stored_features and cfg.model.freeze_backbone:
        if not can_use_features(model, train + held):
            train, held = add_clip_features(model, train, cfg.data.clip_window), \
                add_clip_features(model, held, cfg.data.clip_window)
        use_features = True
    with tempfile.TemporaryDirectory(prefix="resim-reward-") as tmp:
        run_dir = Path(out_dir) / "trainer" if out_dir is not None else Path(tmp)
        fitted = fit(model, train, cfg, use_features, run_dir, progress)
    history = fitted["history"]
    pred_h = predict(model, held, use_features, where=cfg.data.clip_window)
    pred_t = predict(model, train, use_features, where=cfg.data.clip_window)
    true_h = np.array([c.infraction_score for c in held])
    haz_h = np.array([c.hazard for c in held])
    metrics = reward_metrics(pred_h, true_h, haz_h)
    train_metrics = reward_metrics(pred_t, np.array([c.infraction_score for c in train]),
                                   np.array([c.hazard for c in train]))
    result = {"metrics": metrics, "train_metrics": train_metrics, "history": history, "samples_per_s": fitted["samples_per_s"],
              "used_features": use_features, "n_train": len(train), "n_heldout": len(held),
              "heldout_items": sorted({c.item_id for c in held}), "split": split.record("heldout"), "model": model,
              "skipped": skipped, "heldout_pred": pred_h, "heldout_true": true_h, "heldout_hazard": haz_h,
              "notes": list(prepared.notes)}
    if out_dir is not None:
        out = Path(out_dir)
        save_checkpoint(model, out, cfg, {"heldout_metrics": metrics, "train_metrics": train_metrics,
                                          "heldout_items": result["heldout_items"], "split": result["split"],
                                          "used_stored_features": use_features, "skipped_clips": skipped,
                                          "notes": result["notes"]},
                        run_cfg=run_config(cfg, fitted["steps"]))   # final/config.yaml: the trainer's run config
        write_json([{"key": c.key, "item_id": c.item_id, "true": float(t), "pred": float(p),
                     "hazard": bool(c.hazard)} for c, t, p in zip(held, true_h, pred_h)],
                   out / "heldout_predictions.json", indent=1)
        write_json(history, out / "history.json", indent=1)
        plot_predictions(pred_h, true_h, haz_h, out / "heldout_pred_vs_true.png", metrics)
    return result


def plot_predictions(pred, true, hazard, path: str | Path, metrics: dict | None = None) -> Path:
    # matplotlib is slow to import and only the plot needs it
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pred, true, hazard = np.asarray(pred), np.asarray(true), np.asarray(hazard, bool)
    fig, ax = plt.subplots(figsize=(4.5, 4.2), dpi=110)
    ax.scatter(true[~hazard], pred[~hazard], s=14, alpha=0.7, label="clean episodes")
    ax.scatter(true[hazard], pred[hazard], s=14, alpha=0.7, c="tab:red", label="hazardous episodes")
    lo = min(true.min(), pred.min()) - 0.05
    hi = max(true.max(), pred.max()) + 0.05
    ax.plot([lo, hi], [lo, hi], "k--", lw=0.8)
    ax.set_xlabel("true infraction score")
    ax.set_ylabel("predicted")
    if metrics:
        ax.set_title(f"held-out: MAE {metrics['mae']:.3f}  Spearman {metrics['spearman']:.3f}\n"
                     f"hazard AUC {metrics['hazard_auc']:.3f}  (n={metrics['n']})", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return Path(path)
