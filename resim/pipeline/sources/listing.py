"""Listing a source root without the trees the pipeline writes, so an OUT inside an input root is never input.

With ``--out`` inside the OpenDV root, a rerun after a kill listed its own ``OUT/_staging/*.frames.mp4`` as
videos and cut a clip from its own preview; a recursive CARLA ``results_glob`` would read ``OUT/commits/*.json``
and ``OUT/index/*.json`` as leaderboard results the same way. Every reader lists through here with its
config's ``exclude`` (the pipeline passes OUT and OUT's output folders: ``resim.pipeline.units.source_specs``), so
the rule lives once, not as a special case per layout.

Paths are compared resolved (symbolic links followed, relative spellings made absolute): OUT reached through
a link, or a link in the root pointing into OUT, is excluded too. A tree that holds the root itself is not
applied (it would hide the whole source: a root inside OUT); for that case the pipeline also names OUT's own
output folders, which then lie below the root and are excluded.
"""
from __future__ import annotations

import errno
import os
from pathlib import Path
from typing import Iterable

# What a walk may skip silently, as ``Path.rglob`` does: a folder that vanished or is unreadable. Any other
# OSError (EIO on a flaky mount) propagates, so the enumerate stage retries the listing and then quarantines
# the source instead of listing it short.
_SKIPPED_ERRNOS = (errno.ENOENT, errno.ENOTDIR, errno.EACCES, errno.EPERM, errno.ELOOP)


class Excluded:
    """The trees under ``root`` a listing skips (``path in excluded``)."""

    def __init__(self, root: str | Path, trees: Iterable[str | Path]):
        self.root = Path(os.path.realpath(root))
        real = {Path(os.path.realpath(t)) for t in trees}
        self.trees = frozenset(t for t in real if not self.root.is_relative_to(t))

    def __contains__(self, path: str | Path) -> bool:
        if not self.trees:
            return False
        p = Path(os.path.realpath(path))
        return any(p.is_relative_to(t) for t in self.trees)


def _raise_unless_skipped(e: OSError) -> None:
    if e.errno not in _SKIPPED_ERRNOS:
        raise e


def walk_files(root: str | Path, exclude: Iterable[str | Path] = (),
               suffixes: Iterable[str] | None = None, special: bool = False) -> list[Path]:
    """Regular files (or links to one) under ``root``, recursively, as ``root / relative path``, sorted.

    Like ``root.rglob("*")`` filtered by ``is_file()`` (folders reached through a link are not entered),
    except that an excluded tree is pruned before it is entered: an OUT of 88 k shards is not walked.
    ``suffixes``: keep only these (lower-case, with the dot), compared case-insensitively.
    ``special``: also list what carries a kept suffix but is no regular file (a FIFO, a device, a dangling link):
    a source that opens them through ``resim.media.files`` then quarantines each with its reason, instead of the walk
    dropping them without a word.
    """
    root = Path(root)
    ex = Excluded(root, exclude)
    keep = None if suffixes is None else {s.lower() for s in suffixes}
    real_root = str(ex.root)
    found = []
    for dirpath, dirnames, filenames in os.walk(real_root, onerror=_raise_unless_skipped):
        # walked from the resolved root without following links, so each folder's path is already its real
        # path and a lexical match against the (resolved) trees is exact; pruning in place stops the descent
        dirnames[:] = [d for d in dirnames if Path(dirpath, d) not in ex.trees]
        rel = os.path.relpath(dirpath, real_root)
        for name in filenames:
            if keep is not None and Path(name).suffix.lower() not in keep:
                continue
            p = root / rel / name   # pathlib drops the "." of the root's own files
            if p not in ex and (p.is_file() or (special and keep is not None)):   # `in`: links into OUT too
                found.append(p)
    return sorted(found)


def glob(root: str | Path, pattern: str, exclude: Iterable[str | Path] = ()) -> list[Path]:
    """``root.glob(pattern)`` without the paths inside an excluded tree, sorted."""
    ex = Excluded(root, exclude)
    return sorted(p for p in Path(root).glob(pattern) if p not in ex)


def children(root: str | Path, exclude: Iterable[str | Path] = ()) -> list[Path]:
    """``root.iterdir()`` (errors propagate, as there) without the excluded trees, sorted."""
    ex = Excluded(root, exclude)
    return sorted(p for p in Path(root).iterdir() if p not in ex)
