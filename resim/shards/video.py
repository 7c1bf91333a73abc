"""``frames.mp4``: low-resolution RGB frames of a clip as an MPEG-4 Part 2 (``mp4v``) file.

OpenCV's own writer offers ``mp4v`` (not H.264) in the headless wheel, so that is
the codec; any MP4 reader (ffmpeg, PyAV, browsers with MPEG-4 support) decodes it.
Encoding is lossy (a few grey levels of error on smooth content) and, for the same
frames and OpenCV build, deterministic (no timestamps in the container), which the
writer's idempotent re-runs rely on.

``cv2`` is imported inside the functions only, so ``import shards`` needs nothing
beyond numpy/pyarrow/webdataset.
"""
from __future__ import annotations

import errno
import os
import shutil
import tempfile

import numpy as np


class VideoError(ValueError):
    """Frames could not be encoded, or bytes are not a decodable video."""


def _cv2():
    try:
        import cv2
    except ImportError as e:  # the light install has no OpenCV
        raise VideoError("frames.mp4 needs OpenCV: pip install 'resim[pipeline]' (opencv-python-headless)") from e
    return cv2


def encode_mp4(frames: np.ndarray, fps_hz: float) -> bytes:
    """Encode ``frames`` (T, H, W, 3) uint8 RGB at ``fps_hz`` into mp4 (mp4v) bytes.

    H and W must be even (MPEG-4 works on 2x2 chroma blocks).
    """
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8:
        raise VideoError(f"expected (T, H, W, 3) uint8 RGB frames, got {frames.shape} {frames.dtype}")
    t, h, w, _ = frames.shape
    if t < 1:
        raise VideoError("cannot encode zero frames")
    if h % 2 or w % 2:
        raise VideoError(f"frame size {h}x{w} must be even for mp4v")
    if not fps_hz > 0:
        raise VideoError(f"fps_hz must be > 0, got {fps_hz}")
    cv2 = _cv2()
    fd, path = tempfile.mkstemp(suffix=".mp4", prefix="resim-enc-")
    os.close(fd)
    try:
        writer = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"mp4v"), float(fps_hz), (w, h))
        if not writer.isOpened():
            _raise_if_full(path, "open an mp4 writer")
            raise VideoError("OpenCV could not open an mp4v writer")
        try:
            for f in frames:
                writer.write(cv2.cvtColor(np.ascontiguousarray(f), cv2.COLOR_RGB2BGR))
        finally:
            writer.release()
        try:
            with open(path, "rb") as fh:
                data = fh.read()
        except FileNotFoundError:       # the muxer removed what it could not finish
            data = b""
    finally:
        try:
            os.remove(path)
        except FileNotFoundError:
            pass
    # OpenCV reports no write error. A file that is gone, empty, or lacks its index (the moov box, written
    # last) is what a full or read-only temporary folder leaves: an OSError, retried by the pipeline, never a
    # clip with a broken frames.mp4
    if not data or b"moov" not in data:
        _raise_if_full(path, f"write an mp4 of {t} frames")
        raise OSError(errno.EIO, f"OpenCV wrote an incomplete mp4 of {t} frames ({len(data)} bytes, no index)", path)
    return data


def _raise_if_full(path: str, what: str, min_free_bytes: int = 16 << 20) -> None:
    """ENOSPC naming the folder when the filesystem of ``path`` has almost no space left."""
    folder = os.path.dirname(path) or "."
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        return
    if free < min_free_bytes:
        raise OSError(errno.ENOSPC, f"could not {what}: {free} bytes free in the temporary folder {folder} "
                                    "(TMPDIR)", path)


def read_rgb_frames(path: str) -> tuple[bool, list[np.ndarray], int]:
    """Read every frame of a video file with OpenCV, as RGB uint8 ``(H, W, 3)`` arrays.

    Returns ``(opened, frames, expected_count)``; decoding stops at the first unreadable frame, and the
    caller decides what a short read means (``expected_count`` is OpenCV's header count, 0 if unknown).
    """
    cv2 = _cv2()
    cap = cv2.VideoCapture(str(path))
    frames: list[np.ndarray] = []
    try:
        if not cap.isOpened():
            return False, frames, 0
        expected = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        while True:
            ok, f = cap.read()
            if not ok:
                break
            frames.append(cv2.cvtColor(f, cv2.COLOR_BGR2RGB))
    finally:
        cap.release()
    return True, frames, expected


def decode_mp4(data: bytes) -> np.ndarray:
    """Decode mp4 bytes into (T, H, W, 3) uint8 RGB frames."""
    if not isinstance(data, (bytes, bytearray, memoryview)) or len(data) == 0:
        raise VideoError("expected non-empty mp4 bytes")
    cv2 = _cv2()
    fd, path = tempfile.mkstemp(suffix=".mp4", prefix="resim-dec-")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(bytes(data))
        opened, frames, _ = read_rgb_frames(path)
        if not opened:
            raise VideoError("OpenCV cannot open the mp4 bytes (not a valid video)")
    finally:
        os.remove(path)
    if not frames:
        raise VideoError("the mp4 holds no decodable frames")
    return np.stack(frames)


def mp4_looks_valid(data: bytes) -> bool:
    """Cheap container check (no decode): an ISO-BMFF file starts with an ``ftyp`` box."""
    return isinstance(data, (bytes, bytearray)) and len(data) > 12 and bytes(data[4:8]) == b"ftyp"
