"""Crash-safe file operations: write to a temporary name, fsync, rename into place.

A reader never sees a half-written file under a final name: either the old file
(or none) or the complete new one. Temporary names start with a dot and end in
``.tmp-<pid>-<random>`` so listings of ``*.tar``/``*.json``/``*.parquet`` skip them.
"""
from __future__ import annotations

import hashlib
import os
import secrets
from pathlib import Path

TMP_MARK = ".tmp-"


def tmp_name(final: Path) -> Path:
    """A unique temporary path beside ``final`` (same directory, so rename is atomic)."""
    return final.with_name(f".{final.name}{TMP_MARK}{os.getpid()}-{secrets.token_hex(4)}")


def is_tmp_name(name: str) -> bool:
    return name.startswith(".") and TMP_MARK in name


def fsync_dir(path: Path) -> None:
    """Make a rename durable by syncing its directory (no-op where directories cannot be opened)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:  # some filesystems refuse fsync on directories
        pass
    finally:
        os.close(fd)


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (temp file, fsync, rename, fsync dir)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = tmp_name(path)
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    fsync_dir(path.parent)


def link_no_clobber(tmp: Path, final: Path) -> bool:
    """Move ``tmp`` to ``final`` only if ``final`` does not exist (atomic test-and-set via hard link).

    Returns False (and leaves ``tmp``) when ``final`` already exists. On filesystems
    without hard links, falls back to an existence check plus rename (not atomic
    against a concurrent writer of the same name, which the naming rule excludes).
    """
    try:
        os.link(tmp, final)
    except FileExistsError:
        return False
    except OSError:  # no hard links here (some FUSE/SMB mounts)
        if final.exists():
            return False
        os.replace(tmp, final)
        fsync_dir(final.parent)
        return True
    os.unlink(tmp)
    fsync_dir(final.parent)
    return True


def sha256_file(path: Path, chunk: int = 1 << 20) -> tuple[str, int]:
    """(sha256 hex, size in bytes) of a file."""
    h = hashlib.sha256()
    n = 0
    with open(path, "rb") as fh:
        while True:
            b = fh.read(chunk)
            if not b:
                break
            h.update(b)
            n += len(b)
    return h.hexdigest(), n
