"""JSON from a dataset (meta.json members, indexes, prompts.json), with a size and a nesting-depth limit.

``json.loads`` recurses once per nesting level, so a meta.json of 200k ``[`` raised RecursionError, which no
reader treats as bad data: ``resim shards verify/show/preview``, ``resim sample`` and training ended with a
traceback instead of reporting (or skipping) one bad sample. The depth is measured *before* parsing, by a linear
scan that counts brackets outside strings (regex and numpy, no recursion and no ``sys.setrecursionlimit``), and
files are read up to the size limit only (a ``/dev/zero``-like file cannot be read unboundedly).

Errors are :class:`JSONLimitError`, a ``ValueError`` like ``json.JSONDecodeError``: every caller already
treats a ``ValueError`` from JSON as a bad sample / unreadable file (``resim.shards.reader.decode_sample`` turns it
into ``ShardReadError``, which training skips and the CLIs report in one line).
"""
from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from resim.media.files import NotARegularFile, open_regular

# A sample's meta.json is ~2 KB, an index lists a shard's keys (~100 KB for 1000s of samples), prompts.json a
# handful of entries: 64 MiB is far above any of them and still a bounded read.
MAX_JSON_BYTES = 64 << 20
# Our files nest 3-4 levels; 64 leaves room for nested metadata while json's recursion stays far from the limit.
MAX_JSON_DEPTH = 64

# a JSON string (escapes included); the closing quote is optional so an unterminated string ends the match at the
# end of the data instead of failing and being retried from every later quote (which would be quadratic)
_STRING = re.compile(rb'"[^"\\]*(?:\\.[^"\\]*)*"?', re.DOTALL)
_NOT_BRACKETS = bytes(b for b in range(256) if b not in b"[]{}")
_OPEN = np.zeros(256, np.int8)
_OPEN[list(b"[{")] = 1
_OPEN[list(b"]}")] = -1


class JSONLimitError(ValueError):
    """JSON that is too large or nested too deeply to parse safely."""


def nesting_depth(data: bytes) -> int:
    """The deepest nesting of arrays/objects in ``data`` (brackets inside strings do not count)."""
    brackets = _STRING.sub(b"", data).translate(None, _NOT_BRACKETS)
    if not brackets:
        return 0
    return int(np.cumsum(_OPEN[np.frombuffer(brackets, np.uint8)], dtype=np.int64).max())


def loads(data: bytes | bytearray | memoryview | str, max_bytes: int = MAX_JSON_BYTES,
          max_depth: int = MAX_JSON_DEPTH) -> Any:
    """``json.loads`` of UTF-8 ``data`` after checking its size and nesting depth (:class:`JSONLimitError`)."""
    raw = data.encode("utf-8", "surrogatepass") if isinstance(data, str) else bytes(data)
    if len(raw) > max_bytes:
        raise JSONLimitError(f"JSON of {len(raw)} bytes is larger than the limit of {max_bytes}")
    # fast path: fewer opening brackets than the limit cannot nest deeper (a C-speed count; a meta.json has ~10)
    if raw.count(b"[") + raw.count(b"{") > max_depth:
        depth = nesting_depth(raw)
        if depth > max_depth:
            raise JSONLimitError(f"JSON nested {depth} levels deep, more than the limit of {max_depth}")
    try:
        return json.loads(raw.decode("utf-8"))
    except RecursionError:   # cannot happen after the scan; kept so that no input ends a reader with a traceback
        raise JSONLimitError(f"JSON nested too deeply to parse (limit {max_depth})") from None


def load_file(path, max_bytes: int = MAX_JSON_BYTES, max_depth: int = MAX_JSON_DEPTH) -> Any:
    """:func:`loads` of the regular file at ``path``, reading at most ``max_bytes + 1`` bytes (OSError, ValueError).

    Opened non-blocking and checked to be a regular file first: a FIFO or device under a ``.json`` name would
    otherwise block the reader or never end."""
    try:
        fh = open_regular(path)
    except NotARegularFile as e:
        raise JSONLimitError(e.reason) from None
    with fh:
        raw = fh.read(max_bytes + 1)
    if len(raw) > max_bytes:
        raise JSONLimitError(f"file is larger than the limit of {max_bytes} bytes for JSON")
    return loads(raw, max_bytes, max_depth)


def plain(o: Any, null_nonfinite: bool = False) -> Any:
    """``o`` with tensors, arrays, numpy scalars and paths made plain JSON values. JSON has no inf/nan: they are
    written as strings ("nan"), or as null with ``null_nonfinite`` (the reward's metrics: null = undefined)."""
    if isinstance(o, dict):
        return {str(k): plain(v, null_nonfinite) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [plain(v, null_nonfinite) for v in o]
    if isinstance(o, Path):
        return str(o)
    if hasattr(o, "detach") and hasattr(o, "cpu"):   # a torch tensor, recognised without importing torch
        return plain(o.detach().cpu().numpy(), null_nonfinite)
    if isinstance(o, np.ndarray):
        return plain(o.tolist(), null_nonfinite)
    if isinstance(o, (bool, np.bool_)):
        return bool(o)
    if isinstance(o, (np.floating, float)):
        f = float(o)
        return f if math.isfinite(f) else (None if null_nonfinite else str(f))
    if isinstance(o, np.integer):
        return int(o)
    return o


def write_json(obj: Any, path: str | Path, null_nonfinite: bool = False, indent: int = 2) -> Path:
    """Write strict JSON atomically (tmp + rename) so a killed run never leaves half a report."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_suffix(p.suffix + ".tmp")
    tmp.write_text(json.dumps(plain(obj, null_nonfinite), indent=indent, sort_keys=False, allow_nan=False))
    tmp.replace(p)
    return p
