"""Reading shards: safe per-sample decoding, local iteration, and WebDataset training streams.

A shard is untrusted input. Only the schema's encodings are decoded (JSON, npy
with ``allow_pickle=False``, mp4 through OpenCV on demand); a sample carrying a
member whose extension names a code-executing decoder (``FORBIDDEN_EXTENSIONS``:
``.pyd``, ``.pickle``, ``.pth``, ...) raises :class:`ForbiddenMemberError` naming
the shard and key. Members outside the schema are passed through as raw bytes. A member that is not a regular
file (a symbolic or hard link, a device: ``resim.shards.tario`` marks the sample with :data:`BAD_MEMBER`) and, where
whole samples are read (:func:`find_sample`, :func:`iter_samples`), a missing required member make that one
sample bad (:class:`ShardReadError` naming shard, key and reason); its neighbours still read.

Latents and prompt embeddings come back as exact float32 by default
(``latent_as="float32"``; float16 and bfloat16 both widen exactly), or as stored
(``latent_as="stored"``: float16, or uint16 bit patterns for bfloat16, torch's own bfloat16 bits:
``torch.from_numpy(bits.view(np.int16)).view(torch.bfloat16)``).
"""
from __future__ import annotations

from functools import partial
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from resim.shards import layout, safejson
from resim.shards.confine import UnsafePathError, confined
from resim.shards.npy import decode_npy, decode_npy_view, stored_to_float32
from resim.shards.prompts import PromptTable
from resim.shards.schema import FORBIDDEN_EXTENSIONS, MEMBERS, REQUIRED_MEMBERS
from resim.shards.validate import LATENT_DTYPES, is_forbidden_ext
# the errors and member-name split live in resim.shards.errors so tario and manifest need not import this module
from resim.shards.errors import BAD_MEMBER, ForbiddenMemberError, ShardReadError
from resim.shards.manifest import shard_of_key
from resim.shards.tario import count_records, open_records
from resim.shards.video import decode_mp4

LATENT_AS = ("float32", "stored")


def check_members(raw: dict, shard: str | None = None) -> None:
    """Raise :class:`ForbiddenMemberError` if ``raw`` has a member with a forbidden extension."""
    for ext in raw:
        if not ext.startswith("__") and is_forbidden_ext(ext):
            key = raw.get("__key__")
            where = shard or raw.get("__url__") or "<unknown shard>"
            raise ForbiddenMemberError(
                f"shard {where}: sample {key!r} carries member '{key}.{ext}', a code-executing format "
                f"(forbidden: {', '.join(FORBIDDEN_EXTENSIONS)}); refusing this shard")


def check_regular(raw: dict) -> None:
    """Raise :class:`ShardReadError` if ``resim.shards.tario`` found a member of ``raw`` that is not a regular file."""
    if raw.get(BAD_MEMBER):
        raise ShardReadError(f"shard {raw.get('__url__', '?')} sample {raw.get('__key__')!r}: {raw[BAD_MEMBER]}")


def require_members(raw: dict) -> None:
    """Raise :class:`ShardReadError` if a member every sample has (``REQUIRED_MEMBERS``) is missing from ``raw``.

    For readers of whole samples; the training stream leaves members it does not need out on purpose. A link in
    place of a member is named as such, not as a missing member."""
    check_regular(raw)
    missing = [ext for ext in REQUIRED_MEMBERS if ext not in raw]
    if missing:
        raise ShardReadError(f"shard {raw.get('__url__', '?')} sample {raw.get('__key__')!r}: required member"
                             f"{'s' if len(missing) > 1 else ''} {', '.join(missing)} missing")


def decode_sample(raw: dict, *, decode_video: bool = False, latent_as: str = "float32",
                  npy_view: bool = False) -> dict:
    """Decode one raw WebDataset sample (``{"__key__", "meta.json": bytes, ...}``) with the schema's decoders.

    Returns the same keys with decoded values (``frames.mp4`` stays bytes); with
    ``decode_video`` also ``"frames"``: (T, H, W, 3) uint8 RGB. ``npy_view``: npy members become
    read-only zero-copy views of the member bytes (``resim.shards.npy.decode_npy_view``) instead of copies.
    """
    if latent_as not in LATENT_AS:
        raise ValueError(f"latent_as must be one of {LATENT_AS}, got {latent_as!r}")
    check_members(raw)
    check_regular(raw)
    out: dict = {}
    where = f"shard {raw.get('__url__', '?')} sample {raw.get('__key__')!r}"
    for ext, value in raw.items():
        if ext.startswith("__"):
            out[ext] = value
            continue
        m = MEMBERS.get(ext)
        if m is None:
            out[ext] = value  # not in the schema: left as bytes, never decoded
            continue
        try:
            if m.encoding == "json":
                out[ext] = safejson.loads(value)   # size and nesting limits: a JSON bomb is a bad sample
            elif m.encoding == "npy":
                out[ext] = decode_npy_view(value) if npy_view else decode_npy(value)
            else:
                out[ext] = bytes(value)
        except (ValueError, UnicodeDecodeError) as e:
            raise ShardReadError(f"{where}: member {ext} cannot be decoded: {e}") from e
    if "meta.json" in out and not isinstance(out["meta.json"], dict):
        raise ShardReadError(f"{where}: meta.json is a JSON {type(out['meta.json']).__name__}, not an object")
    if latent_as == "float32" and isinstance(out.get("latent.npy"), np.ndarray):
        lat = out["latent.npy"]
        dtype = (out.get("meta.json") or {}).get("latent_dtype", lat.dtype.name)
        # the stored dtype must be the one meta declares: uint16 read as float16 (or the reverse) would give
        # finite, silently wrong latents
        if dtype not in LATENT_DTYPES or lat.dtype != LATENT_DTYPES[dtype]:
            raise ShardReadError(f"{where}: latent.npy is stored as {lat.dtype} but meta.latent_dtype is {dtype!r} "
                                 f"(float16 is stored as float16, bfloat16 as uint16 bits)")
        out["latent.npy"] = stored_to_float32(lat, dtype)
    if decode_video and "frames.mp4" in out:
        out["frames"] = decode_mp4(out["frames.mp4"])
    return out


# ---- local reading --------------------------------------------------------------------------------
def iter_raw_shard(path) -> Iterator[dict]:
    """Raw samples of one local tar, grouped like WebDataset (``resim.shards.tario``).

    The whole shard's headers are read first (data seeked over), so a shard with a forbidden member, a
    corrupt header or a cut end is refused before any sample is yielded. (``tarfile``, used here before,
    ends quietly at a corrupt header after the first member: a silently short shard.)"""

    path = str(path)
    try:
        count_records(path)
        yield from open_records(path)
    except OSError as e:
        raise ShardReadError(f"shard {path}: cannot read the tar: {e}") from e


class PromptAttacher:
    """Adds ``prompt_embedding`` and ``null_prompt_embedding`` from the dataset's prompt table (cached)."""

    def __init__(self, root, latent_as: str = "float32"):
        self.root = str(root)
        self.as_float32 = latent_as == "float32"
        self._table = None

    def __call__(self, sample: dict) -> dict:
        if self._table is None:  # opened lazily, so the attacher pickles cheaply into workers
            self._table = PromptTable(self.root)
        meta = sample["meta.json"]
        sample["prompt_embedding"] = self._table.get(meta["prompt_id"], as_float32=self.as_float32)
        sample["null_prompt_embedding"] = self._table.get(meta["null_prompt_id"], as_float32=self.as_float32)
        return sample


def iter_samples(root, *, decode_video: bool = False, latent_as: str = "float32", attach_prompts: bool = True,
                 shards: Iterable | None = None) -> Iterator[dict]:
    """Decoded samples of every committed shard of dataset ``root`` (or of the given shard paths), in order."""
    paths = [Path(s) for s in shards] if shards is not None else layout.committed_shards(root)
    attach = PromptAttacher(root, latent_as) if attach_prompts else None
    for p in paths:
        for raw in iter_raw_shard(p):
            require_members(raw)
            s = decode_sample(raw, decode_video=decode_video, latent_as=latent_as)
            yield attach(s) if attach else s


def find_sample(root, key: str, *, decode_video: bool = False, latent_as: str = "float32",
                attach_prompts: bool = True) -> dict:
    """One decoded sample by key (finds its shard through the manifest, else scans).

    Only the sample asked for is decoded: a corrupt neighbour in the same shard does not hide it. The manifest's
    shard name is a dataset value, so it must name a file inside ``DIR/shards`` (else :class:`ShardReadError`).
    """

    shard = shard_of_key(root, key)
    if shard:
        try:
            paths = [confined(layout.shards_dir(root), shard, f"manifest row of sample {key!r}: shard")]
        except UnsafePathError as e:
            raise ShardReadError(str(e)) from None
    else:
        paths = layout.committed_shards(root)
    for p in paths:
        for raw in iter_raw_shard(p):
            if raw["__key__"] == key:
                require_members(raw)
                s = decode_sample(raw, decode_video=decode_video, latent_as=latent_as)
                return PromptAttacher(root, latent_as)(s) if attach_prompts else s
    raise KeyError(f"no sample with key {key!r} in {root}")


# ---- training streams -----------------------------------------------------------------------------
def shard_urls(root) -> list[str]:
    """Paths of the committed shards of a dataset folder, for ``make_webdataset``."""
    return [str(p) for p in layout.committed_shards(root)]


def _decode_checked(raw: dict, decode_video: bool, latent_as: str) -> dict:
    return decode_sample(raw, decode_video=decode_video, latent_as=latent_as)


def make_webdataset(urls, *, shardshuffle: int | bool = False, shuffle_samples: int = 0, resampled: bool = False,
                    nodesplitter=None, workersplitter=None, empty_check: bool = False, seed: int | None = None,
                    decode_video: bool = False, latent_as: str = "float32", prompts_root=None, handler=None):
    """A ``webdataset.WebDataset`` stream of decoded samples for training.

    Args:
        urls: a dataset folder (its committed shards are used), or shard paths/URLs (list or brace pattern).
        shardshuffle: shard-order shuffle buffer (False: keep order).
        shuffle_samples: sample shuffle buffer (0: none).
        resampled: sample shards with replacement forever (for fixed-step training; shardshuffle is ignored).
        nodesplitter: defaults to ``wds.split_by_node`` (each rank gets a disjoint slice of shards under DDP).
        workersplitter: defaults to ``wds.split_by_worker`` (DataLoader workers split a rank's shards).
        empty_check: WebDataset raises when a worker gets no shards if True; False lets fewer shards than
            workers through.
        prompts_root: attach prompt embeddings from this dataset's prompt table in the stream. Leave None in
            multi-worker loaders and look embeddings up by ``meta.prompt_id`` in the main process
            (``PromptTable.get`` caches them), so 1-4 MB arrays do not travel through worker queues per sample.
        handler: WebDataset exception handler (default: re-raise).
    """
    # webdataset imports torch, and shards must stay importable without it: only the training stream needs it
    import webdataset as wds

    if isinstance(urls, (str, Path)) and Path(urls).is_dir():
        urls = shard_urls(urls)
        if not urls:
            raise ShardReadError("no committed shards (shards/*.tar with an index) in the given folder")
    ds = wds.WebDataset(
        urls,
        handler=handler or wds.reraise_exception,
        resampled=resampled,
        shardshuffle=False if resampled else shardshuffle,
        nodesplitter=nodesplitter or wds.split_by_node,
        workersplitter=workersplitter or wds.split_by_worker,
        empty_check=empty_check,
        seed=seed,
    )
    if shuffle_samples:
        ds = ds.shuffle(shuffle_samples)
    ds = ds.map(partial(_decode_checked, decode_video=decode_video, latent_as=latent_as))
    if prompts_root is not None:
        ds = ds.map(PromptAttacher(prompts_root, latent_as))
    return ds
