"""Frame geometry and streaming helpers shared by the pipeline's label and encode stages and the sampler
(a history video is resized exactly as training clips were). A leaf module: imports nothing of ours.

* ``cover_size`` + ``center_crop``: resize keeping the aspect ratio so the frame covers the target,
  then crop the centre (no distortion; ReSim's 256x448 / 512x896 are ~16:9 like dashcams, so the
  crop is small). The resize happens inside the reader right after decoding (``size_hw``), so a
  1080p frame never lives in memory at full size longer than one decode.
* ``rate_step``: how many source frames per clip frame (readers expose their own rate; OpenDV is
  resampled to 10 Hz by its reader, CARLA is 10 Hz, a 20 Hz log is subsampled 2:1).
* ``sliding_windows``: one sequential pass over an episode yielding every requested window, holding at
  most ``num_frames`` frames — overlapping windows (the 5x turn balance) share decoded frames.
"""
from __future__ import annotations

import math
from collections import deque
from typing import Iterable, Iterator

import numpy as np


def cover_size(src_hw: tuple[int, int], dst_hw: tuple[int, int]) -> tuple[int, int]:
    """Smallest (H, W) with the source's aspect ratio that covers ``dst_hw``."""
    sh, sw = src_hw
    dh, dw = dst_hw
    scale = max(dh / sh, dw / sw)
    return max(dh, math.ceil(sh * scale - 1e-6)), max(dw, math.ceil(sw * scale - 1e-6))


def resize_rgb(img: np.ndarray, size_hw: tuple[int, int] | None) -> np.ndarray:
    """Resize with area interpolation when shrinking (anti-aliased), linear when growing."""
    if size_hw is None or tuple(img.shape[:2]) == tuple(size_hw):
        return img
    import cv2   # OpenCV only where a frame is resized (the geometry helpers above need numpy alone)

    h, w = size_hw
    interp = cv2.INTER_AREA if (h < img.shape[0] and w < img.shape[1]) else cv2.INTER_LINEAR
    return cv2.resize(img, (int(w), int(h)), interpolation=interp)


def cover_crop(img: np.ndarray, dst_hw: tuple[int, int]) -> np.ndarray:
    """The pipeline's clip geometry in one call: cover-resize keeping the aspect ratio, then centre crop."""
    return center_crop(resize_rgb(img, cover_size(tuple(img.shape[:2]), dst_hw)), dst_hw)


def center_crop(img: np.ndarray, dst_hw: tuple[int, int]) -> np.ndarray:
    h, w = img.shape[:2]
    dh, dw = dst_hw
    if h < dh or w < dw:
        raise ValueError(f"frame {h}x{w} smaller than crop {dh}x{dw}")  # our bug: cover_size guarantees it
    y, x = (h - dh) // 2, (w - dw) // 2
    return img[y:y + dh, x:x + dw]


# A source this much below a clip rate still counts as that rate (9.99-fps files): resampling to the nearest source
# frame then repeats one frame per 100+. Further below, frames would be repeated, i.e. motion timing invented
# (the OpenDV reader quarantines such a video; the sampler refuses such a history).
MIN_RATE_SLACK = 0.01


def rate_step(source_fps_hz: float, clip_fps_hz: float) -> int | None:
    """Integer subsampling step from the source rate to the clip rate, or None if impossible."""
    ratio = source_fps_hz / clip_fps_hz
    step = round(ratio)
    if step < 1 or abs(ratio - step) > 0.02 * step:
        return None
    return step


def clip_frames(episode, start: int, stop: int, step: int, size_hw: tuple[int, int] | None) -> Iterator[np.ndarray]:
    """Clip-rate frames ``start .. stop-1`` (clip-rate indices) of ``episode``, resized as given."""
    src = episode.frames(start * step, (stop - 1) * step + 1, size_hw=size_hw)
    for i, frame in enumerate(src):
        if i % step == 0:
            yield frame


def sliding_windows(frames: Iterable[np.ndarray], first_index: int, starts: list[int],
                    num_frames: int) -> Iterator[tuple[int, np.ndarray]]:
    """Yield ``(start, (num_frames, H, W, 3) array)`` for each start (ascending), from one pass.

    ``frames`` begins at clip index ``first_index``. Stops early (yielding fewer windows) if the
    frames run out; the caller compares what it got with what it asked for.
    """
    todo = sorted(starts)
    buf: deque = deque(maxlen=num_frames)
    k = 0
    for i, frame in enumerate(frames, start=first_index):
        buf.append(frame)
        while k < len(todo) and i == todo[k] + num_frames - 1:
            yield todo[k], np.stack(buf)
            k += 1
        if k == len(todo):
            return
