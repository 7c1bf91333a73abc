"""Path confinement: a name taken from a dataset (a sample key, a prompt table's ``file``, a manifest's shard)
may only name something inside the folder it belongs in.

A dataset is untrusted input. Without this, a tar member and manifest row keyed ``../../../../tmp/x`` made
``resim shards preview --out DIR`` write outside DIR, and a prompts.json entry ``"file": "/dev/zero"`` was read
until MemoryError. Every place where a dataset value becomes a path goes through :func:`confined`.
"""
from __future__ import annotations

import os
from pathlib import Path, PurePosixPath


class UnsafePathError(ValueError):
    """A name from a dataset would point outside the folder it must stay in (absolute, ``..``, NUL, symlink)."""


def confined(base, name, what: str) -> Path:
    """``base / name`` when that stays inside ``base``; else :class:`UnsafePathError` naming ``what`` and why.

    Refused: a non-string or empty name, a NUL byte (the OS would cut the path there), an absolute path, any
    ``..`` component (even one that would come back: a name from a dataset has no reason to climb), and a path
    that resolves outside ``base`` through a symbolic link (of ``name``'s own folders or its last component,
    existing or not yet). ``what`` names the item for the message, e.g. ``"prompt 3fa2...: file"``.
    """
    base = Path(base)
    if not isinstance(name, str) or not name:
        raise UnsafePathError(f"{what} {name!r} is not a file name (a non-empty string)")
    if "\0" in name:
        raise UnsafePathError(f"{what} {name!r} holds a NUL byte")
    # both separators: a dataset written on one OS may be read on another
    if os.path.isabs(name) or name.startswith(("/", "\\")) or PurePosixPath(name.replace("\\", "/")).is_absolute():
        raise UnsafePathError(f"{what} {name!r} is an absolute path; it must name a file inside {base}")
    if ".." in PurePosixPath(name.replace("\\", "/")).parts:
        raise UnsafePathError(f"{what} {name!r} climbs out of {base} with '..'")
    path = base / name
    real, real_base = path.resolve(), base.resolve()
    if real != real_base and real_base not in real.parents:
        raise UnsafePathError(f"{what} {name!r} leads through a symbolic link to {real}, outside {base}")
    return path
