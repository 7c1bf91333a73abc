"""The deterministic, resumable shard stream behind ``resim.train.data.StreamLoader``.

Why not a plain ``wds.WebDataset(resampled=True).shuffle(n)``: exact resume needs the position
in the stream to be small, saveable state, and the WebDataset maintainers' recipe for equal
batch counts under DDP (resampled shards + a fixed epoch length) leaves the shard RNG and the
shuffle buffer inside worker processes. Here every choice is a pure function of
``(seed, epoch, rank, worker, index)``, through a counter-based hash (``_hash``: splitmix64 folded
over the integers; no RNG object is built per sample, which cost ~0.1-0.3 ms each with
``np.random.default_rng``):

* shard draw ``k`` of a worker: ``u = uniform(hash(seed, epoch, rank, worker, k, 1))`` inverted through
  the cumulative mixing probabilities (with replacement, so any number of shards serves any number
  of ranks x workers: no hang, no idle worker, equal batch counts);
* raw sample ``i`` of a worker is taken from slot ``hash(seed, epoch, rank, worker, i, 2) mod S``:
  each worker interleaves ``S`` open shards (``data.open_shards_per_worker``), which shuffles across
  shards without a buffer;
* a slot's shard is read front to back; when it ends the slot takes the next draw;
* shape buckets: decoded samples go, in that order, into the bucket of their ``batch_key`` (latent shape,
  clip geometry, trajectory shape, ...: what collation and the objective need equal across a batch); a
  bucket that reaches ``batch_size`` is emitted as a batch. Mixed datasets (OpenDV 13 latent frames,
  NAVSIM 3) thus train together, every batch homogeneous, each shape in proportion to its share of the
  mixed sample stream. Partial buckets at an epoch's end are dropped (mixed geometries).

The position of a worker (``Cursor``) is: draws made, raw samples taken, per slot (draw index,
shard index, samples read), and per partial bucket the (shard, record) of each sample it holds.
Resuming reopens each slot's shard and seeks over the samples read (tar headers only, nothing
decoded), and re-reads the few buffered samples by seeking to their records. Reading uses ``resim.shards.tario.open_records`` (a lean tar
reader for local shards that seeks over members the model does not use; WebDataset's ``gopen`` +
tar iterator for other URLs), decoding ``resim.shards.reader.decode_sample`` with zero-copy npy views.

Bad data: a sample that fails to decode or validate is skipped and counted; a shard that cannot
be opened or read (or holds a forbidden member) is dropped for that draw and counted; both are
reported on stderr. ``strict`` turns either into a ``DataError`` naming the shard (and key).
"""
from __future__ import annotations

import bisect
import dataclasses
import math
import sys
import tarfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from resim.shards import layout
from resim.shards.reader import ForbiddenMemberError, ShardReadError, decode_sample
from resim.shards.tario import open_records

_DRAW, _SLOT = 1, 2
SAMPLE_ORDER = "splitmix64-v2"  # recorded in the data position: positions of another order are refused
_M64 = (1 << 64) - 1


class DataError(RuntimeError):
    """Training data cannot be used (strict mode, nothing readable, inconsistent shapes)."""


# The stream gives up when this many samples in a row were unusable (left out: near-duplicates the dedup pass
# marked or clips of held-out episodes in a shard that also holds training ones; or
# corrupt: NaN latents, unknown prompts, ...). Skipping a bad sample is right; skipping forever is a hang: a
# dataset whose every key is a duplicate, or whose every latent holds a NaN, spun at full CPU with no batch. A
# usable sample resets the count. Draws interleave `open_shards_per_worker` shards, so where a share q of the data
# is unusable a run of N has probability ~q^N: 1e-44 at q = 0.9, and at q = 0.99 still 4e-5 per draw, when one
# sample in a hundred is usable and the dataset needs looking at anyway. Each unusable sample costs a tar read and
# at most a decode (~1 ms here), so N = 1000 gives up within seconds.
MAX_UNUSABLE_SAMPLES = 1000
# "skipping corrupt ..." lines per worker before they thin out to one per 100 (the count is in every line)
_WARN_EVERY_AFTER = 20


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
    read_unused_members: bool = False      # read frames.mp4/dino.npy bytes even when not loaded (benchmarks)
    max_shape_buckets: int = 16            # distinct batch keys (latent shapes, clip geometries) a worker buffers
    exclude_keys: frozenset = frozenset()  # clips left out: near-duplicates (dedup), held-out episodes (split)
    dataset: str = ""                      # the dataset folder, for messages

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
    pending: list = field(default_factory=list)  # partial shape buckets: per bucket [[shard, record], ...]

    @classmethod
    def from_dict(cls, d: dict | None) -> "Cursor":
        return cls(**d) if d else cls()


def _mix64(z: int) -> int:
    """splitmix64's finaliser (Steele et al. 2014): a bijection on 64-bit ints with full avalanche."""
    z = (z + 0x9E3779B97F4A7C15) & _M64
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & _M64
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & _M64
    return z ^ (z >> 31)


def _hash(*ints: int) -> int:
    """64-bit hash of a tuple of integers (each folded in with ``_mix64``): the stream's counter-based RNG."""
    h = 0
    for i in ints:
        h = _mix64(h ^ (int(i) & _M64))
    return h


def _uniform(h: int) -> float:
    """A 64-bit hash -> float in [0, 1) with 53 random bits."""
    return (h >> 11) * (1.0 / (1 << 53))


_CHUNK = 1 << 15


def _max_magnitude_bits(bits: np.ndarray, scratch: np.ndarray) -> int:
    """``max(bits & 0x7FFF)`` of 16-bit float bit patterns (uint16): sign masked off, so the float is NaN/inf
    iff this reaches the all-ones exponent. In cache-sized chunks through ``scratch`` (uint16, ``_CHUNK``): a fresh
    0.75 MB temporary per sample costs more in page faults than the arithmetic."""
    flat = bits.reshape(-1)
    m = 0
    for i in range(0, flat.size, _CHUNK):
        part = flat[i:i + _CHUNK]
        out = scratch[:part.size]
        np.bitwise_and(part, 0x7FFF, out=out)
        m = max(m, int(out.max()))
    return m


def _warn(msg: str) -> None:
    print(f"[resim data] warning: {msg}", file=sys.stderr, flush=True)


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
        self._unusable = {"left out": 0, "corrupt": 0}   # in a row, since the last usable sample
        self._scratch = np.empty(_CHUNK, np.uint16)  # for the NaN/inf test of 16-bit latents
        self._h = _hash(*self.key)  # hash prefix: per-sample choices fold in only (index, kind)
        p = np.asarray(plan.probs, dtype=np.float64)
        if p.ndim != 1 or not len(p) or (p < 0).any() or not p.sum() > 0:
            raise DataError(f"shard probabilities must be >= 0 with a positive sum, got {plan.probs}")
        cum = np.cumsum(p / p.sum())
        cum[int(np.flatnonzero(p > 0)[-1]):] = 2.0  # u in [0, 1) always lands on a shard with p > 0
        self._cum = cum.tolist()
        # members the batch does not use: their bytes are seeked over, not read
        self._skip_exts = () if plan.read_unused_members else tuple(
            e for e, used in (("frames.mp4", plan.load_frames), ("dino.npy", plan.load_dino)) if not used)

    # -------------------------------------------------------------- shards
    def _draw(self) -> tuple[int, int]:
        k = self.cur.draws
        self.cur.draws += 1
        u = _uniform(_mix64(_mix64(self._h ^ k) ^ _DRAW))  # = _uniform(_hash(*self.key, k, _DRAW))
        return k, bisect.bisect_right(self._cum, u)

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
        """(Re)open the shard of ``slot`` at its recorded offset (seeking over the records already read)."""
        k, shard, offset = self.cur.slots[slot]
        self._iters[slot] = open_records(self.plan.urls[shard], start=offset, skip_exts=self._skip_exts)

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
        # latents stay as stored (float16, or bfloat16 bits): Batch.to() widens them on the device, which
        # moves half the bytes through worker queues and host memory (bench/loader_overhead.py)
        # npy members as zero-copy read-only views of the member bytes (collation copies them once)
        s = decode_sample(raw, decode_video=self.plan.load_frames, latent_as="stored", npy_view=True)
        meta = s.get("meta.json")
        lat = s.get("latent.npy")
        if not isinstance(meta, dict):
            raise ValueError("meta.json is missing or not an object")
        if not isinstance(lat, np.ndarray) or lat.ndim != 4:
            raise ValueError(f"latent.npy missing or not 4-D (T, C, h, w): {getattr(lat, 'shape', None)}")
        if list(lat.shape) != list(meta.get("latent_shape", lat.shape)):
            raise ValueError(f"latent shape {lat.shape} != meta.latent_shape {meta.get('latent_shape')}")
        ldt = meta.get("latent_dtype")
        if ldt == "bfloat16":
            if lat.dtype != np.uint16:
                raise ValueError(f"meta.latent_dtype=bfloat16 but latent.npy is {lat.dtype} (expected uint16 bits)")
            # bf16 is NaN/inf iff its exponent bits are all ones
            if _max_magnitude_bits(lat, self._scratch) >= 0x7F80:
                raise ValueError("latent.npy holds NaN/inf")
        elif ldt == "float16":
            if lat.dtype != np.float16:
                raise ValueError(f"meta.latent_dtype=float16 but latent.npy is {lat.dtype}")
            # NaN/inf iff the exponent bits are all ones, i.e. |bits| >= 0x7C00 (an integer test:
            # np.isfinite on float16 is ~50x slower)
            if _max_magnitude_bits(lat.view(np.uint16), self._scratch) >= 0x7C00:
                raise ValueError("latent.npy holds NaN/inf")
        elif ldt == "float32":
            if lat.dtype != np.float32:
                raise ValueError(f"meta.latent_dtype=float32 but latent.npy is {lat.dtype}")
            if not np.isfinite(lat).all():
                raise ValueError("latent.npy holds NaN/inf")
        else:
            raise ValueError(f"meta.latent_dtype={ldt!r} is not float16/bfloat16/float32")
        for pid in ("prompt_id", "null_prompt_id"):
            if meta.get(pid) not in self._known_prompts:
                raise ValueError(f"meta.{pid}={meta.get(pid)!r} is not in the prompt table")
        traj = s.get("traj.npy")
        if traj is not None and (traj.ndim != 2 or traj.shape[1] != 3 or not np.isfinite(traj).all()):
            raise ValueError(f"traj.npy must be finite (N, 3), got {traj.shape}")
        if self.plan.load_dino and not isinstance(s.get("dino.npy"), np.ndarray):
            raise ValueError("data.load_dino is set but the sample has no dino.npy")
        return s

    def samples(self) -> Iterator[tuple[dict, int, int]]:
        """Decoded samples in stream order, each with (shard index, record index in the shard)."""
        S = self.plan.open_shards
        while True:
            i = self.cur.index
            slot = _mix64(_mix64(self._h ^ i) ^ _SLOT) % S if S > 1 else 0  # = _hash(*self.key, i, _SLOT) % S
            raw, shard = self._next_raw(slot)
            rec = self.cur.slots[slot][2] - 1  # record index in the shard: how a buffered sample is re-read
            self.cur.index += 1
            if raw.get("__key__") in self.plan.exclude_keys:   # a near-duplicate (its copy is trained on) or held out
                self._unusable_sample("left out", shard, "a near-duplicate (dedup/duplicates.parquet) or a held-out "
                                                         "episode's clip (split.json)")
                continue
            try:
                sample = self._decode(raw)
            except ForbiddenMemberError as e:  # the whole shard is refused
                self._bad_shard(shard, e)
                self.cur.slots[slot] = None
                self._iters[slot] = None
                continue
            except (ShardReadError, ValueError, KeyError, TypeError) as e:
                where = f"sample {raw.get('__key__')!r} of shard {self.plan.urls[shard]}"
                if self.plan.strict:
                    raise DataError(f"corrupt {where}: {e}") from e
                self.cur.skipped_samples += 1
                n = self.cur.skipped_samples
                if n <= _WARN_EVERY_AFTER or n % 100 == 0:
                    _warn(f"skipping corrupt {where}: {e} (skipped on this worker: {n})")
                self._unusable_sample("corrupt", shard, f"{where}: {e}")
                continue
            if self._unusable["left out"] or self._unusable["corrupt"]:   # no dict built per sample
                self._unusable = {"left out": 0, "corrupt": 0}
            yield sample, shard, rec

    def _unusable_sample(self, kind: str, shard: int, last: str) -> None:
        """Count one unusable sample; a ``DataError`` naming the dataset and the counts after
        ``MAX_UNUSABLE_SAMPLES`` in a row."""
        self._unusable[kind] += 1
        n = sum(self._unusable.values())
        if n >= MAX_UNUSABLE_SAMPLES:
            counts = ", ".join(f"{v} {k}" for k, v in self._unusable.items() if v)
            raise DataError(f"{self.plan.dataset or self.plan.urls[shard]}: no usable sample in the last {n} read "
                            f"({counts}; last: {last}); check the dataset with `resim shards verify` and its "
                            f"dedup/duplicates.parquet")

    def batch_key(self, s: dict) -> tuple:
        """What must be equal across a batch: the latent shape (T_lat, C, h, w), the clip geometry the
        objective reads per batch (history frames, frame rate -> history latent frames, latent frame duration),
        the trajectory shape (None when absent), and frames/dino shapes when they are loaded."""
        meta, traj = s["meta.json"], s.get("traj.npy")
        key = (tuple(s["latent.npy"].shape), int(meta.get("num_history_frames", 0)), float(meta.get("fps_hz", 0.0)),
               None if traj is None else tuple(traj.shape))
        if self.plan.load_frames:
            key += (tuple(s["frames"].shape),)
        if self.plan.load_dino:
            key += (tuple(s["dino.npy"].shape),)
        return key

    def _add(self, buckets: dict, item: tuple[dict, int, int]) -> list:
        k = self.batch_key(item[0])
        b = buckets.get(k)
        if b is None:
            if len(buckets) >= self.plan.max_shape_buckets:
                raise DataError(
                    f"more than data.max_shape_buckets={self.plan.max_shape_buckets} distinct sample geometries "
                    f"(latent shape, history frames, fps, trajectory) on one worker: {sorted(map(str, buckets))} "
                    f"and now {k} from {self.plan.urls[item[1]]}; is the dataset meant to mix this many "
                    "resolutions / clip lengths? (raise the limit if so)")
            b = buckets[k] = []
        b.append(item)
        return b

    def _restore(self, pending: list) -> dict:
        """Partial buckets of a saved position: re-read each buffered sample at its (shard, record)."""
        buckets: dict = {}
        for bucket in pending:
            for shard, rec in bucket:
                url = self.plan.urls[shard]
                try:
                    it = open_records(url, start=rec, skip_exts=self._skip_exts)
                    try:
                        raw = next(it)
                    finally:
                        it.close()
                    s = self._decode(raw)
                except (StopIteration, OSError, EOFError, tarfile.TarError, ShardReadError, ValueError, KeyError,
                        TypeError) as e:
                    # the sample was read fine when the position was saved: the shard changed since
                    where = f"buffered sample (record {rec}) of shard {url}"
                    if self.plan.strict:
                        raise DataError(f"resume: cannot re-read {where}: {e!r}") from e
                    self.cur.skipped_samples += 1
                    _warn(f"resume: cannot re-read {where}: {e!r}; skipped (the resumed order is no longer exact)")
                    continue
                self._add(buckets, (s, shard, rec))
        return buckets

    def batches(self) -> Iterator[tuple[list[dict], dict]]:
        """Up to ``batches_per_worker`` shape-homogeneous batches (fewer if resumed), each with the cursor
        after it (as a dict). With one geometry in the data this is plain consecutive grouping."""
        it = self.samples()
        B = self.plan.batch_size
        buckets = self._restore(self.cur.pending)
        while self.cur.batches < self.plan.batches_per_worker:
            item = next(it)
            b = self._add(buckets, item)
            if len(b) < B:
                continue
            del buckets[self.batch_key(item[0])]
            self.cur.batches += 1
            c = self.cur  # a JSON-able snapshot (dataclasses.asdict per batch was ~0.5 ms)
            c.pending = [[[sh, r] for _, sh, r in v] for v in buckets.values()]
            yield [x[0] for x in b], {"batches": c.batches, "index": c.index, "draws": c.draws,
                                      "slots": [list(s) if s else None for s in c.slots],
                                      "skipped_samples": c.skipped_samples, "bad_shards": c.bad_shards,
                                      "pending": c.pending}


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


def dataset_counts(root: Path, strict: bool = True) -> tuple[list[str], list[dict[str, int]]]:
    """(shard paths, per-shard source counts) of the committed shards, from the index files
    (each index carries the manifest's per-source histogram). A tar whose size is not the one its index
    recorded is a ``DataError`` when ``strict``, else left out with a warning (as unreadable shards are)."""
    paths, kept, dropped = layout.committed_shards(root), [], []
    counts = []
    for p in paths:
        try:
            idx = layout.read_index(root, p.name)   # size/nesting-limited JSON
        except (OSError, ValueError) as e:
            raise DataError(f"index {layout.index_path(root, p.name)}: unreadable: {e}") from e
        if not isinstance(idx, dict):
            raise DataError(f"index {layout.index_path(root, p.name)}: a JSON {type(idx).__name__}, not an object")
        # the check that costs nothing (the sha256 needs a full read: `resim shards verify`, docs/security.md):
        # a tar whose size is not the one its index recorded was truncated or replaced after it was written
        want = idx.get("bytes")
        if isinstance(want, int) and p.stat().st_size != want:
            msg = (f"shard {p}: {p.stat().st_size} bytes, but its index recorded {want}: the tar changed after it "
                   f"was written (truncated or replaced); run `resim shards verify {root}`")
            if strict:
                raise DataError(msg)
            _warn(f"skipping {msg}")
            dropped.append(msg)
            continue
        kept.append(p)
        hist = (idx.get("histograms") or {}).get("source")
        counts.append({str(k): int(v) for k, v in hist.items()} if hist else {"unknown": int(idx.get("num_samples", 0))})
    if paths and not kept:
        raise DataError(f"none of the {len(paths)} committed shards is usable (e.g. {dropped[0]})")
    return [str(p) for p in kept], counts
