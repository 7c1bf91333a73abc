"""Safe ``.npy`` encoding for shard members, and bfloat16 as uint16 bits.

The ``.npy`` format (NumPy format version 1.0/2.0) is a short ASCII header plus
the raw array bytes, so readers in any language can parse it. We never write
object arrays and always read with ``allow_pickle=False``: a shard is untrusted
input and an object array in ``.npy`` is a pickle.

npy has no bfloat16 dtype, so bfloat16 tensors are stored as their raw 16-bit
patterns in a ``<u2`` (little-endian uint16) array; the sample's
``meta.latent_dtype`` (or the prompt table's ``dtype``) says ``"bfloat16"``.
A bfloat16 value is the upper 16 bits of the IEEE float32 with the same value,
so widening is exact: ``float32_bits = uint32(bits) << 16``.
"""
from __future__ import annotations

import ast
import io

import numpy as np

_MAGIC = b"\x93NUMPY"
_HEADERS: dict[bytes, tuple[np.dtype, tuple[int, ...], bool]] = {}  # parsed-header cache (shapes repeat)

# dtypes we ever write; anything else is refused before it reaches a shard
ALLOWED_NPY_DTYPES = ("float16", "float32", "float64", "uint16", "uint8", "int16", "int32", "int64", "bool")


class NpyError(ValueError):
    """A ``.npy`` payload is malformed or of a kind we refuse (object/pickled arrays)."""


def encode_npy(arr: np.ndarray) -> bytes:
    """Serialise ``arr`` as ``.npy`` bytes (C order, little-endian, no pickle)."""
    arr = np.asarray(arr)
    if arr.dtype.name not in ALLOWED_NPY_DTYPES:
        raise NpyError(f"refusing to write an npy array of dtype {arr.dtype} (allowed: {ALLOWED_NPY_DTYPES})")
    if arr.dtype.byteorder == ">":
        arr = arr.astype(arr.dtype.newbyteorder("<"))
    buf = io.BytesIO()
    np.lib.format.write_array(buf, np.ascontiguousarray(arr), allow_pickle=False)
    return buf.getvalue()


def decode_npy(data: bytes) -> np.ndarray:
    """Parse ``.npy`` bytes without pickle into a writable copy; raise :class:`NpyError` on anything else.

    Built on :func:`decode_npy_view`, which checks the header's shape against the payload's length
    before anything is allocated: ``np.load`` allocates what a (corrupt) header claims first, and a flipped
    byte in the shape became a MemoryError for 416 TiB in ``resim shards verify``."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise NpyError(f"expected bytes, got {type(data).__name__}")
    if bytes(data[:2]) == b"PK":
        raise NpyError("payload is an .npz archive, not a single .npy array")
    return decode_npy_view(data).copy()


def _parse_header(header: bytes, encoding: str) -> tuple[np.dtype, tuple[int, ...], bool]:
    """An npy header dict -> (dtype, shape, fortran_order), validated like ``numpy.lib.format`` does, and
    refusing object dtypes (they are pickles). ``ast.literal_eval`` evaluates literals only (no code)."""
    try:
        d = ast.literal_eval(header.decode(encoding))
    except (SyntaxError, ValueError, UnicodeDecodeError, MemoryError, RecursionError) as e:
        raise NpyError(f"cannot parse the npy header {header[:80]!r}: {e}") from None
    if not isinstance(d, dict) or set(d) != {"descr", "fortran_order", "shape"}:
        raise NpyError(f"npy header is not a dict with keys descr/fortran_order/shape: {header[:80]!r}")
    shape, fortran = d["shape"], d["fortran_order"]
    if not isinstance(shape, tuple) or not all(isinstance(x, int) and not isinstance(x, bool) and x >= 0
                                               for x in shape):
        raise NpyError(f"npy shape is not a tuple of non-negative ints: {shape!r}")
    if not isinstance(fortran, bool):
        raise NpyError(f"npy fortran_order is not a bool: {fortran!r}")
    try:
        dtype = np.lib.format.descr_to_dtype(d["descr"])
    except (TypeError, ValueError) as e:
        raise NpyError(f"npy descr {d['descr']!r} is not a dtype: {e}") from None
    if dtype.hasobject:
        raise NpyError(f"not a valid pickle-free .npy payload: dtype {dtype} holds Python objects (a pickle)")
    return dtype, shape, fortran


def decode_npy_view(data: bytes | memoryview) -> np.ndarray:
    """Parse ``.npy`` bytes into a read-only array that *views* ``data`` (no copy; keeps ``data`` alive).

    Same contract as :func:`decode_npy` (versions 1-3, no pickle / object arrays, :class:`NpyError` on
    anything malformed), and stricter on length: the payload must be exactly header + array bytes.
    Headers are cached by their bytes: a stream of same-shape arrays parses each distinct header once.
    """
    try:
        mv = memoryview(data)
    except TypeError:
        raise NpyError(f"expected bytes, got {type(data).__name__}") from None
    if mv.ndim != 1 or mv.itemsize != 1:
        mv = mv.cast("B")
    if len(mv) < 10 or mv[:6] != _MAGIC:
        raise NpyError("not a valid pickle-free .npy payload: bad magic (not an npy file)")
    major = mv[6]
    if major == 1:
        hlen, start, enc = int.from_bytes(mv[8:10], "little"), 10, "latin1"
    elif major in (2, 3):
        if len(mv) < 12:
            raise NpyError("not a valid pickle-free .npy payload: truncated header")
        hlen, start, enc = int.from_bytes(mv[8:12], "little"), 12, "latin1" if major == 2 else "utf8"
    else:
        raise NpyError(f"not a valid pickle-free .npy payload: unknown format version {major}.{mv[7]}")
    if len(mv) < start + hlen:
        raise NpyError("not a valid pickle-free .npy payload: truncated header")
    header = mv[start:start + hlen].tobytes()
    parsed = _HEADERS.get(header)
    if parsed is None:
        parsed = _parse_header(header, enc)
        if len(_HEADERS) >= 256:
            _HEADERS.clear()
        _HEADERS[header] = parsed
    dtype, shape, fortran = parsed
    count = 1
    for x in shape:
        count *= x
    offset = start + hlen
    if len(mv) - offset != count * dtype.itemsize:
        raise NpyError(f"not a valid pickle-free .npy payload: {len(mv) - offset} data bytes for shape {shape} "
                       f"{dtype} ({count * dtype.itemsize} expected)")
    arr = np.frombuffer(mv, dtype=dtype, count=count, offset=offset)
    if fortran:
        return arr.reshape(shape[::-1]).transpose()
    return arr.reshape(shape)


def float32_to_bf16_bits(x: np.ndarray) -> np.ndarray:
    """Round float32 values to bfloat16 (round-to-nearest-even, like torch) and return the uint16 bits."""
    x = np.ascontiguousarray(x, dtype=np.float32)
    u = x.view(np.uint32).astype(np.uint64)
    rounding = ((u >> 16) & 1) + 0x7FFF
    bits = ((u + rounding) >> 16).astype(np.uint16)
    nan = np.isnan(x)
    if nan.any():  # keep NaN a quiet NaN (rounding could carry it into inf)
        bits[nan] = ((u[nan] >> 16) | 0x40).astype(np.uint16)
    return bits


def bf16_bits_to_float32(bits: np.ndarray) -> np.ndarray:
    """Widen bfloat16 bit patterns (uint16) to float32 exactly."""
    bits = np.asarray(bits)
    if bits.dtype != np.uint16:
        raise NpyError(f"bfloat16 bits must be uint16, got {bits.dtype}")
    return (bits.astype(np.uint32) << 16).view(np.float32)


def stored_to_float32(arr: np.ndarray, dtype_name: str) -> np.ndarray:
    """A stored array (per its declared dtype name) as float32: exact for float16 and bfloat16."""
    if dtype_name == "bfloat16":
        return bf16_bits_to_float32(arr)
    return np.asarray(arr, dtype=np.float32)
