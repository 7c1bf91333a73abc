"""Why a path that should be a folder is not one, in words for a one-line error.

"does not exist" for a path that is there as a file sent users looking for a missing folder; the reason
says what the path is instead.
"""
from __future__ import annotations

from pathlib import Path


def folder_problem(path) -> str | None:
    """None if ``path`` is a folder (following symbolic links), else why not: ``"does not exist"``, ``"is a file,
    not a folder"``, ``"is a broken symbolic link"`` or ``"is not a folder (a device, socket or pipe)"``."""
    p = Path(path)
    if p.is_dir():
        return None
    if p.is_file():
        return "is a file, not a folder"
    if p.is_symlink() and not p.exists():
        return "is a broken symbolic link"
    if p.exists():
        return "is not a folder (a device, socket or pipe)"
    return "does not exist"
