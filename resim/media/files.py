"""Opening only what is a regular file: the one check every reader of ours makes before it opens a path.

``open()`` on a FIFO blocks until someone writes to it, forever where no one will (``mkfifo f.mp4; resim label
f.mp4`` hung); a character device such as ``/dev/zero`` reads without end; a directory or a dangling link fails
deep inside a library with a message that names neither. So videos, checkpoint metadata, prompt embeddings and
configs are checked here first, and the error names the path and what it is instead.

``stat`` follows symbolic links (a link to a regular file is fine) and never blocks on a FIFO. Between the check
and a library's own ``open`` the path could be swapped; :func:`open_regular` closes that window for readers that
take a file object (it opens non-blocking and checks the descriptor it got).

This module sits in ``media`` because every layer that opens files may import it and it imports nothing of ours.
"""
from __future__ import annotations

import errno
import fcntl
import os
import stat
from pathlib import Path
from typing import BinaryIO


# errno values that say an output cannot be written: the machine's problem (disk full, quota, read-only mount),
# never the input's. Pipelines, training and sampling report them in one line through this set. (EACCES is not
# here: on an input it is the input's problem, so each writer says where it is the output's.)
OUTPUT_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS})


class NotARegularFile(ValueError):
    """``path`` is missing, or not a regular file (``reason`` says what it is instead)."""

    def __init__(self, path: str | Path, reason: str):
        self.path, self.reason = str(path), reason
        super().__init__(f"{path}: {reason}")


def describe_mode(mode: int) -> str:
    """What a non-regular ``st_mode`` is, in words."""
    for test, what in ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a named pipe (FIFO)"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return what
    return "not a regular file"


def check_regular(path: str | Path) -> Path:
    """``path`` as a Path where it is (a link to) a regular file; else :class:`NotARegularFile`, naming it."""
    p = Path(path)
    try:
        st = os.stat(p)
    except FileNotFoundError:
        raise NotARegularFile(p, "a dangling symbolic link" if p.is_symlink() else "no such file") from None
    except OSError as e:
        # a link loop (ELOOP), a component that is not a folder (ENOTDIR), no permission (EACCES)
        raise NotARegularFile(p, f"cannot be read ({e.strerror})") from None
    if not stat.S_ISREG(st.st_mode):
        raise NotARegularFile(p, f"is {describe_mode(st.st_mode)}, not a regular file")
    return p


def open_regular(path: str | Path) -> BinaryIO:
    """Open ``path`` for binary reading, refusing anything but a regular file without ever blocking.

    Opened with ``O_NONBLOCK`` (a FIFO opens at once instead of waiting for a writer), checked with ``fstat`` on
    the descriptor itself (no window between check and open), then switched back to blocking reads."""
    p = Path(path)
    try:
        fd = os.open(p, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        raise NotARegularFile(p, "a dangling symbolic link" if p.is_symlink() else "no such file") from None
    except OSError as e:
        raise NotARegularFile(p, f"cannot be read ({e.strerror})") from None
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise NotARegularFile(p, f"is {describe_mode(mode)}, not a regular file")
        fcntl.fcntl(fd, fcntl.F_SETFL, fcntl.fcntl(fd, fcntl.F_GETFL) & ~os.O_NONBLOCK)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_bytes(path: str | Path) -> bytes:
    """The bytes of a regular file (:func:`open_regular`)."""
    with open_regular(path) as f:
        return f.read()


def read_text(path: str | Path, encoding: str = "utf-8") -> str:
    """The text of a regular file (:func:`open_regular`)."""
    return read_bytes(path).decode(encoding)
