"""A restricted unpickler for NAVSIM/OpenScene log pickles (issue 3).

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
:class:`~pipelines.sources.episode.SourceError` that names the file and the
class. Object arrays are safe too: their elements go through the same check.
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


class RestrictedUnpickler(pickle.Unpickler):
    """Unpickler admitting only builtins data and numpy arrays (see module docstring)."""

    def __init__(self, file, item: str):
        super().__init__(file)
        self._item = item

    def find_class(self, module: str, name: str):
        if module == "builtins" and name in _BUILTINS:
            return getattr(__import__("builtins"), name)
        if (module, name) in _NUMPY:
            return _numpy_attr(module, name)
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
        return RestrictedUnpickler(io.BytesIO(data), item).load()
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
