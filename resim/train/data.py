"""Training data: the typed ``Batch`` and ``StreamLoader`` (shards -> batches, split across ranks and workers).

``StreamLoader(cfg, rank=r, world_size=n)`` is an iterable of ``Batch`` (one epoch per ``iter``)
with ``state_dict()`` / ``load_state_dict()`` for exact resume. Every rank yields exactly
``plan.batches_per_rank`` batches per epoch whatever the number of shards, so DDP never waits
on a rank that ran dry (see ``resim/train/stream.py`` for how shards are drawn).

DataLoader workers yield pre-stacked tensors; the prompt embeddings (1-4 MB each, a handful of
distinct ones per dataset) are attached in the main process from the dataset's prompt table
(cached), so they do not travel through worker queues per sample.

Worker order: DataLoader takes batches round-robin from its workers, so batch ``b`` of an epoch
comes from logical worker ``b % W``. On resume at batch ``b0`` the physical worker ``p`` plays
logical worker ``(b0 + p) % W``, which keeps the global order exactly as in the uninterrupted run.
"""
from __future__ import annotations

import dataclasses
import hashlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import torch
from torch.utils.data import DataLoader, IterableDataset, get_worker_info

from resim.shards import split as dataset_split
from resim.shards.duplicates import duplicate_keys
from resim.shards.manifest import read_manifest
from resim.shards.npy import stored_to_float32
from resim.shards.prompts import PromptTable, PromptTableError
from resim.shards.schema import COMMANDS, latent_frame_count, temporal_compression_of
from resim.train.config import DataConfig
from resim.train.stream import (SAMPLE_ORDER, Cursor, DataError, StreamPlan, WorkerStream, batches_per_worker,
                             dataset_counts, shard_mixing)

_COMMAND_INDEX = {c: i for i, c in enumerate(COMMANDS)}


@dataclass
class Batch:
    """One batch of clips, ``B`` samples.

    latents:        (B, T_lat, C, h, w) VAE latents x scaling factor. From the loader as stored
                    (float16 or bfloat16); ``.to(device)`` widens them to float32 *on the device*
                    (exact for both), so host memory and worker queues carry half the bytes.
    text:           (B, L, D) float32 prompt embedding (prefix + command), padded as the encoder produced it;
                    a property gathering ``prompt_table[prompt_index]`` (on the table's device)
    null_text:      (B, L, D) float32 embedding of the prefix alone (CFG / command-drop null prompt);
                    a property, a broadcast view when the batch shares one null prompt (always, in ReSim)
    prompt_table:   (K, L, D) float32 the K distinct embeddings the batch uses (K <= 4 in ReSim data)
    prompt_index / null_index: (B,) int64 rows of ``prompt_table``
    trajectory:     (B, N, 3) float32 future waypoints (x m fwd, y m left, yaw rad left +); zeros where absent
    has_trajectory: (B,) bool, whether ``trajectory`` is real for the sample
    command:        (B,) int64 index into ``resim.shards.schema.COMMANDS``
    source:         B strings (``opendv`` | ``navsim`` | ``carla`` | ``synthetic``)
    keys:           B sample keys; ``meta``: B metadata dicts (``meta.json``)
    frames:         (B, T, 3, H, W) uint8 RGB 0..255 from frames.mp4, when ``data.load_frames``
    dino:           (B, T_dino, N_tok, D) DINOv2 features (float16 as stored; float32 after ``.to``), when
                    ``data.load_dino``
    actions:        (B, T_lat, A) per-frame actions, when a data source provides them (None from shards:
                    the world model's objective derives them from the trajectory)
    """

    latents: torch.Tensor
    prompt_table: torch.Tensor
    prompt_index: torch.Tensor
    null_index: torch.Tensor
    trajectory: torch.Tensor
    has_trajectory: torch.Tensor
    command: torch.Tensor
    source: list[str]
    keys: list[str]
    meta: list[dict] = field(default_factory=list)
    frames: torch.Tensor | None = None
    dino: torch.Tensor | None = None
    actions: torch.Tensor | None = None

    def __len__(self) -> int:
        return int(self.latents.shape[0])

    @property
    def text(self) -> torch.Tensor:
        return self.prompt_table[self.prompt_index.to(self.prompt_table.device)]

    @property
    def null_text(self) -> torch.Tensor:
        idx = self.null_index
        if len(idx) and bool((idx == idx[0]).all()):
            return self.prompt_table[int(idx[0])].expand(len(idx), *self.prompt_table.shape[1:])
        return self.prompt_table[idx.to(self.prompt_table.device)]

    @property
    def num_history_frames(self) -> int:
        """History (conditioning) pixel frames of the clips (from the metadata; equal across the batch)."""
        return int(self.meta[0]["num_history_frames"]) if self.meta else 0

    def _temporal_compression(self) -> int | None:
        """Pixel frames per latent frame after the first (CogVideoX: 4), from num_frames and T_lat."""
        if not self.meta or "num_frames" not in self.meta[0]:
            return None
        t_lat, n = int(self.latents.shape[1]), int(self.meta[0]["num_frames"])
        return temporal_compression_of(n, t_lat, default=None)

    @property
    def num_history_latent_frames(self) -> int | None:
        """Latent frames made of history pixel frames only: ``1 + (H - 1) // r`` for a causal VAE of ratio r (4:
        9 -> 3, NAVSIM's 1 -> 1; 1: every frame); None when the metadata does not say. Equal across the batch
        (the stream's buckets)."""
        c = self._temporal_compression()
        h = self.num_history_frames
        return latent_frame_count(h, c) if c and h >= 1 else None

    @property
    def latent_frame_dt_s(self) -> float | None:
        """Seconds one latent frame spans: r pixel frames / fps (4x VAE: 0.4 s at 10 Hz, 2 s at NAVSIM's 2 Hz)."""
        c = self._temporal_compression()
        fps = float(self.meta[0].get("fps_hz") or 0.0) if self.meta else 0.0
        return c / fps if c and fps > 0 else None

    def to(self, device: torch.device | str, non_blocking: bool = True) -> "Batch":
        """Move tensors to ``device``; float16/bfloat16 latents and features become float32 there."""
        def mv(name, v):
            if not isinstance(v, torch.Tensor):
                return v
            v = v.to(device, non_blocking=non_blocking)
            if name in ("latents", "dino") and v.dtype in (torch.float16, torch.bfloat16):
                v = v.float()
            return v
        return dataclasses.replace(self, **{f.name: mv(f.name, getattr(self, f.name))
                                            for f in dataclasses.fields(self)})

    def pin_memory(self) -> "Batch":
        def pin(v):
            return v.pin_memory() if isinstance(v, torch.Tensor) else v
        return dataclasses.replace(self, **{f.name: pin(getattr(self, f.name)) for f in dataclasses.fields(self)})


def _stack(arrays: list[np.ndarray], name: str, keys: list[str]) -> torch.Tensor:
    shapes = {a.shape for a in arrays}
    if len(shapes) > 1:
        detail = ", ".join(f"{k}: {a.shape}" for k, a in zip(keys, arrays))
        # the stream buckets samples by shape (WorkerStream.batch_key): reaching this is our bug
        raise DataError(f"cannot batch {name}: samples differ in shape ({detail}); the stream's shape buckets "
                        "should have kept them apart (resim.train.stream.WorkerStream.batch_key)")
    return torch.from_numpy(np.stack(arrays))


def _stack_latents(samples: list[dict], keys: list[str]) -> torch.Tensor:
    """Stored latents -> one tensor: float16 stays float16, bfloat16 bits become torch.bfloat16 (zero-copy
    view), float32 stays; a batch mixing dtypes is widened to float32 (exact)."""
    dtypes = {s["meta.json"]["latent_dtype"] for s in samples}
    if len(dtypes) == 1:
        dt = dtypes.pop()
        arr = _stack([s["latent.npy"] for s in samples], "latents", keys)
        return arr.view(torch.int16).view(torch.bfloat16) if dt == "bfloat16" else arr
    return _stack([stored_to_float32(s["latent.npy"], s["meta.json"]["latent_dtype"]) for s in samples],
                  "latents", keys)


def _identity(x):
    return x


def collate_samples(samples: list[dict], num_waypoints: int | None = None) -> dict[str, Any]:
    """Decoded shard samples -> a dict of stacked tensors (no prompt embeddings yet). Runs in workers."""
    keys = [s["__key__"] for s in samples]
    metas = [s["meta.json"] for s in samples]
    lat = _stack_latents(samples, keys)
    trajs = [s.get("traj.npy") for s in samples]
    n = num_waypoints or next((t.shape[0] for t in trajs if t is not None), 8)
    traj = np.zeros((len(samples), n, 3), np.float32)
    has = np.zeros(len(samples), bool)
    for i, t in enumerate(trajs):
        if t is not None:
            if t.shape[0] != n:
                raise DataError(f"cannot batch trajectories: {keys[i]} has {t.shape[0]} waypoints, others {n}")
            traj[i], has[i] = t, True
    out = {
        "latents": lat, "trajectory": torch.from_numpy(traj), "has_trajectory": torch.from_numpy(has),
        "command": torch.from_numpy(np.array([_COMMAND_INDEX.get(m.get("command"), -1) for m in metas], np.int64)),
        "source": [m.get("source", "") for m in metas], "keys": keys, "meta": metas,
        "prompt_id": [m["prompt_id"] for m in metas], "null_prompt_id": [m["null_prompt_id"] for m in metas],
    }
    if "frames" in samples[0]:
        out["frames"] = _stack([s["frames"] for s in samples], "frames", keys).permute(0, 1, 4, 2, 3).contiguous()
    if "dino.npy" in samples[0]:
        out["dino"] = _stack([s["dino.npy"] for s in samples], "dino", keys)
    return out


class _EpochStream(IterableDataset):
    """One epoch of one rank; each DataLoader worker plays one logical worker."""

    def __init__(self, plan: StreamPlan, epoch: int, rank: int, offset: int, cursors: dict[int, dict]):
        self.plan, self.epoch, self.rank, self.offset, self.cursors = plan, epoch, rank, offset, cursors

    def __iter__(self):
        info = get_worker_info()
        phys = info.id if info is not None else 0
        nphys = info.num_workers if info is not None else 1
        if nphys != self.plan.num_workers:
            raise DataError(f"{nphys} DataLoader workers, plan made for {self.plan.num_workers}")
        logical = (self.offset + phys) % self.plan.num_workers
        ws = WorkerStream(self.plan, self.epoch, self.rank, logical, Cursor.from_dict(self.cursors.get(logical)))
        for items, cursor in ws.batches():
            out = collate_samples(items)
            out["_worker"] = logical
            out["_cursor"] = cursor
            yield out


def _train_side(root: Path, paths: list[str], counts: list[dict[str, int]]):
    """(shard paths, per-shard source counts, held-out sample keys, the split's record) of the train side of
    ``root``'s split: shards wholly held out are left out, and the others' counts lose their held-out samples."""
    t = read_manifest(root)
    split = dataset_split.read(root, manifest=t)
    held_keys, held_n = set(), {}
    for key, shard, src, item in zip(t["key"].to_pylist(), t["shard"].to_pylist(), t["source"].to_pylist(),
                                     t["item_id"].to_pylist()):
        if item in split.heldout:
            held_keys.add(key)
            held_n[(shard, src)] = held_n.get((shard, src), 0) + 1
    kept_paths, kept_counts = [], []
    for p, c in zip(paths, counts):
        name = Path(p).name
        left = {s: n - held_n.get((name, s), 0) for s, n in c.items()}
        if sum(left.values()) > 0:
            kept_paths.append(p)
            kept_counts.append({s: n for s, n in left.items() if n > 0})
    if paths and not kept_paths:
        raise DataError(f"{root}: every episode is on the held-out side of its split ({split.origin})")
    return kept_paths, kept_counts, frozenset(held_keys), split.record("train")


class StreamLoader:
    """Batches for rank ``rank`` of ``world_size`` from the shards of ``cfg``; resumable."""

    def __init__(self, cfg: DataConfig, *, rank: int = 0, world_size: int = 1, pin_memory: bool = False,
                 verbose: bool = True):
        if cfg.shards is None:
            raise DataError("data.shards is not set: the dataset folder (shards/, index/, prompts/) is needed "
                            "for sample counts and the prompt table")
        root = Path(cfg.shards)
        if not root.is_dir():
            raise DataError(f"data.shards={root} is not a folder")
        paths, counts = dataset_counts(root, strict=cfg.strict)
        exclude = duplicate_keys(root) if cfg.skip_duplicates else frozenset()
        self.split = {"side": "all"}
        if cfg.split == "train":   # the held-out episodes stay out of training (resim/shards/split.py)
            paths, counts, held_keys, self.split = _train_side(root, paths, counts)
            exclude = exclude | held_keys
        urls = list(cfg.urls) or paths
        if cfg.urls and len(cfg.urls) != len(paths):
            counts = [{"unknown": 1} for _ in urls]  # explicit URLs: no per-shard counts, draw uniformly
        if not urls:
            raise DataError(f"no committed shards in {root / 'shards'} (a shard is committed when index/<name>.json exists)")
        probs, share = shard_mixing(counts, dict(cfg.source_weights))
        total = sum(sum(c.values()) for c in counts)
        spe = cfg.samples_per_epoch or total
        if cfg.urls and cfg.samples_per_epoch is None:
            raise DataError("data.urls given: set data.samples_per_epoch (the shard indexes may not describe them)")
        self.prompts = PromptTable(root)
        try:   # every entry's file confined to prompts/ and sized, up front: not an error at the first batch
            prompt_ids = self.prompts.ids()
            for pid in prompt_ids:
                self.prompts.file_path(pid)
                self.prompts.declared_bytes(pid)
        except PromptTableError as e:
            raise DataError(str(e)) from e
        W = max(1, cfg.num_workers)
        self.plan = StreamPlan(
            urls=urls, probs=probs, prompt_ids=prompt_ids, batch_size=cfg.batch_size_per_gpu,
            batches_per_worker=batches_per_worker(spe, cfg.batch_size_per_gpu, world_size, W), num_workers=W,
            world_size=world_size, seed=cfg.seed, open_shards=cfg.open_shards_per_worker, strict=cfg.strict,
            max_consecutive_failures=cfg.max_consecutive_failures, load_frames=cfg.load_frames,
            load_dino=cfg.load_dino, mixing=share, max_shape_buckets=cfg.max_shape_buckets,
            exclude_keys=exclude, dataset=str(root))
        self.cfg, self.rank, self.world_size, self.pin_memory = cfg, rank, world_size, pin_memory
        self.epoch = 0
        self.batches_in_epoch = 0
        self.cursors: dict[int, dict] = {}
        self.skipped_before = 0  # skipped samples + bad shard draws of finished epochs
        self._emb: dict[str, torch.Tensor] = {}
        self._tables: dict[tuple, torch.Tensor] = {}
        self._swap = command_groups(self.prompts) if cfg.shuffle_commands else None
        if self._swap is not None and not self._swap:
            raise DataError(f"data.shuffle_commands: the prompt table of {root} holds no command prompts to shuffle")
        if verbose and rank == 0:
            mix = ", ".join(f"{s} {v:.0%}" for s, v in sorted(share.items()))
            side = (f"the train side of the split: {self.split['episodes_train']} episodes, "
                    f"{self.split['episodes_heldout']} held out"
                    + ("; the default split: no split.json" if self.split["origin"].startswith("the default") else "")
                    if cfg.split == "train" else "every episode")
            print(f"[resim data] {len(urls)} shards, {total} samples ({mix}; {side}); {self.plan.batches_per_rank} "
                  f"batches of {cfg.batch_size_per_gpu} per rank per epoch ({world_size} ranks x {W} workers)",
                  flush=True)

    def __len__(self) -> int:
        return self.plan.batches_per_rank

    @property
    def skipped(self) -> int:
        """Corrupt samples skipped + unreadable shard draws on this rank so far."""
        return self.skipped_before + sum(c["skipped_samples"] + c["bad_shards"] for c in self.cursors.values())

    def _embedding(self, pid: str) -> torch.Tensor:
        if pid not in self._emb:
            try:
                emb = self.prompts.get(pid, as_float32=True)
            except PromptTableError as e:   # an entry naming a file outside prompts/, of another size, ...
                raise DataError(str(e)) from e
            if not np.isfinite(emb).all():   # else the first loss is NaN and the message blames the learning rate
                raise DataError(f"{self.prompts.root}: prompt {pid} ({self.prompts.info(pid).get('text', '?')!r}): "
                                f"its embedding holds {int((~np.isfinite(emb)).sum())} NaN/inf values; re-encode the "
                                "prompt table (`resim pipeline run` writes it) or drop the dataset")
            self._emb[pid] = torch.from_numpy(np.array(emb, dtype=np.float32, copy=True))
        return self._emb[pid]

    def _batch(self, d: dict) -> Batch:
        if self._swap is not None:
            d = self._shuffled(d)
        ids = tuple(sorted(set(d["prompt_id"] + d["null_prompt_id"])))
        if ids not in self._tables:  # a handful of combinations per dataset: stack each once, reuse
            embs = [self._embedding(p) for p in ids]
            if len({t.shape for t in embs}) > 1:
                raise DataError(f"prompt embeddings differ in shape within a batch ({d['keys']})")
            if len(self._tables) > 256:
                self._tables.clear()
            self._tables[ids] = torch.stack(embs)
        row = {p: i for i, p in enumerate(ids)}
        return Batch(latents=d["latents"], prompt_table=self._tables[ids],
                     prompt_index=torch.from_numpy(np.array([row[p] for p in d["prompt_id"]], np.int64)),
                     null_index=torch.from_numpy(np.array([row[p] for p in d["null_prompt_id"]], np.int64)),
                     trajectory=d["trajectory"], has_trajectory=d["has_trajectory"], command=d["command"],
                     source=list(d["source"]), keys=list(d["keys"]), meta=list(d["meta"]),
                     frames=d.get("frames"), dino=d.get("dino"))

    def _shuffled(self, d: dict) -> dict:
        """``data.shuffle_commands``: each clip's command prompt swapped for the same prefix's prompt under
        :func:`drawn_command` (``Batch.command`` follows; ``meta`` keeps what was recorded). Null prompts stay."""
        pids, cmds = [], d["command"].clone()
        for k, (key, pid) in enumerate(zip(d["keys"], d["prompt_id"])):
            group = self._swap.get(pid)
            if group is None:
                pids.append(pid)
                continue
            c = drawn_command(key, self.cfg.seed, [c for c in COMMANDS if c in group])
            pids.append(group[c])
            cmds[k] = COMMANDS.index(c)
        return {**d, "prompt_id": pids, "command": cmds}

    def __iter__(self) -> Iterator[Batch]:
        W = self.plan.num_workers
        ds = _EpochStream(self.plan, self.epoch, self.rank, self.batches_in_epoch % W, dict(self.cursors))
        nw = self.cfg.num_workers
        # no workers, no pinning: iterate the stream directly (DataLoader would only add per-batch profiler
        # hooks; it draws its seed from its own generator, so skipping it changes no RNG state)
        dl = ds if nw == 0 and not self.pin_memory else DataLoader(ds, batch_size=None, num_workers=nw, pin_memory=self.pin_memory,
                        prefetch_factor=self.cfg.prefetch_factor if nw else None, persistent_workers=False,
                        # its own generator: a DataLoader iterator otherwise draws its base seed from the global
                        # torch RNG, so a resumed run (a new iterator mid-epoch) would shift the model's noise
                        generator=torch.Generator().manual_seed(self.cfg.seed),
                        collate_fn=_identity)  # workers already yield tensors; skip the recursive default_convert
        for d in dl:
            self.cursors[int(d.pop("_worker"))] = {k: (v.tolist() if isinstance(v, torch.Tensor) else v)
                                                   for k, v in d.pop("_cursor").items()}
            self.batches_in_epoch += 1
            yield self._batch(d)
        self.skipped_before = self.skipped
        self.epoch += 1
        self.batches_in_epoch = 0
        self.cursors = {}

    def state_dict(self) -> dict:
        return {"epoch": self.epoch, "batches_in_epoch": self.batches_in_epoch, "skipped_before": self.skipped_before,
                "cursors": {str(k): v for k, v in self.cursors.items()}, "plan": {
                    "num_workers": self.plan.num_workers, "batch_size": self.plan.batch_size,
                    "batches_per_worker": self.plan.batches_per_worker, "num_shards": len(self.plan.urls),
                    "sample_order": SAMPLE_ORDER}}

    def load_state_dict(self, d: dict) -> None:
        want = self.state_dict()["plan"]
        if d.get("plan") != want:
            raise DataError(f"cannot resume the data position exactly: the checkpoint's stream was {d.get('plan')}, "
                            f"this run's is {want} (same shards, workers and batch size are needed)")
        self.epoch = int(d["epoch"])
        self.batches_in_epoch = int(d["batches_in_epoch"])
        self.skipped_before = int(d.get("skipped_before", 0))
        self.cursors = {int(k): v for k, v in d["cursors"].items()}


def command_groups(prompts: PromptTable) -> dict[str, dict[str, str]]:
    """Command prompt id -> {command: prompt id} of the prompts that share its prefix and text encoder (the
    prompts a shuffled command can swap it for)."""
    by_prefix: dict[tuple, dict[str, str]] = {}
    for pid, e in prompts.entries().items():
        c = e.get("command")
        if e.get("role") == "command" and c in COMMANDS:
            by_prefix.setdefault((e.get("encoder_id"), e["text"].rsplit(c, 1)[0]), {})[c] = pid
    return {pid: group for group in by_prefix.values() for pid in group.values()}


def drawn_command(key: str, seed: int, commands: list[str]) -> str:
    """A command for clip ``key``, uniform over ``commands`` and fixed by ``(seed, key)``: the same in every epoch,
    on every rank and after a resume (a hash, not an RNG stream, so the data order does not matter)."""
    h = int.from_bytes(hashlib.sha256(f"{seed}:{key}".encode()).digest()[:8], "big")
    return commands[h % len(commands)]
