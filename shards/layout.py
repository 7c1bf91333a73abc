"""Paths inside a dataset folder (see ``docs/data_format.md``)::

    DIR/shards/<prefix>-<seq:05d>.tar   DIR/index/<prefix>-<seq:05d>.json
    DIR/manifest/<prefix>-<seq:05d>.parquet   DIR/prompts/   DIR/quarantine/

A shard is *committed* when its index file exists: the writer renames the tar
into place first, then writes the manifest, then the index. Readers list
committed shards only.
"""
from __future__ import annotations

import json
import re
from pathlib import Path

PREFIX_RE = re.compile(r"^[A-Za-z0-9_-]{1,120}$")
SHARD_RE = re.compile(r"^(?P<prefix>[A-Za-z0-9_-]+)-(?P<seq>\d{5})\.tar$")


def shards_dir(root) -> Path:
    return Path(root) / "shards"


def index_dir(root) -> Path:
    return Path(root) / "index"


def manifest_dir(root) -> Path:
    return Path(root) / "manifest"


def prompts_dir(root) -> Path:
    return Path(root) / "prompts"


def quarantine_dir(root) -> Path:
    return Path(root) / "quarantine"


def shard_name(prefix: str, seq: int) -> str:
    return f"{prefix}-{seq:05d}.tar"


def stem(shard: str) -> str:
    return shard[:-4] if shard.endswith(".tar") else shard


def index_path(root, shard: str) -> Path:
    return index_dir(root) / f"{stem(shard)}.json"


def manifest_path(root, shard: str) -> Path:
    return manifest_dir(root) / f"{stem(shard)}.parquet"


def all_shard_files(root) -> list[Path]:
    """Every ``*.tar`` under ``DIR/shards`` (committed or not), sorted by name."""
    d = shards_dir(root)
    return sorted(p for p in d.glob("*.tar") if not p.name.startswith(".")) if d.is_dir() else []


def committed_shards(root) -> list[Path]:
    """Shards with an index (complete and committed), sorted by name."""
    return [p for p in all_shard_files(root) if index_path(root, p.name).is_file()]


def read_index(root, shard: str) -> dict:
    with open(index_path(root, shard)) as fh:
        return json.load(fh)
