"""``OUT/dedup/duplicates.parquet``: the clips a dataset's dedup pass left out (``resim/pipeline/dedup.py`` writes it;
readers that train skip the keys it lists). Columns: ``key`` string, ``duplicate_of`` string (the kept clip),
``distance_bits`` int32 (signature Hamming distance)."""
from __future__ import annotations

from pathlib import Path

import pyarrow.parquet as pq


def duplicates_path(root: str | Path) -> Path:
    return Path(root) / "dedup" / "duplicates.parquet"


def duplicate_keys(root: str | Path) -> frozenset[str]:
    """Keys the dedup pass left out (empty when the dataset has none or was never deduped)."""
    path = duplicates_path(root)
    if not path.is_file():
        return frozenset()
    return frozenset(pq.read_table(path, columns=["key"]).column("key").to_pylist())
