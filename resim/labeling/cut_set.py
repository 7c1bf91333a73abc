"""A labelled set of shot boundaries built from real driving clips: hard cuts, fades through black and
dissolves, at known frames (for measuring scene-cut detectors: ``lab/scene_cuts.py``, tests).

Segments of 1.6-3 s are taken from the given clips at random starts (two segments of one clip at different
times are a cut too: an edited drive) and joined by one kind of transition each:

* ``hard``: the next segment's first frame follows the last one's: the boundary is that first frame;
* ``fade``: the last ``fade_frames`` of a segment darken to black, the next segment's first ``fade_frames``
  brighten from black; the boundary interval spans both;
* ``dissolve``: ``dissolve_frames`` frames cross-fade from one segment into the next.

Inside a segment the video is continuous (camera motion, shadows, bridges: the hard negatives).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

KINDS = ("hard", "fade", "dissolve")


@dataclass(frozen=True)
class Boundary:
    kind: str
    first: int      # first frame index of the transition (hard: the new shot's first frame)
    last: int       # last frame index of the transition (hard: == first)


def build_cut_video(clips: list[np.ndarray], kind: str, num_cuts: int, seed: int = 0, fade_frames: int = 6,
                    dissolve_frames: int = 10, min_len: int = 40, max_len: int = 75) -> tuple[np.ndarray, list[Boundary]]:
    """(frames ``(T, H, W, 3)`` uint8, boundaries): ``num_cuts + 1`` segments of ``clips`` (each ``(T_i, H, W, 3)``
    uint8, one size) joined by ``kind`` transitions."""
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    rng = np.random.default_rng(seed)
    segs = []
    prev = None
    for _ in range(num_cuts + 1):
        while True:    # never the same clip at an overlapping time: that would be no cut at all
            c = int(rng.integers(len(clips)))
            n = int(rng.integers(min_len, max_len + 1))
            s = int(rng.integers(0, len(clips[c]) - n))
            if prev is None or prev[0] != c or abs(prev[1] - s) > max_len + 25:
                break
        segs.append(clips[c][s:s + n].astype(np.float32))
        prev = (c, s)
    out, bounds = [segs[0]], []
    t = len(segs[0])
    for seg in segs[1:]:
        if kind == "hard":
            bounds.append(Boundary(kind, t, t))
            out.append(seg)
            t += len(seg)
        elif kind == "fade":
            k = fade_frames
            ramp = np.linspace(1.0, 0.0, k + 1)[1:, None, None, None]           # to black over k frames
            out[-1] = out[-1].copy()
            out[-1][-k:] *= ramp
            seg = seg.copy()
            seg[:k] *= ramp[::-1]                                              # from black
            bounds.append(Boundary(kind, t - k, t + k - 1))
            out.append(seg)
            t += len(seg)
        else:
            k = dissolve_frames
            a = np.linspace(0.0, 1.0, k + 2)[1:-1, None, None, None]
            tail = out[-1][-k:]
            mix = (1 - a) * tail + a * seg[:k]
            out[-1] = out[-1][:-k]
            out.append(mix)
            out.append(seg[k:])
            bounds.append(Boundary(kind, t - k, t - 1))
            t += len(seg) - k
    return np.clip(np.concatenate(out), 0, 255).astype(np.uint8), bounds


def score(detected: list[int], bounds: list[Boundary], tolerance_frames: int = 1) -> dict:
    """Precision / recall: a detection hits a boundary when it lies in ``[first - tol, last + tol]``; each
    boundary counts once (a second detection inside the same transition, e.g. both ends of a fade, is neither
    a hit nor a false positive: a clip across either is dropped alike); every other detection is a false
    positive."""
    hit = [False] * len(bounds)
    fp = 0
    for d in detected:
        inside = [i for i, b in enumerate(bounds) if b.first - tolerance_frames <= d <= b.last + tolerance_frames]
        if not inside:
            fp += 1
        for i in inside:
            hit[i] = True
    tp = sum(hit)
    return {"tp": tp, "fp": fp, "fn": len(bounds) - tp,
            "precision": tp / (tp + fp) if tp + fp else 1.0, "recall": tp / len(bounds) if bounds else 1.0}
