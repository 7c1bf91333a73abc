"""Scoring API of Video2Reward: score pixel videos of any length >= the model's window.

``score_videos(model, videos)`` is what the planner calls to rank
imagined futures. A video longer than one window is scored by sliding windows:
window ``k`` starts at frame ``k * stride`` (stride defaults to the window's
span, i.e. non-overlapping windows, plus the final window aligned to the end so
no frame is left out), each window takes ``num_frames`` frames every
``frame_step``; the video's score is the plain mean of its window scores.

Bad input raises ``ScoreError`` naming the video and the reason: too short for
the window, wrong shape/dtype/range, non-finite values, unreadable frames.
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from resim.models.reward.model import Video2Reward
from resim.shards.video import read_rgb_frames


class ScoreError(ValueError):
    """A video cannot be scored (names the video and the reason)."""


def window_starts(num_frames_in_video: int, window_frames: int, stride: int) -> list[int]:
    """Start frames of the sliding windows: 0, stride, 2*stride, ... and one aligned to the end."""
    last = num_frames_in_video - window_frames
    if last < 0:
        raise ScoreError(f"{num_frames_in_video} frames < window of {window_frames}")
    starts = list(range(0, last + 1, stride))
    if starts[-1] != last:
        starts.append(last)
    return starts


def _as_video_tensor(v, name: str) -> torch.Tensor:
    """(T, 3, H, W) float in [0, 1] from a torch tensor / numpy array of that layout,
    or (T, H, W, 3) uint8 RGB (numpy or torch)."""
    t = torch.as_tensor(v) if not isinstance(v, torch.Tensor) else v
    if t.ndim != 4:
        raise ScoreError(f"{name}: expected (T, 3, H, W) float or (T, H, W, 3) uint8, got shape {tuple(t.shape)}")
    if t.dtype == torch.uint8:
        if t.shape[-1] != 3:
            raise ScoreError(f"{name}: uint8 video must be (T, H, W, 3) RGB, got {tuple(t.shape)}")
        return t.permute(0, 3, 1, 2).float() / 255.0
    if not t.is_floating_point():
        raise ScoreError(f"{name}: dtype {t.dtype} not supported (float in [0, 1] or uint8)")
    if t.shape[1] != 3:
        raise ScoreError(f"{name}: float video must be (T, 3, H, W), got {tuple(t.shape)}")
    t = t.float()
    if not torch.isfinite(t).all():
        bad = int((~torch.isfinite(t)).flatten(1).any(1).nonzero()[0])
        raise ScoreError(f"{name}: frame {bad} is unreadable (non-finite values)")
    lo, hi = float(t.min()), float(t.max())
    if lo < -1e-3 or hi > 1 + 1e-3:
        raise ScoreError(f"{name}: values must be in [0, 1], got [{lo:.3g}, {hi:.3g}]")
    return t


@torch.no_grad()
def score_videos(model: Video2Reward, videos, stride: int | None = None, batch_size: int = 16,
                 names: Sequence[str] | None = None) -> np.ndarray:
    """Predicted infraction score per video, (B,) float32 (higher = safer; 1 = clean).

    videos: a tensor (B, T, 3, H, W) float in [0, 1], or a list of videos of possibly different
    lengths/sizes, each (T_i, 3, H, W) float in [0, 1] or (T_i, H, W, 3) uint8 RGB, T_i >= the
    model's window (``model.cfg.window_frames``). stride: frames between window starts (default:
    the window's span). Windows of all videos are batched ``batch_size`` at a time.
    """
    if isinstance(videos, torch.Tensor) or isinstance(videos, np.ndarray):
        if videos.ndim != 5:
            raise ScoreError(f"expected a batch (B, T, 3, H, W) or a list of videos, got shape {tuple(videos.shape)}")
        videos = list(videos)
    if len(videos) == 0:
        raise ScoreError("no videos to score")
    names = list(names) if names is not None else [f"video[{i}]" for i in range(len(videos))]
    cfg = model.cfg
    if stride is None:  # not `stride or ...`: a stride of 0 is an error, not a request for the default
        stride = cfg.window_frames
    if stride < 1:
        raise ScoreError(f"stride must be >= 1, got {stride}")
    was_training = model.training
    model.eval()
    try:
        windows: list[torch.Tensor] = []
        owner: list[int] = []
        for i, v in enumerate(videos):
            t = _as_video_tensor(v, names[i])
            if t.shape[0] < cfg.window_frames:
                raise ScoreError(f"{names[i]}: {t.shape[0]} frames is shorter than the model's window of "
                                 f"{cfg.window_frames} frames ({cfg.num_frames} frames every {cfg.frame_step})")
            for s in window_starts(t.shape[0], cfg.window_frames, stride):
                windows.append(t[s: s + cfg.window_frames: cfg.frame_step])
                owner.append(i)
        device = next(model.parameters()).device
        preds = []
        for k in range(0, len(windows), batch_size):
            chunk = windows[k:k + batch_size]
            size = chunk[0].shape[-2:]
            if any(w.shape[-2:] != size for w in chunk):  # the model resizes anyway; stack at one size
                chunk = [torch.nn.functional.interpolate(w, size=size, mode="bilinear", antialias=True)
                         for w in chunk]
            preds.append(model(video=torch.stack(chunk).to(device)).float().cpu())
        p = torch.cat(preds).numpy()
        own = np.asarray(owner)
        return np.array([p[own == i].mean() for i in range(len(videos))], dtype=np.float32)
    finally:
        model.train(was_training)


def read_video_file(path: str | Path) -> np.ndarray:
    """Read a video file with OpenCV -> (T, H, W, 3) uint8 RGB; ScoreError on unreadable files/frames."""
    p = Path(path)
    if not p.is_file():
        raise ScoreError(f"{p}: no such video file")
    opened, frames, expected = read_rgb_frames(str(p))
    if not opened:
        raise ScoreError(f"{p}: OpenCV cannot open it as a video")
    if not frames:
        raise ScoreError(f"{p}: no decodable frame")
    if expected > 0 and len(frames) < expected:
        raise ScoreError(f"{p}: frame {len(frames)} of {expected} is unreadable (decoding stopped there)")
    return np.stack(frames)
