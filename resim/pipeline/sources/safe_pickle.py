"""A restricted unpickler for NAVSIM/OpenScene log pickles.

NAVSIM ships its logs as ``pickle.dump(list_of_frame_dicts)`` (see
docs/sources.md). ``pickle.load`` on such a file would run whatever callable
the file names, so we never use it. :func:`load_restricted` admits only:

* plain pickle data (dict, list, tuple, str, bytes, int, float, bool, None),
  which needs no class lookup at all, plus ``builtins.set``/``frozenset``/
  ``complex``/``bytearray``;
* numpy array reconstruction: ``numpy.core.multiarray._reconstruct`` and
  ``numpy._core.multiarray._reconstruct`` (protocol <= 4), ``numpy.ndarray``,
  ``numpy.dtype``, ``numpy[._]core.multiarray.scalar`` (numpy scalars) and
  ``numpy[._]core.numeric._frombuffer`` (protocol 5, which is what
  ``pickle.HIGHEST_PROTOCOL`` gives on Python >= 3.8, i.e. what the real writer
  produced).

Anything else (a class of nuPlan, ``os.system``, ``builtins.eval``, even
``_codecs.encode`` used by protocol-2 pickles of arrays) is refused with a
:class:`~resim.pipeline.sources.episode.SourceError` that names the file and the
class. Object arrays are safe too: their elements go through the same check.

Allocation is bounded too: an admitted callable that allocates from a size argument (``bytearray(n)``,
``numpy.ndarray(shape, dtype)``, ``_reconstruct(cls, shape, dtype)``) may not ask for more than
:func:`allocation_limit` of the file's size, so a 37-byte pickle cannot allocate gigabytes. Real logs carry
their array data in the file (``_reconstruct`` of an empty array, then its bytes), so they stay far below.
"""
from __future__ import annotations

import io
import pickle
from pathlib import Path

import numpy as np

from .episode import SourceError

_BUILTINS = {"set", "frozenset", "complex", "bytearray"}
_NUMPY = {
    ("numpy.core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "scalar"),
    ("numpy.core.numeric", "_frombuffer"),
    ("numpy._core.numeric", "_frombuffer"),
    ("numpy", "ndarray"),
    ("numpy", "dtype"),
}


def _numpy_attr(module: str, name: str):
    """Resolve an admitted numpy global without importing the deprecated ``numpy.core`` shim."""
    if module == "numpy":
        return getattr(np, name)
    sub = module.split(".", 2)[-1]           # "multiarray" | "numeric"
    try:
        import numpy._core as core           # numpy >= 2
    except ImportError:                      # numpy 1.x
        import numpy.core as core            # type: ignore[no-redef]
    return getattr(getattr(core, sub), name)


def allocation_limit(file_bytes: int) -> int:
    """Bytes one admitted call may allocate for a pickle of ``file_bytes``: 8x the file, at least 64 MiB."""
    return max(64 << 20, 8 * int(file_bytes))


def _nbytes(shape, dtype) -> int:
    """Bytes of an array of ``shape`` (int or tuple) and ``dtype``; a shape that is not ints counts as 0 here
    (numpy itself refuses it)."""
    dims = shape if isinstance(shape, (tuple, list)) else (shape,)
    if not all(isinstance(d, int) for d in dims):
        return 0
    try:
        itemsize = np.dtype(dtype).itemsize if dtype is not None else 8
    except TypeError:
        itemsize = 8
    n = 1
    for d in dims:
        n *= max(d, 0)
    return n * max(itemsize, 1)


class RestrictedUnpickler(pickle.Unpickler):
    """Unpickler admitting only builtins data and numpy arrays (see module docstring)."""

    def __init__(self, file, item: str, limit_bytes: int | None = None):
        super().__init__(file)
        self._item = item
        self._limit = limit_bytes

    def _bounded(self, fn, what: str, size_of):
        """``fn``, refusing calls whose allocation (``size_of(*args)`` bytes) exceeds the limit."""
        limit, item = self._limit, self._item

        def call(*args, **kwargs):
            n = size_of(*args, **kwargs)
            if limit is not None and n > limit:
                raise SourceError(item, f"pickle asks {what} to allocate {n:,} bytes (limit {limit:,} for a file "
                                        "this size): refused")
            return fn(*args, **kwargs)
        return call

    def find_class(self, module: str, name: str):
        if module == "builtins" and name in _BUILTINS:
            fn = getattr(__import__("builtins"), name)
            if name == "bytearray":
                return self._bounded(fn, "bytearray", lambda n=0, *a, **k: n if isinstance(n, int) else 0)
            return fn
        if (module, name) in _NUMPY:
            fn = _numpy_attr(module, name)
            if name == "ndarray":
                # array pickles name ndarray only as _reconstruct's first argument (unwrapped there, below); a
                # direct call ndarray(shape, dtype) allocates uninitialised memory of any size
                guard = self._bounded(fn, "numpy.ndarray", lambda shape=(), dtype=float, *a, **k: _nbytes(shape, dtype))
                guard.wrapped_type = fn   # type: ignore[attr-defined]
                return guard
            if name == "_reconstruct":
                def reconstruct(cls, *args, **kwargs):
                    return fn(getattr(cls, "wrapped_type", cls), *args, **kwargs)
                return self._bounded(reconstruct, "numpy _reconstruct",
                                     lambda cls=None, shape=(), dtype=None, *a, **k: _nbytes(shape, dtype))
            return fn
        raise SourceError(
            self._item,
            f"pickle names class {module}.{name}, which the restricted unpickler refuses "
            "(only builtins data and numpy arrays are admitted)",
        )

    def persistent_load(self, pid):  # noqa: D401 - pickle hook
        raise SourceError(self._item, "pickle uses persistent ids, which the restricted unpickler refuses")


def loads_restricted(data: bytes, item: str = "<bytes>"):
    """Unpickle ``data`` with :class:`RestrictedUnpickler`; SourceError on refusal or corruption."""
    try:
        return RestrictedUnpickler(io.BytesIO(data), item, allocation_limit(len(data))).load()
    except SourceError:
        raise
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError, IndexError,
            KeyError, MemoryError, OverflowError, UnicodeDecodeError) as e:
        raise SourceError(item, f"corrupt pickle ({type(e).__name__}: {e})") from None


def load_restricted(path: str | Path):
    """Read a pickle file with the restricted unpickler; errors name the file.

    A file that is not there (or is a folder, or is not readable by us) is bad input: ``SourceError``.
    Any other ``OSError`` (EIO, a stale NFS handle, a timeout) may be transient and propagates, so the
    pipeline retries it ``quarantine.max_attempts`` times before quarantining the log.
    """
    p = Path(path)
    try:
        data = p.read_bytes()
    except (FileNotFoundError, IsADirectoryError, NotADirectoryError, PermissionError) as e:
        raise SourceError(str(p), f"cannot read ({e.strerror})") from None
    return loads_restricted(data, str(p))
