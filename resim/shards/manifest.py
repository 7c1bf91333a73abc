"""Read a dataset's manifests (one Parquet row per sample) and indexes (one JSON per shard) without opening tars."""
from __future__ import annotations

import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from resim.shards import layout, safejson
from resim.shards.confine import UnsafePathError, confined
from resim.shards.errors import ShardReadError
from resim.shards.schema import MANIFEST_COLUMNS, MANIFEST_COLUMNS_SINCE
from resim.shards.writer import manifest_schema


def read_manifest(root, committed_only: bool = True):
    """All manifest rows as one ``pyarrow.Table`` (columns ``MANIFEST_COLUMNS``; empty table if none).

    With ``committed_only``, rows of shards without an index (an interrupted writer) are left out.
    """
    d = layout.manifest_dir(root)
    tables = []
    for p in sorted(d.glob("*.parquet")) if d.is_dir() else []:
        if p.name.startswith("."):
            continue
        if committed_only and not layout.index_path(root, p.stem + ".tar").is_file():
            continue
        try:
            t = pq.read_table(p)
            for c in MANIFEST_COLUMNS_SINCE:                     # a manifest of an older schema: null columns
                if c not in t.column_names:
                    t = t.append_column(c, pa.nulls(len(t), manifest_schema().field(c).type))
            tables.append(t.select(list(MANIFEST_COLUMNS)).cast(manifest_schema()))
        except (pa.ArrowException, KeyError) as e:   # not Parquet, truncated, or missing/mistyped columns
            raise ShardReadError(f"manifest {p}: unreadable: {e} (`resim shards verify` lists every problem)") from e
    if not tables:
        return manifest_schema().empty_table()
    return pa.concat_tables(tables)


def read_indexes(root) -> list[dict]:
    """Every ``index/*.json``, sorted by shard name."""
    d = layout.index_dir(root)
    out = []
    for p in sorted(d.glob("*.json")) if d.is_dir() else []:
        if not p.name.startswith("."):
            try:
                idx = safejson.load_file(p)
            except (OSError, ValueError) as e:
                raise ShardReadError(f"index {p}: unreadable: {e} (`resim shards verify` lists every problem)") from e
            if not isinstance(idx, dict) or not {"shard", "num_samples", "bytes"} <= set(idx):
                raise ShardReadError(f"index {p}: not a shard index (a JSON object with shard, num_samples, bytes)")
            try:   # the shard's name becomes a path (stats checks the tar exists): it must stay in DIR/shards
                confined(layout.shards_dir(root), idx["shard"], f"index {p}: shard")
            except UnsafePathError as e:
                raise ShardReadError(str(e)) from None
            out.append(idx)
    return out


def read_quarantine(root):
    """``DIR/quarantine/*.parquet`` concatenated (the pipeline's columns: item, unit_id, source, stage, status,
    reason, attempts; see resim/pipeline/quarantine.py), or None."""
    d = layout.quarantine_dir(root)
    files = sorted(p for p in d.glob("*.parquet") if not p.name.startswith(".")) if d.is_dir() else []
    if not files:
        return None
    return pa.concat_tables([pq.read_table(p) for p in files], promote_options="default")


def shard_of_key(root, key: str) -> str | None:
    """The shard file name holding ``key``, from the manifest (None if not listed)."""
    t = read_manifest(root)
    hit = t.filter(pc.equal(t["key"], key))
    return hit["shard"][0].as_py() if hit.num_rows else None
