"""The harness shared by the small models trained on clips held in memory: Video2Reward (``resim.models.reward``)
and the inverse dynamics model (``resim.train.tasks.idm``).

What the two have in common, and only that, lives here:

* :func:`split_clips`: train / held-out clips by the dataset's own split (``resim.shards.split``);
  :func:`split_by_episode`: a split of the training episodes for early stopping, whole episodes (``item_id``)
  on one side, ordered by a seeded hash of their id, optionally stratified;
* :func:`usable`: clips the model can use, and ``[{"key", "reason"}]`` of the others (named, never fatal);
* :func:`frames_to_tensor`: uint8 RGB frames (numpy) to the float [0, 1] tensors both models take;
* :class:`EpochBatches`: re-iterable shuffled epochs of collated batches for ``Trainer.fit`` (epoch ``e``
  drawn from ``numpy.random.default_rng(seed * 1000 + e)``);
* :func:`run_config` and :func:`fit`: the common ``resim.train.trainer.Trainer`` (checkpoints, exact resume,
  metrics.jsonl, progress bar, loss curve) for a number of epochs, plus the per-step history it logged;
* :func:`predict`: the model over clips in batches, in input order.

What differs stays with each model: its clip type and targets, its window of frames, its loss (``model.loss``),
its optimiser settings, its metrics, and the IDM's mirror augmentation and early stopping.
"""
from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path
from typing import Any, Callable, Hashable, Iterator, Protocol, Sequence, TypeVar

import numpy as np
import torch
from torch import nn

from resim.shards.split import DatasetSplit
from resim.train.config import DataConfig, OptimConfig, RunConfig, TrainerConfig
from resim.train.trainer import Trainer, to_device


class ClipError(ValueError):
    """A clip cannot be used (too short, unreadable frames, bad features); names the clip."""


class EpisodeClip(Protocol):
    key: str
    item_id: str


C = TypeVar("C", bound=EpisodeClip)


# ---- the held-out split ------------------------------------------------------------------------------

def episode_order(episodes: Sequence[str], seed: int) -> list[str]:
    """Distinct ``episodes`` ordered by a seeded hash of their id: the first ones are held out."""
    return sorted(set(episodes), key=lambda e: hashlib.sha256(f"{seed}\0{e}".encode()).hexdigest())


def heldout_count(n_episodes: int, heldout_fraction: float, min_heldout: int = 1) -> int:
    """``round(heldout_fraction * n)`` (half up), at least ``min_heldout`` and 1, at most ``n - 1`` (one trains)."""
    return min(n_episodes - 1, max(1, min_heldout, int(np.floor(heldout_fraction * n_episodes + 0.5))))


def split_by_episode(clips: Sequence[C], heldout_fraction: float, seed: int = 0, *, min_heldout: int = 1,
                     stratum: Callable[[C], Hashable] | None = None) -> tuple[list[C], list[C]]:
    """(train, held-out), each in input order, with whole episodes on one side: overlapping clips of one
    episode on both sides would leak.

    Without ``stratum``: :func:`heldout_count` episodes are held out; fewer than 2 episodes is a ValueError.
    With ``stratum`` (clip -> label; an episode's label is the largest of its clips', so for booleans an
    episode is positive when any clip is): the same count within each stratum of at least 2 episodes;
    smaller strata are held out from not at all, and the caller says so when nothing could be held out.
    """
    if stratum is None:
        eps = episode_order([c.item_id for c in clips], seed)
        if len(eps) < 2:
            raise ValueError(f"{len(clips)} clips from {len(eps)} episode(s): a split by episode needs at least 2")
        held = set(eps[:heldout_count(len(eps), heldout_fraction, min_heldout)])
    else:
        label: dict[str, Any] = {}
        for c in clips:
            s = stratum(c)
            label[c.item_id] = s if c.item_id not in label else max(label[c.item_id], s)
        held = set()
        for s in sorted(set(label.values())):
            eps = episode_order([e for e, v in label.items() if v == s], seed)
            if len(eps) >= 2:
                held.update(eps[:heldout_count(len(eps), heldout_fraction, min_heldout)])
    return [c for c in clips if c.item_id not in held], [c for c in clips if c.item_id in held]


def split_clips(clips: Sequence[C], split: DatasetSplit, what: str) -> tuple[list[C], list[C]]:
    """(train, held-out) clips, each in input order, by the dataset's own split (``resim.shards.split``: whole
    episodes on one side). A ``ValueError`` naming ``what`` and the split when a side is empty."""
    sides = [split.side(c.item_id) for c in clips]
    train = [c for c, s in zip(clips, sides) if s == "train"]
    held = [c for c, s in zip(clips, sides) if s == "heldout"]
    for name, part in (("train", train), ("held-out", held)):
        if not part:
            eps = len({c.item_id for c in clips})
            raise ValueError(f"no {what} of the {eps} episode(s) it can use is on the {name} side of the split "
                             f"({split.origin}); write another split: `resim shards split DIR --heldout-fraction F "
                             f"--min-heldout-episodes N`")
    return train, held


def usable(clips: Sequence[C], check: Callable[[C], Any], errors: type[Exception] | tuple = ClipError
           ) -> tuple[list[C], list[dict]]:
    """(clips ``check`` accepts, ``[{"key", "reason"}]`` of those where it raised one of ``errors``)."""
    ok, skipped = [], []
    for c in clips:
        try:
            check(c)
            ok.append(c)
        except errors as e:
            skipped.append({"key": c.key, "reason": str(e)})
    return ok, skipped


# ---- batches ----------------------------------------------------------------------------------------

def frames_to_tensor(frames: np.ndarray) -> torch.Tensor:
    """(T, H, W, 3) uint8 RGB -> (T, 3, H, W) float32 in [0, 1]."""
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8:
        raise ClipError(f"frames must be (T, H, W, 3) uint8 RGB, got {frames.shape} {frames.dtype}")
    return torch.from_numpy(np.ascontiguousarray(frames)).permute(0, 3, 1, 2).float().div_(255.0)


class EpochBatches:
    """Re-iterable epochs of batches for ``Trainer.fit``: iteration ``e`` (counted from 0) is one epoch over
    ``clips`` in the order ``rng.permutation(n)``, ``rng = numpy.random.default_rng(seed * 1000 + e)``, cut
    into batches of ``batch_size`` and passed to ``collate(clips)``.

    ``augment(rng, n)``: per-clip draws from the same RNG after the permutation (the IDM's mirror flags),
    indexed like the shuffled clips and passed on as ``collate(clips, draws)``. ``on_epoch_end(epoch)`` runs
    after the last batch of every epoch (when the trainer asks for the next one; the very last epoch's is the
    caller's). The trainer checkpoints the position (epoch, batches consumed) and replays it on resume."""

    def __init__(self, clips: Sequence, batch_size: int, seed: int, collate: Callable[..., Any], *,
                 augment: Callable[[np.random.Generator, int], np.ndarray] | None = None,
                 on_epoch_end: Callable[[int], None] | None = None):
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        self.clips, self.batch_size, self.seed, self.collate = list(clips), batch_size, seed, collate
        self.augment, self.on_epoch_end = augment, on_epoch_end
        self.epoch = 0

    def __len__(self) -> int:
        return -(-len(self.clips) // self.batch_size)

    def __iter__(self) -> Iterator:
        rng = np.random.default_rng(self.seed * 1000 + self.epoch)
        order = rng.permutation(len(self.clips))
        draws = self.augment(rng, len(self.clips)) if self.augment is not None else None
        self.epoch += 1
        for i in range(0, len(order), self.batch_size):
            chunk = [self.clips[j] for j in order[i:i + self.batch_size]]
            yield self.collate(chunk) if draws is None else self.collate(chunk, draws[i:i + self.batch_size])
        if self.on_epoch_end is not None:
            self.on_epoch_end(self.epoch)


# ---- training and prediction --------------------------------------------------------------------------

def run_config(model_name: str, model: dict, *, steps: int, batch_size: int, seed: int, optim: OptimConfig,
               save_final_weights: bool, preset: str, reference: dict, progress: bool = False,
               **data_flags: bool) -> RunConfig:
    """The common trainer's RunConfig for a small in-memory run: one process (``parallel="none"``), no
    TensorBoard, a loss-curve PNG, ``steps`` optimiser steps. ``data_flags`` (``load_frames``, ``load_dino``)
    only record what the batches hold."""
    return RunConfig(
        model_name=model_name, model=model,
        data=DataConfig(batch_size_per_gpu=batch_size, seed=seed, **data_flags),
        optim=optim,
        trainer=TrainerConfig(steps=steps, seed=seed, parallel="none", tensorboard=False, progress_bar=progress,
                              loss_curve_png=True, save_final_weights=save_final_weights),
        preset=preset, reference=reference)


def read_history(run_dir: str | Path) -> list[dict]:
    """The per-step rows the trainer logged to ``run_dir/metrics.jsonl`` ([] when there is none)."""
    p = Path(run_dir) / "metrics.jsonl"
    return [json.loads(line) for line in p.read_text().splitlines() if line.strip()] if p.is_file() else []


def fit(model: nn.Module, data: EpochBatches, epochs: int, make_config: Callable[[int], RunConfig],
        run_dir: str | Path) -> dict:
    """Train ``model`` in place through ``resim.train.trainer.Trainer`` for ``epochs`` passes over ``data``
    (``make_config(steps)`` gives the run's config), then put it in eval mode.

    Returns the trainer's summary plus "steps", "seconds" (wall time, set-up and checkpoints included),
    "history" (the metrics.jsonl rows), "samples_per_s" (steady state: the trainer's per-step timings, data +
    forward + backward + step, leaving out step 0, the warm-up, when there are more) and "wall_samples_per_s".
    """
    steps = epochs * len(data)
    t0 = time.perf_counter()
    summary = Trainer(model, make_config(steps), run_dir).fit(data)
    seconds = time.perf_counter() - t0
    model.eval()
    history = read_history(run_dir)
    rows = history[1:] if len(history) > 1 else history
    t = sum(r["step_time_s"] for r in rows)
    sps = sum(r["samples_per_s"] * r["step_time_s"] for r in rows) / t if t > 0 else float("nan")
    return {**summary, "steps": steps, "seconds": seconds, "history": history, "samples_per_s": sps,
            "wall_samples_per_s": epochs * len(data.clips) / seconds}


@torch.no_grad()
def predict(model: nn.Module, clips: Sequence, collate: Callable[[list], Any],
            forward: Callable[[nn.Module, Any], torch.Tensor], batch_size: int = 32,
            empty_shape: tuple[int, ...] = ()) -> np.ndarray:
    """``forward(model, collate(batch))`` over ``clips`` in batches of ``batch_size``, in input order, in eval
    mode on the model's device; the outputs concatenated on the CPU as numpy (``(0, *empty_shape)`` float32
    for no clips)."""
    model.eval()
    dev = next(model.parameters()).device
    out = [forward(model, to_device(collate(list(clips[i:i + batch_size])), dev)).cpu()
           for i in range(0, len(clips), batch_size)]
    return torch.cat(out).numpy() if out else np.zeros((0, *empty_shape), np.float32)
