"""ShardWriter: validated samples -> WebDataset tars, written crash-safely, with index and manifest.

Naming and concurrency rule (many Ray workers at once)
------------------------------------------------------
* A writer owns a *prefix* (``[A-Za-z0-9_-]``, e.g. the hash of the work unit it
  writes) and names its shards ``<prefix>-00000.tar``, ``<prefix>-00001.tar``, ...
  Two writers never share a prefix at the same time; the caller picks prefixes
  so (one work unit = one prefix). Then no two writers can produce the same name.
* A shard is written under a temporary dot-name in ``DIR/shards``, fsynced and
  renamed into place (hard link: refuses to replace a file that appeared in the
  meantime). Then ``manifest/<stem>.parquet`` and finally ``index/<stem>.json``
  are written atomically. **A shard is committed when its index exists.**
* Tar bytes are deterministic (fixed member order, mtime, owner, mode), so
  re-running a work unit on the same input reproduces the same shards.
* When a final shard already exists:
    - without an index (a crash between rename and index): it was never committed
      and is replaced;
    - with an index whose sha256 and sample count equal the new shard's: the
      rerun is a no-op for that shard (``ShardInfo.reused``);
    - with a different committed index: :class:`ShardExistsError`, unless the
      writer was built with ``overwrite=True`` (the index is removed first, so the
      shard is uncommitted while it is replaced).
* A prefix holds exactly one run's shards. When :meth:`ShardWriter.close` has
  committed the last shard, shards of the prefix numbered at or above the count
  this run wrote (an earlier run of the unit that produced more shards) are
  *stale*: with ``overwrite=True`` they are removed, index first (so each is
  uncommitted at once), then manifest and tar; without it, committed stale shards
  raise :class:`ShardExistsError` and stay. Stale shards are only touched after
  every new shard is committed, so a crash during the rerun leaves each shard
  either committed and complete (new, or the earlier run's) or uncommitted; a
  crash during the removal leaves uncommitted tars, which readers skip,
  ``verify`` reports and the next writer of the prefix deletes. Until ``close``
  returns, a rerun with ``overwrite=True`` may leave a mix of new and earlier
  shards committed under the prefix (the pipeline's per-unit commit marker,
  written after ``close``, is what says a unit is complete).
* On start, a writer deletes leftovers of *its own prefix* only: temporary files
  from a killed run, uncommitted final tars and manifests without an index. The
  pipeline redoes uncommitted units deterministically, so nothing committed is
  ever lost.
* If the writer's ``with`` block raises, the open shard's temporary file is
  deleted; shards already committed stay (they are complete), and so do the
  earlier run's higher-numbered shards (the run did not finish).
"""
from __future__ import annotations

import io
import json
import os
import re
import tarfile
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from resim import __version__
from resim.shards import layout, safejson
from resim.shards.fsio import atomic_write_bytes, fsync_dir, is_tmp_name, link_no_clobber, sha256_file, tmp_name
from resim.shards.npy import encode_npy
from resim.shards.schema import MANIFEST_COLUMNS, MEMBERS, QUALITY_META, SCHEMA_VERSION
from resim.shards.validate import SampleError, sample_problems

TAR_BLOCK = 512


class ShardExistsError(FileExistsError):
    """A committed shard with different content already has this name, or an earlier run's committed shards
    of this prefix are numbered past this run's last shard (and the writer may not overwrite)."""


@dataclass
class ShardInfo:
    name: str            # file name, e.g. "abc123-00000.tar"
    path: Path           # final path
    num_samples: int
    bytes: int
    sha256: str
    reused: bool = False  # an identical committed shard was already there


def _tar_size(n: int) -> int:
    return TAR_BLOCK + -(-n // TAR_BLOCK) * TAR_BLOCK


def encode_member(ext: str, value: Any) -> bytes:
    """Bytes of one member as the schema encodes it (json: UTF-8 compact sorted; npy; mp4 bytes as is)."""
    enc = MEMBERS[ext].encoding
    if enc == "json":
        return json.dumps(value, sort_keys=True, separators=(",", ":"), ensure_ascii=False,
                          allow_nan=False).encode("utf-8")
    if enc == "npy":
        return encode_npy(value)
    if enc == "mp4":
        return bytes(value)
    raise AssertionError(f"schema member {ext} has unknown encoding {enc}")  # our bug


def manifest_schema():
    types = {
        "key": pa.string(), "shard": pa.string(), "source": pa.string(), "item_id": pa.string(),
        "start_frame": pa.int64(), "command": pa.string(), "command_source": pa.string(),
        "is_turning": pa.bool_(), "hazard": pa.bool_(), "infraction_score": pa.float64(),
        "has_trajectory": pa.bool_(), "prompt_id": pa.string(), "bytes_total": pa.int64(),
        "ego_motion_pct_s": pa.float64(), "stopped": pa.bool_(), "signature": pa.string(),
        "luma_mean_8bit": pa.float64(), "luma_std_8bit": pa.float64(), "sharpness_lapvar": pa.float64(),
        "static_edge_frac": pa.float64(), "flow_quality": pa.float64(),
    }
    assert tuple(types) == MANIFEST_COLUMNS, "manifest types out of step with schema.MANIFEST_COLUMNS"
    return pa.schema([(k, v) for k, v in types.items()])


def _hazard_label(h) -> str:
    return "null" if h is None else ("true" if h else "false")


class ShardWriter:
    """Write samples into ``DIR/shards/<prefix>-<seq:05d>.tar`` (see the module docstring for the rules).

    Args:
        root: dataset folder (created if missing).
        prefix: this writer's unique shard-name prefix, ``[A-Za-z0-9_-]{1,120}``.
        max_samples_per_shard / max_bytes_per_shard: roll to a new shard before either
            would be exceeded (a single sample larger than the byte limit gets a shard alone).
        config_hash: hash of the resolved config that produced the data (stored in each index).
        overwrite: replace committed shards of this prefix whose content differs, and on ``close`` remove the
            prefix's shards an earlier run numbered past this run's last one (see the module docstring).
        mtime: modification time stamped on every tar member (fixed, for reproducible bytes).

    After ``close``, ``removed_stale`` lists the names of the earlier run's shards it removed.
    """

    def __init__(self, root, prefix: str, max_samples_per_shard: int = 1000,
                 max_bytes_per_shard: int = 1 << 30, config_hash: str = "", overwrite: bool = False,
                 mtime: int = 0):
        if not layout.PREFIX_RE.match(prefix or ""):
            raise ValueError(f"shard prefix {prefix!r} must match {layout.PREFIX_RE.pattern} (no dots or slashes)")
        if max_samples_per_shard < 1 or max_bytes_per_shard < 1:
            raise ValueError("max_samples_per_shard and max_bytes_per_shard must be >= 1")
        self.root = Path(root)
        self.prefix = prefix
        self.max_samples = int(max_samples_per_shard)
        self.max_bytes = int(max_bytes_per_shard)
        self.config_hash = config_hash
        self.overwrite = overwrite
        self.mtime = int(mtime)
        for d in (layout.shards_dir(root), layout.index_dir(root), layout.manifest_dir(root)):
            d.mkdir(parents=True, exist_ok=True)
        self._cleanup_own_leftovers()
        self._seq = 0
        self._keys: set[str] = set()
        self._infos: list[ShardInfo] = []
        self._fh = None
        self._tar: tarfile.TarFile | None = None
        self._closed = False
        self.removed_stale: list[str] = []

    # ---- context manager -------------------------------------------------------------------------
    def __enter__(self) -> "ShardWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    # ---- public API ------------------------------------------------------------------------------
    def write(self, sample: dict) -> None:
        """Validate ``sample`` against the schema and append it (raises :class:`SampleError`)."""
        if self._closed:
            raise RuntimeError("ShardWriter is closed")
        problems = sample_problems(sample)
        key = sample.get("__key__")
        if not problems and key in self._keys:
            problems = [f"key {key!r} was already written by this writer"]
        if problems:
            raise SampleError(str(key), problems)
        payloads = [(ext, encode_member(ext, sample[ext])) for ext in MEMBERS if ext in sample]
        size = sum(_tar_size(len(b)) for _, b in payloads)
        # tarfile pads the closed file to whole 10 KiB records (RECORDSIZE): count that too, or a shard could end
        # up to 10 KiB over max_bytes
        if self._tar is not None and (self._count >= self.max_samples
                                      or -(-(self._bytes + size) // tarfile.RECORDSIZE) * tarfile.RECORDSIZE
                                      > self.max_bytes):
            self._finish_shard()
        if self._tar is None:
            self._open_shard()
        for ext, data in payloads:
            ti = tarfile.TarInfo(f"{key}.{ext}")
            ti.size, ti.mtime, ti.mode = len(data), self.mtime, 0o644
            ti.uid = ti.gid = 0
            ti.uname = ti.gname = ""
            self._tar.addfile(ti, io.BytesIO(data))
            self._member_bytes[ext] += len(data)
            self._member_counts[ext] += 1
        self._bytes += size
        self._count += 1
        self._keys.add(key)
        self._add_row(sample, sum(len(b) for _, b in payloads))

    def close(self) -> list[ShardInfo]:
        """Commit the open shard (if any), deal with the prefix's stale shards (:meth:`_drop_stale_shards`) and
        return every shard this writer committed."""
        if not self._closed:
            if self._tar is not None:
                self._finish_shard()
            self._closed = True
            self._drop_stale_shards()
        return list(self._infos)

    def abort(self) -> None:
        """Drop the open shard's temporary file; committed shards stay."""
        if self._tar is not None:
            try:
                self._tar.close()
                self._fh.close()
            finally:
                self._tmp.unlink(missing_ok=True)
                self._tar = self._fh = None
        self._closed = True

    # ---- internals -------------------------------------------------------------------------------
    def _cleanup_own_leftovers(self) -> None:
        own = re.compile(rf"^\.?{re.escape(self.prefix)}-\d{{5}}\.(tar|json|parquet)")
        for d in (layout.shards_dir(self.root), layout.index_dir(self.root), layout.manifest_dir(self.root)):
            for p in d.iterdir():
                if is_tmp_name(p.name) and own.match(p.name):
                    p.unlink(missing_ok=True)
        for name in layout.shards_of_prefix(self.root, self.prefix):
            if not layout.index_path(self.root, name).exists():
                # renamed but never committed, or left by an interrupted removal: the rerun rewrites what it needs
                layout.manifest_path(self.root, name).unlink(missing_ok=True)
                (layout.shards_dir(self.root) / name).unlink(missing_ok=True)

    def _drop_stale_shards(self) -> None:
        """After the run's last commit: remove the prefix's shards numbered >= the shards this run wrote.

        They are an earlier run's (a prefix holds one run's shards, numbered from 0). Indexes go first, highest
        number first, and are made durable before any manifest or tar is deleted, so an interrupted removal
        leaves only uncommitted files (see the module docstring). Without ``overwrite``, committed stale shards
        raise :class:`ShardExistsError` and nothing is removed.
        """
        stale = [n for n in layout.shards_of_prefix(self.root, self.prefix) if layout.shard_seq(n) >= self._seq]
        committed = [n for n in stale if layout.index_path(self.root, n).exists()]
        if committed and not self.overwrite:
            raise ShardExistsError(
                f"prefix {self.prefix!r}: this run wrote {self._seq} shard(s), but {', '.join(committed)} from an "
                "earlier run with more shards are still committed; another writer may be using this prefix, or "
                "the input changed. Pass overwrite=True to remove them.")
        for name in reversed(stale):
            layout.index_path(self.root, name).unlink(missing_ok=True)   # uncommit first
        if stale:
            fsync_dir(layout.index_dir(self.root))
        for name in stale:
            layout.manifest_path(self.root, name).unlink(missing_ok=True)
            (layout.shards_dir(self.root) / name).unlink(missing_ok=True)
        if stale:
            fsync_dir(layout.manifest_dir(self.root))
            fsync_dir(layout.shards_dir(self.root))
        self.removed_stale = stale

    def _open_shard(self) -> None:
        self._name = layout.shard_name(self.prefix, self._seq)
        self._final = layout.shards_dir(self.root) / self._name
        self._tmp = tmp_name(self._final)
        self._fh = open(self._tmp, "wb")
        self._tar = tarfile.open(fileobj=self._fh, mode="w", format=tarfile.USTAR_FORMAT)
        self._count = 0
        self._bytes = 2 * TAR_BLOCK
        self._rows: dict[str, list] = {c: [] for c in MANIFEST_COLUMNS}
        self._shard_keys: list[str] = []
        self._hist: dict[str, Counter] = {k: Counter() for k in
                                          ("command", "source", "hazard", "command_source", "latent_shape",
                                           "latent_dtype")}
        self._member_bytes: Counter = Counter()
        self._member_counts: Counter = Counter()

    def _add_row(self, sample: dict, nbytes: int) -> None:
        m = sample["meta.json"]
        vals = dict(key=sample["__key__"], shard=self._name, source=m["source"], item_id=m["item_id"],
                    start_frame=m["start_frame"], command=m["command"], command_source=m["command_source"],
                    is_turning=m["is_turning"], hazard=m["hazard"], infraction_score=m["infraction_score"],
                    has_trajectory=m["has_trajectory"], prompt_id=m["prompt_id"], bytes_total=nbytes,
                    ego_motion_pct_s=m.get("ego_motion_pct_s"), stopped=m.get("stopped"),
                    signature=m.get("signature"),
                    **{c: m.get(c) for c in QUALITY_META})
        for c in MANIFEST_COLUMNS:
            self._rows[c].append(vals[c])
        self._shard_keys.append(sample["__key__"])
        h = self._hist
        h["command"][m["command"]] += 1
        h["source"][m["source"]] += 1
        h["hazard"][_hazard_label(m["hazard"])] += 1
        h["command_source"][m["command_source"]] += 1
        h["latent_shape"]["x".join(map(str, m["latent_shape"]))] += 1
        h["latent_dtype"][m["latent_dtype"]] += 1

    def _finish_shard(self) -> None:
        self._tar.close()
        self._fh.flush()
        os.fsync(self._fh.fileno())
        self._fh.close()
        self._tar = self._fh = None
        sha, nbytes = sha256_file(self._tmp)
        idx_path = layout.index_path(self.root, self._name)
        reused = False
        if not link_no_clobber(self._tmp, self._final):
            old = None
            if idx_path.exists():
                old = safejson.load_file(idx_path)
            if old is not None and old.get("sha256") == sha and old.get("num_samples") == self._count:
                self._tmp.unlink()
                reused = True
            elif old is not None and not self.overwrite:
                self._tmp.unlink()
                raise ShardExistsError(
                    f"{self._final} is already committed with different content (sha256 {old.get('sha256')} vs "
                    f"new {sha}); another writer may be using prefix {self.prefix!r}, or the input changed. "
                    "Pass overwrite=True to replace it.")
            else:
                idx_path.unlink(missing_ok=True)  # uncommit first, so no index ever describes other bytes
                os.replace(self._tmp, self._final)
                fsync_dir(self._final.parent)
        table = pa.table({c: self._rows[c] for c in MANIFEST_COLUMNS}, schema=manifest_schema())
        buf = io.BytesIO()
        pq.write_table(table, buf)
        atomic_write_bytes(layout.manifest_path(self.root, self._name), buf.getvalue())

        index = {
            "schema_version": SCHEMA_VERSION,
            "shard": self._name,
            "path": f"shards/{self._name}",
            "prefix": self.prefix,
            "seq": self._seq,
            "num_samples": self._count,
            "bytes": nbytes,
            "sha256": sha,
            "keys": self._shard_keys,
            "histograms": {k: dict(sorted(v.items())) for k, v in self._hist.items()},
            "member_bytes": dict(sorted(self._member_bytes.items())),
            "member_counts": dict(sorted(self._member_counts.items())),
            "config_hash": self.config_hash,
            "writer": f"resim {__version__}",
        }
        atomic_write_bytes(idx_path, (json.dumps(index, indent=1, sort_keys=True) + "\n").encode())
        self._infos.append(ShardInfo(self._name, self._final, self._count, nbytes, sha, reused))
        self._seq += 1
