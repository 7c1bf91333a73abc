"""Label a whole video in (overlapping) windows: the engine behind ``resim label``."""
from __future__ import annotations

import itertools
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from resim.config import check_positive
from resim.labeling.commands import command_from_yaw
from resim.labeling.config import LabelerConfig
from resim.labeling.flow import FlowLabeler, window_quality
from resim.labeling.flow_sampling import iter_grey_samples
from resim.media.video_probe import VideoError, VideoInfo, probe


# Frames are decoded in blocks of this many samples, then the flow runs over the block: decoder and flow
# then keep their own data in cache instead of evicting each other every frame. 3-9 % less CPU for the
# whole labeler on 1280x720 H.264 (bench/label_throughput.py, 2026-11-24); same output; 128 samples at
# 256x144 are 4.7 MB.
DECODE_BLOCK_SAMPLES = 128


def _in_blocks(it, n: int):
    while block := list(itertools.islice(it, n)):
        yield from block


@dataclass(frozen=True)
class WindowLabel:
    start_s: float
    end_s: float
    command: str
    yaw_deg: float        # heading change over [start_s, end_s], degrees, left +
    confidence: float     # command confidence x flow quality, 0..1
    quality: float        # flow quality of the window, 0..1


@dataclass
class VideoLabels:
    info: VideoInfo
    sample_hz: float          # effective sampling rate (min of the config's and the video's)
    times_s: np.ndarray       # (S,) sample times
    yaw_inc_deg: np.ndarray   # (S-1,) yaw change per sample pair, degrees, left +
    quality: np.ndarray       # (S-1,) per-pair share of grid points kept
    windows: list[WindowLabel]
    decode: dict              # decoder, frames_decoded, nonref_skipped, incomplete, ... (resim/media/video.py)
    foe_sources: list[str] = field(default_factory=list)   # per chunk of pairs: "rig" / "pooled" / "per_pair"


def window_starts(duration_s: float, window_s: float, stride_s: float, tol_s: float) -> list[tuple[float, float]]:
    """Windows [start, start + window_s] that fit in the video; one shorter window when none fits."""
    if duration_s + tol_s < window_s:
        return [(0.0, duration_s)]
    out, k = [], 0
    while k * stride_s + window_s <= duration_s + tol_s:
        out.append((k * stride_s, k * stride_s + window_s))
        k += 1
    return out


def label_video(path: str | Path, cfg: LabelerConfig | None = None, window_s: float | None = None,
                stride_s: float = 2.0, progress: bool = False) -> VideoLabels:
    """Per-pair yaw over the whole video, then one label per window. Raises VideoError on bad input.

    A truncated or damaged file is labelled up to where it stops decoding, and ``decode["incomplete"]`` says so
    (seconds decoded vs the container's video duration, and why; None for a complete decode): check it where
    partial labels are not wanted (docs/labeling.md, "Odd files").

    ``progress``: a tqdm bar on stderr in seconds of video (OpenDV videos run for hours: at 15-22x real time per
    core, an hour of 720p video is ~3-4 min of CPU).
    """
    cfg = cfg or LabelerConfig()
    window_s = cfg.command.window_s if window_s is None else window_s
    check_positive("window_s", window_s)   # ConfigError (a ValueError); NaN passed `<= 0` and gave zero windows
    check_positive("stride_s", stride_s)
    info = probe(path)
    fc = cfg.flow
    times: list[float] = []
    stats: dict = {}

    # the container's video duration (else its frame count) may be approximate: the bar's total is a guess, its
    # position the decoded time; no total where neither is known (raw .h264)
    total_s = info.video_duration_s or (info.duration_s if info.num_frames > 0 else None)
    bar = tqdm(total=round(total_s, 1) if total_s else None, unit="s", desc=Path(path).name[:30], disable=not progress,
               file=sys.stderr, bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.0f}/{total:.0f} s of video "
                                           "[{elapsed}<{remaining}, {rate_fmt}]")

    def greys():
        samples = iter_grey_samples(path, fc.sample_hz, fc.work_width_px, info, decoder=fc.decoder, stats=stats)
        for t, g in _in_blocks(samples, DECODE_BLOCK_SAMPLES):
            if times:
                bar.update(t - times[-1])   # flow has finished the pairs before this sample
            times.append(t)
            yield g

    labeler = FlowLabeler(cfg)
    eff_hz = min(fc.sample_hz, info.fps_hz)
    try:
        rates = labeler.yaw_rates_from_grey(greys(), eff_hz)
        if bar.total is not None and not stats.get("incomplete"):
            bar.update(max(bar.total - bar.n, 0.0))   # the last pair is done (the frame count's duration runs 1 frame on)
    finally:
        bar.close()
    t = np.asarray(times)
    if len(t) < 2:
        raise VideoError(path, f"too short: {len(t)} frame(s) at {eff_hz:g} Hz, at least 2 are needed")
    inc = rates / eff_hz
    quality = labeler.last_quality
    windows = []
    tol = 0.5 / eff_hz
    mid = 0.5 * (t[:-1] + t[1:])
    for s, e in window_starts(float(t[-1]), window_s, stride_s, tol):
        # each pair counts in the window that holds its midpoint: a window starting between two samples sums
        # window_s of pairs, not one more (both ends inclusive summed 4.1 s for [0.25, 4.25] at 10 Hz)
        sel = (mid >= s) & (mid < e)
        yaw = float(inc[sel].sum())
        # the threshold of the window asked for, also for the one short window of a shorter video (as before:
        # scaling it to the shorter span would change the labels of short clips at the default window)
        cmd, conf = command_from_yaw(yaw, cfg.command, window_s)
        q = window_quality(quality[sel])
        windows.append(WindowLabel(round(s, 3), round(min(e, float(t[-1])), 3), cmd, yaw, conf * q, q))
    return VideoLabels(info, eff_hz, t, inc, quality, windows, stats, list(labeler.last_foe_sources))
