import numpy as np
import pytest

from resim.shards.npy import (NpyError, bf16_bits_to_float32, decode_npy, encode_npy, float32_to_bf16_bits,
                        stored_to_float32)
from resim.shards.video import VideoError, decode_mp4, encode_mp4
from tests.support.shards import dummy_frames


def test_npy_round_trip_dtypes():
    rng = np.random.default_rng(0)
    for dt in ("float16", "float32", "uint16", "uint8", "int64", "bool"):
        a = (rng.standard_normal((3, 4, 5)) * 100).astype(dt)
        b = decode_npy(encode_npy(a))
        assert b.dtype == a.dtype and b.shape == a.shape and np.array_equal(a, b)


def test_npy_refuses_object_arrays_both_ways():
    with pytest.raises(NpyError):
        encode_npy(np.array([{"a": 1}], dtype=object))
    import io

    buf = io.BytesIO()
    np.save(buf, np.array([{"a": 1}], dtype=object), allow_pickle=True)  # a pickle inside an npy
    with pytest.raises(NpyError, match="pickle-free"):
        decode_npy(buf.getvalue())
    with pytest.raises(NpyError):
        decode_npy(b"not an npy")


def test_bf16_bits_match_torch():
    torch = pytest.importorskip("torch")
    rng = np.random.default_rng(1)
    x = np.concatenate([rng.standard_normal(5000).astype(np.float32) * 10.0 ** rng.integers(-30, 30, 5000),
                        np.array([0.0, -0.0, np.inf, -np.inf, 1e-40, -1e-42, 3.4e38, 1.0 + 2 ** -8,
                                  1.0 + 3 * 2 ** -8], np.float32)]).astype(np.float32)
    ours = float32_to_bf16_bits(x)
    ref = torch.from_numpy(x).to(torch.bfloat16).view(torch.int16).numpy().view(np.uint16)
    assert np.array_equal(ours, ref)
    # widening is exact: float32 -> bf16 -> float32 equals torch's bf16 -> float32
    assert np.array_equal(bf16_bits_to_float32(ours), torch.from_numpy(x).to(torch.bfloat16).float().numpy())
    nan_bits = float32_to_bf16_bits(np.array([np.nan], np.float32))
    assert np.isnan(bf16_bits_to_float32(nan_bits)).all()
    # the stored bits are torch's own bfloat16 bits: a reader gets the tensor with a view, no conversion
    t = torch.from_numpy(ours.view(np.int16).copy()).view(torch.bfloat16)
    assert t.dtype == torch.bfloat16 and torch.equal(t.view(torch.int16), torch.from_numpy(ref.view(np.int16)))
    assert stored_to_float32(np.float16([1.5]), "float16").dtype == np.float32


def test_mp4_round_trip():
    frames = dummy_frames(49, 32, 48, yaw_deg=20.0, seed=3)
    data = encode_mp4(frames, 10.0)
    assert data[4:8] == b"ftyp"
    assert encode_mp4(frames, 10.0) == data  # deterministic bytes (the writer's idempotent reruns rely on it)
    back = decode_mp4(data)
    assert back.shape == frames.shape and back.dtype == np.uint8
    assert np.abs(back.astype(int) - frames).mean() < 6.0  # lossy, but close
    assert np.abs(back.astype(int) - frames[::-1]).mean() > np.abs(back.astype(int) - frames).mean()


def test_mp4_errors():
    with pytest.raises(VideoError, match="even"):
        encode_mp4(np.zeros((2, 31, 48, 3), np.uint8), 10.0)
    with pytest.raises(VideoError, match=r"\(T, H, W, 3\)"):
        encode_mp4(np.zeros((2, 32, 48), np.uint8), 10.0)
    with pytest.raises(VideoError):
        decode_mp4(b"\x00" * 100)
