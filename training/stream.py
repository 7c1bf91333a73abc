"""The deterministic, resumable shard stream behind ``training.data.StreamLoader``.

Why not a plain ``wds.WebDataset(resampled=True).shuffle(n)``: exact resume needs the position
in the stream to be small, saveable state, and the WebDataset maintainers' recipe for equal
batch counts under DDP (resampled shards + a fixed epoch length) leaves the shard RNG and the
shuffle buffer inside worker processes. Here every choice is a pure function of
``(seed, epoch, rank, worker, index)``:

* shard draw ``k`` of a worker: ``default_rng([seed, epoch, rank, worker, k, 1]).choice(shards, p=mix)``
  (with replacement, so any number of shards serves any number of ranks x workers: no hang,
  no idle worker, equal batch counts);
* raw sample ``i`` of a worker is taken from slot ``default_rng([seed, epoch, rank, worker, i, 2])
  .integers(S)``: each worker interleaves ``S`` open shards (``data.open_shards_per_worker``),
  which shuffles across shards without a buffer;
* a slot's shard is read front to back; when it ends the slot takes the next draw.

The position of a worker (``Cursor``) is: draws made, raw samples taken, and per slot (draw
index, shard index, samples read). Resuming reopens each slot's shard and skips the samples read
(raw tar records, not decoded). Reading uses WebDataset's ``gopen`` (local paths and any URL it
opens) and its tar iterator / key grouping; decoding uses ``shards.reader.decode_sample``.

Bad data: a sample that fails to decode or validate is skipped and counted; a shard that cannot
be opened or read (or holds a forbidden member) is dropped for that draw and counted; both are
reported on stderr. ``strict`` turns either into a ``DataError`` naming the shard (and key).
"""
from __future__ import annotations

import dataclasses
import math
import sys
import tarfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

_DRAW, _SLOT = 1, 2


class DataError(RuntimeError):
    """Training data cannot be used (strict mode, nothing readable, inconsistent shapes)."""


@dataclass
class StreamPlan:
    """What every worker of every rank agrees on (built once on each rank from the dataset folder)."""

    urls: list[str]
    probs: list[float]                     # draw probability per shard (source mixing)
    prompt_ids: list[str]                  # known prompt ids (a sample naming another is corrupt)
    batch_size: int
    batches_per_worker: int                # per logical worker per epoch: equal on every rank
    num_workers: int                       # logical workers per rank (>= 1)
    world_size: int
    seed: int
    open_shards: int
    strict: bool
    max_consecutive_failures: int
    load_frames: bool = False
    load_dino: bool = False
    mixing: dict = field(default_factory=dict)  # source -> effective share of draws (for the log)

    @property
    def batches_per_rank(self) -> int:
        return self.batches_per_worker * self.num_workers


@dataclass
class Cursor:
    """Position of one logical worker within an epoch (JSON-able via ``dataclasses.asdict``)."""

    batches: int = 0                       # batches yielded
    index: int = 0                         # raw samples taken (decides the next slot)
    draws: int = 0                         # shard draws made
    slots: list = field(default_factory=list)  # per slot: [draw k, shard index, samples read] or None
    skipped_samples: int = 0
    bad_shards: int = 0

    @classmethod
    def from_dict(cls, d: dict | None) -> "Cursor":
        return cls(**d) if d else cls()


def _rng(*ints: int) -> np.random.Generator:
    return np.random.default_rng([int(i) & 0xFFFFFFFF for i in ints])


def _warn(msg: str) -> None:
    print(f"[resim data] warning: {msg}", file=sys.stderr, flush=True)


def iter_raw_records(url: str) -> Iterator[dict]:
    """Raw samples ``{"__key__", "__url__", ext: bytes}`` of one tar via WebDataset's reader (any URL
    ``gopen`` opens). Raises on unreadable / truncated tars (never yields a partial sample)."""
    from webdataset.gopen import gopen
    from webdataset.tariterators import group_by_keys, tar_file_iterator

    stream = gopen(url)
    try:
        files = ({**f, "__url__": url} for f in tar_file_iterator(stream))
        yield from group_by_keys(files)
    finally:
        stream.close()


class WorkerStream:
    """Decoded samples of logical worker ``worker`` of ``rank`` in ``epoch``, grouped into batches."""

    def __init__(self, plan: StreamPlan, epoch: int, rank: int, worker: int, cursor: Cursor | None = None):
        self.plan = plan
        self.key = (plan.seed, epoch, rank, worker)
        self.cur = dataclasses.replace(cursor) if cursor else Cursor()
        if not self.cur.slots:
            self.cur.slots = [None] * plan.open_shards
        if len(self.cur.slots) != plan.open_shards:
            raise DataError(f"resume: cursor has {len(self.cur.slots)} open shards, config says {plan.open_shards}")
        self.cur.slots = [list(s) if s else None for s in self.cur.slots]
        self._iters: list[Iterator[dict] | None] = [None] * plan.open_shards
        self._known_prompts = set(plan.prompt_ids)
        self._failures = 0

    # -------------------------------------------------------------- shards
    def _draw(self) -> tuple[int, int]:
        k = self.cur.draws
        self.cur.draws += 1
        p = np.asarray(self.plan.probs, dtype=np.float64)
        shard = int(_rng(*self.key, k, _DRAW).choice(len(p), p=p / p.sum()))
        return k, shard

    def _bad_shard(self, shard: int, err: Exception) -> None:
        url = self.plan.urls[shard]
        if self.plan.strict:
            raise DataError(f"unreadable shard {url}: {err}") from err
        self.cur.bad_shards += 1
        self._failures += 1
        _warn(f"skipping unreadable shard {url}: {err} (bad shard draws on this worker: {self.cur.bad_shards})")
        if self._failures > self.plan.max_consecutive_failures:
            raise DataError(f"{self._failures} shard reads in a row failed (last: {url}: {err}); is every shard "
                            f"bad? ({len(self.plan.urls)} shards)")

    def _open(self, slot: int) -> None:
        """(Re)open the shard of ``slot`` at its recorded offset, skipping raw records."""
        k, shard, offset = self.cur.slots[slot]
        it = iter_raw_records(self.plan.urls[shard])
        for _ in range(offset):
            next(it)
        self._iters[slot] = it

    def _next_raw(self, slot: int) -> tuple[dict, int]:
        """Next raw record from ``slot``; refill the slot with new draws when its shard ends or fails."""
        while True:
            if self.cur.slots[slot] is None:
                k, shard = self._draw()
                self.cur.slots[slot] = [k, shard, 0]
                self._iters[slot] = None
            shard = self.cur.slots[slot][1]
            try:
                if self._iters[slot] is None:
                    self._open(slot)
                raw = next(self._iters[slot])
            except StopIteration:
                if self.cur.slots[slot][2] == 0:  # an empty shard is bad data too
                    self._bad_shard(shard, DataError("no samples in the tar"))
                self.cur.slots[slot] = None
                continue
            except (OSError, EOFError, tarfile.TarError, ValueError) as e:
                self._bad_shard(shard, e)
                self.cur.slots[slot] = None
                self._iters[slot] = None
                continue
            self.cur.slots[slot][2] += 1
            self._failures = 0
            return raw, shard

    # -------------------------------------------------------------- samples
    def _decode(self, raw: dict) -> dict:
        from shards.reader import decode_sample

        s = decode_sample(raw, decode_video=self.plan.load_frames)
        meta = s.get("meta.json")
        lat = s.get("latent.npy")
        if not isinstance(meta, dict):
            raise ValueError("meta.json is missing or not an object")
        if not isinstance(lat, np.ndarray) or lat.ndim != 4:
            raise ValueError(f"latent.npy missing or not 4-D (T, C, h, w): {getattr(lat, 'shape', None)}")
        if list(lat.shape) != list(meta.get("latent_shape", lat.shape)):
            raise ValueError(f"latent shape {lat.shape} != meta.latent_shape {meta.get('latent_shape')}")
        if not np.isfinite(lat).all():
            raise ValueError("latent.npy holds NaN/inf")
        for pid in ("prompt_id", "null_prompt_id"):
            if meta.get(pid) not in self._known_prompts:
                raise ValueError(f"meta.{pid}={meta.get(pid)!r} is not in the prompt table")
        traj = s.get("traj.npy")
        if traj is not None and (traj.ndim != 2 or traj.shape[1] != 3 or not np.isfinite(traj).all()):
            raise ValueError(f"traj.npy must be finite (N, 3), got {traj.shape}")
        if self.plan.load_dino and not isinstance(s.get("dino.npy"), np.ndarray):
            raise ValueError("data.load_dino is set but the sample has no dino.npy")
        return s

    def samples(self) -> Iterator[dict]:
        from shards.reader import ForbiddenMemberError, ShardReadError

        S = self.plan.open_shards
        while True:
            i = self.cur.index
            slot = int(_rng(*self.key, i, _SLOT).integers(S)) if S > 1 else 0
            raw, shard = self._next_raw(slot)
            self.cur.index += 1
            try:
                yield self._decode(raw)
            except ForbiddenMemberError as e:  # the whole shard is refused
                self._bad_shard(shard, e)
                self.cur.slots[slot] = None
                self._iters[slot] = None
            except (ShardReadError, ValueError, KeyError, TypeError) as e:
                where = f"sample {raw.get('__key__')!r} of shard {self.plan.urls[shard]}"
                if self.plan.strict:
                    raise DataError(f"corrupt {where}: {e}") from e
                self.cur.skipped_samples += 1
                _warn(f"skipping corrupt {where}: {e} (skipped on this worker: {self.cur.skipped_samples})")

    def batches(self) -> Iterator[tuple[list[dict], Cursor]]:
        """Up to ``batches_per_worker`` batches (fewer if resumed), each with the cursor after it."""
        it = self.samples()
        while self.cur.batches < self.plan.batches_per_worker:
            items = [next(it) for _ in range(self.plan.batch_size)]
            self.cur.batches += 1
            yield items, dataclasses.replace(self.cur, slots=[list(s) if s else None for s in self.cur.slots])


def batches_per_worker(samples_per_epoch: int, batch_size: int, world_size: int, num_workers: int) -> int:
    """Fixed epoch length: ceil(samples / (batch x ranks x workers)), at least 1."""
    return max(1, math.ceil(samples_per_epoch / (batch_size * world_size * num_workers)))


def shard_mixing(counts: list[dict[str, int]], weights: dict[str, float]) -> tuple[list[float], dict[str, float]]:
    """Draw probability per shard from per-shard source counts and per-source weights.

    ``p(shard) = sum_s w_s * n(shard, s) / N_s`` (normalised), so source ``s`` gets a share ``w_s / sum w``
    of the samples whatever its size; with no weights, ``p`` is proportional to shard size (the
    natural mixture). Returns (probabilities, effective share per source).
    """
    totals: dict[str, int] = {}
    for c in counts:
        for s, n in c.items():
            totals[s] = totals.get(s, 0) + int(n)
    if weights:
        for s in sorted(set(weights) - set(totals)):
            if weights[s] > 0:
                _warn(f"data.source_weights.{s}={weights[s]} but the dataset has no {s!r} samples; ignored")
        w = {s: float(weights.get(s, 0.0)) for s in totals}
        if not any(v > 0 for v in w.values()):
            raise DataError(f"data.source_weights {dict(weights)} gives no weight to any source present "
                            f"({sorted(totals)})")
    else:
        grand = sum(totals.values()) or 1
        w = {s: n / grand for s, n in totals.items()}
    probs = [sum(w[s] * n / totals[s] for s, n in c.items() if totals[s]) for c in counts]
    z = sum(probs)
    if z <= 0:
        raise DataError("no shard has samples of a source with weight > 0")
    probs = [p / z for p in probs]
    share: dict[str, float] = {}
    for p, c in zip(probs, counts):
        n = sum(c.values()) or 1
        for s, k in c.items():
            share[s] = share.get(s, 0.0) + p * k / n
    return probs, share


def dataset_counts(root: Path) -> tuple[list[str], list[dict[str, int]]]:
    """(shard paths, per-shard source counts) of the committed shards, from the index files
    (each index carries the manifest's per-source histogram)."""
    from shards import layout

    paths = layout.committed_shards(root)
    counts = []
    for p in paths:
        idx = layout.read_index(root, p.name)
        hist = (idx.get("histograms") or {}).get("source")
        counts.append({str(k): int(v) for k, v in hist.items()} if hist else {"unknown": int(idx.get("num_samples", 0))})
    return [str(p) for p in paths], counts
