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

import io

import numpy as np

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
    """Parse ``.npy`` bytes without pickle; raise :class:`NpyError` on anything else."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise NpyError(f"expected bytes, got {type(data).__name__}")
    try:
        arr = np.load(io.BytesIO(bytes(data)), allow_pickle=False)
    except (ValueError, OSError, EOFError) as e:  # numpy's errors for bad header/short data/object arrays
        raise NpyError(f"not a valid pickle-free .npy payload: {e}") from e
    if not isinstance(arr, np.ndarray):
        raise NpyError("payload is an .npz archive, not a single .npy array")
    return arr


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


def bf16_bits_to_torch(bits: np.ndarray):
    """bfloat16 bits (uint16 array) -> ``torch.bfloat16`` tensor, bit-exact (imports torch lazily)."""
    import torch

    bits = np.ascontiguousarray(bits)
    if bits.dtype != np.uint16:
        raise NpyError(f"bfloat16 bits must be uint16, got {bits.dtype}")
    return torch.from_numpy(bits.view(np.int16).copy()).view(torch.bfloat16)


def stored_to_float32(arr: np.ndarray, dtype_name: str) -> np.ndarray:
    """A stored array (per its declared dtype name) as float32: exact for float16 and bfloat16."""
    if dtype_name == "bfloat16":
        return bf16_bits_to_float32(arr)
    return np.asarray(arr, dtype=np.float32)
