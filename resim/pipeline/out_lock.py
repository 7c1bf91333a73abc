"""The run lock on OUT: one ``resim pipeline run`` writes a dataset folder at a time.

Two runs into one OUT at once mixed two configs in one dataset (51 samples of one data hash, 12 of another,
and ``resim shards verify`` said OK): the data-hash check in ``runner.prepare_out`` refuses a second config
only once OUT holds a committed unit, and two runs started together both find none. So the process that
writes OUT — the driver of ``resim pipeline run``, which is also what a job of ``resim pipeline submit``
runs on the cluster (the submitting client writes nothing) — holds ``OUT/.lock`` for the whole run, from
before the data-hash check to the last stats file.

``flock`` rather than ``O_CREAT|O_EXCL``: the kernel releases a flock when its process dies (SIGKILL, OOM,
a lost node on NFSv4, where Linux maps flock onto the server's locks), so a crashed run never blocks the
rerun that resumes it. The file records its owner (pid, host, since when) for the refusal message; a clean
release empties it, so an owner still recorded when the lock is free is a run that died holding it (said
in the log, then taken over). The file is never removed: deleting a flocked file lets a third run lock a
new file of the same name while the second still holds the old one.
"""
from __future__ import annotations

import contextlib
import datetime
import fcntl
import json
import logging
import os
import socket
from pathlib import Path
from typing import Iterator

log = logging.getLogger("resim.pipeline")

LOCK_NAME = ".lock"


class OutBusy(Exception):
    """OUT is locked by another live run; the message is the one line to show."""


def _owner_text(fd: int) -> str:
    """The recorded owner as 'pid P on HOST since T' ('' when nothing is recorded)."""
    raw = os.pread(fd, 4096, 0)
    if not raw.strip():
        return ""
    try:
        o = json.loads(raw)
        return f"pid {o['pid']} on {o['host']} since {o['since']}"
    except (ValueError, KeyError, TypeError):   # written by something else: show it rather than guess
        return repr(raw[:120].decode("utf-8", "replace"))


def _record(fd: int) -> None:
    since = datetime.datetime.now().astimezone().isoformat(timespec="seconds")
    data = json.dumps({"pid": os.getpid(), "host": socket.gethostname(), "since": since}).encode() + b"\n"
    os.ftruncate(fd, 0)
    os.pwrite(fd, data, 0)
    os.fsync(fd)   # on a shared filesystem another host reads the owner from the server


@contextlib.contextmanager
def hold(out: str | Path) -> Iterator[Path]:
    """Hold ``OUT/.lock`` while the block runs; ``OutBusy`` at once (no waiting) if a live run holds it.

    OUT must exist. The descriptor is not inherited by the processes a run starts (Python opens files
    non-inheritable), so a Ray daemon outliving the driver cannot keep OUT locked.
    """
    out = Path(out)
    path = out / LOCK_NAME
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            owner = _owner_text(fd) or "another process (owner not recorded yet)"
            raise OutBusy(f"out: {out} is in use by another pipeline run ({owner}); wait for it to end, "
                          "or use another --out") from None
        stale = _owner_text(fd)
        if stale:
            log.warning("out: %s: taking over the lock of a run that ended without releasing it (%s)", out, stale)
        _record(fd)
        try:
            yield path
        finally:
            os.ftruncate(fd, 0)   # released cleanly: the next run finds no owner, so no stale-lock warning
    finally:
        os.close(fd)              # closing the last descriptor releases the flock
