"""Paths inside a dataset folder (see ``docs/data_format.md``)::

    DIR/shards/<prefix>-<seq:05d>.tar   DIR/index/<prefix>-<seq:05d>.json
    DIR/manifest/<prefix>-<seq:05d>.parquet   DIR/prompts/   DIR/quarantine/

A shard is *committed* when its index file exists: the writer renames the tar
into place first, then writes the manifest, then the index. Readers list
committed shards only. Removal goes the other way (index first, then manifest
and tar), so an interrupted removal leaves an uncommitted tar, never a committed
index without its tar.
"""
from __future__ import annotations

import re
from pathlib import Path

from resim.shards import safejson

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


def shards_of_prefix(root, prefix: str) -> list[str]:
    """Shard names ``<prefix>-<seq:05d>.tar`` of exactly ``prefix`` with any file on disk (tar, index or
    manifest, committed or not; temporaries excluded), sorted by sequence number."""
    found = set()
    for d, suffix in ((shards_dir(root), ".tar"), (index_dir(root), ".json"), (manifest_dir(root), ".parquet")):
        for p in d.glob(f"*{suffix}") if d.is_dir() else []:
            name = p.name[:-len(suffix)] + ".tar"
            m = SHARD_RE.match(name)
            if m and not p.name.startswith(".") and m.group("prefix") == prefix:
                found.add(name)
    return sorted(found, key=shard_seq)


def shard_seq(shard: str) -> int:
    """The sequence number of shard name ``<prefix>-<seq:05d>.tar`` (ValueError for another name)."""
    m = SHARD_RE.match(shard)
    if not m:
        raise ValueError(f"{shard!r} is not a shard name <prefix>-<seq:05d>.tar")
    return int(m.group("seq"))


def committed_shards(root) -> list[Path]:
    """Shards with an index (complete and committed), sorted by name."""
    return [p for p in all_shard_files(root) if index_path(root, p.name).is_file()]


def read_index(root, shard: str) -> dict:
    return safejson.load_file(index_path(root, shard))


def foreign_entries(out, allowed: set[str]) -> str | None:
    """A short listing ("a, b, c, ...") of what makes ``out`` a non-empty folder holding entries other than
    ``allowed`` (a command's own outputs), or None where it is absent, empty or holds only those. Commands that
    write a dataset into OUT refuse such a folder rather than mix their output into it."""
    out = Path(out)
    foreign = sorted(p.name for p in out.iterdir() if p.name not in allowed) if out.is_dir() else []
    return (", ".join(foreign[:5]) + (", ..." if len(foreign) > 5 else "")) if foreign else None
