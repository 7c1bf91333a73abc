"""Scene cuts (shot boundaries) in driving video: where an edited upload jumps to another shot.

A 49-frame clip that spans a cut teaches a world model teleportation, so the pipeline never cuts a clip
across one (``resim/pipeline/stages/label.py``). Detectors (``CutConfig.method``), picked by measurement on a
labelled set of hard cuts, fades and dissolves built from real dashcam clips, at the 10 Hz the label stage
sees uploads at (``lab/scene_cuts.py``; docs/pipeline.md "Scene cuts"):

* ``flow`` (default): ours: a cut is a pair whose photometric residual after warping by DIS optical flow (the
  labeler's flow method, computed again here on 64-px frames: at the labeler's 256-px width this detector
  caught fewer dissolves, 0.63 against 0.87 on the tuning seeds, and cost 3x more) is a local peak above 3x its neighbours' median and at least 0.05: flow explains camera
  motion, shadows and fades, not a new scene. Held out: precision 1.00, recall 1.00 on hard cuts and fades,
  0.78 on dissolves; ~18 % of the labeler's cost;
* ``content``, ``adaptive``, ``histogram``, ``hash``: PySceneDetect's detectors (the maintained library
  cosmos-curate's and Open-Sora's pipelines start from), fed frame by frame, so no second decode. At 10 Hz
  the histogram detector fires on shadows and bridges (precision 0.91), the others miss dissolves;
* ``flow+histogram``: both (a cut where either fires); ``none`` (not "off": YAML reads that as false).

Frames are RGB uint8 at any size (resized to ``width_px`` first). Returns the indices of the first frame of
each new shot.
"""
from __future__ import annotations

from typing import Iterable

import cv2
import numpy as np

from resim.config import ConfigError
from resim.labeling.config import CUT_METHODS as METHODS, CutConfig

__all__ = ["METHODS", "CutConfig", "CutDetector", "detect_cuts", "flow_residuals"]


def _scenedetect(method: str, threshold: float | None, min_len: int):
    # optional import: only the PySceneDetect methods need it (the default, "flow", does not)
    try:
        from scenedetect.detectors import AdaptiveDetector, ContentDetector, HashDetector, HistogramDetector
    except ImportError as e:
        raise ConfigError(f"labels.cuts.method={method} needs PySceneDetect (pip install 'scenedetect>=0.6.4', "
                          f"part of resim[pipeline]): {e}") from None

    kw = {"min_scene_len": max(1, min_len)}
    if method == "content":
        return ContentDetector(**({"threshold": threshold} if threshold else {}), **kw)
    if method == "adaptive":
        return AdaptiveDetector(**({"adaptive_threshold": threshold} if threshold else {}), **kw)
    if method == "histogram":
        return HistogramDetector(**({"threshold": threshold} if threshold else {}), **kw)
    return HashDetector(**({"threshold": threshold} if threshold else {}), **kw)


class CutDetector:
    """Streaming detection: ``push`` every frame as it is decoded (the label stage feeds the flow the same
    pass), ``finish`` returns the cuts. Memory: one small frame and one float per pair."""

    def __init__(self, cfg: CutConfig, fps_hz: float):
        self.cfg, self.n = cfg, 0
        self.min_len = int(round(cfg.min_shot_s * fps_hz))
        self.cuts: list[int] = []
        self.det = None
        if cfg.method not in ("none", "flow"):
            self.det = _scenedetect(cfg.method, cfg.threshold, self.min_len)
        self.residuals = _FlowResiduals() if cfg.method in ("flow", "flow+histogram") else None
        if cfg.method == "flow+histogram":
            self.det = _scenedetect("histogram", None, self.min_len)

    def push(self, frame: np.ndarray) -> None:
        """One RGB uint8 frame, in order."""
        if self.det is not None or self.residuals is not None:
            small = _resize(frame, self.cfg.width_px)
            if self.det is not None:
                self.cuts.extend(self.det.process_frame(self.n, np.ascontiguousarray(small[..., ::-1])))
            if self.residuals is not None:
                self.residuals.push(small)
        self.n += 1

    def finish(self) -> list[int]:
        """Indices of the first frame of every new shot."""
        if self.det is not None and self.n:
            self.cuts.extend(self.det.post_process(self.n - 1))
        if self.residuals is not None:
            self.cuts.extend(_peaks(np.asarray(self.residuals.out), self.cfg.threshold or FLOW_RATIO, self.min_len))
        both = sorted({int(c) for c in self.cuts if 0 < int(c) < self.n})
        return [c for i, c in enumerate(both) if i == 0 or c - both[i - 1] >= max(1, self.min_len)]


def detect_cuts(frames: Iterable[np.ndarray], fps_hz: float, cfg: CutConfig) -> list[int]:
    """Indices of the first frame of every new shot in ``frames`` (RGB uint8 ``(H, W, 3)``, consecutive at
    ``fps_hz``)."""
    det = CutDetector(cfg, fps_hz)
    for f in frames:
        det.push(f)
    return det.finish()


def _resize(f: np.ndarray, width_px: int) -> np.ndarray:
    if f.shape[1] == width_px:
        return f
    h = max(2, int(round(f.shape[0] * width_px / f.shape[1])))
    return cv2.resize(f, (width_px, h), interpolation=cv2.INTER_AREA)


FLOW_RATIO = 3.0      # a cut: the pair's residual over the median of its 24 neighbours (lab/scene_cuts.py)
# and at least this residual: a frozen stretch (the car standing, identical frames) has neighbours of ~0, so
# the codec's flicker would otherwise be a "cut"; continuous driving is ~0.025 (median), cuts ~0.2-0.7
FLOW_MIN_RESIDUAL = 0.05


class _FlowResiduals:
    """Per consecutive pair: mean |g0 - g1 warped back by DIS flow| over the mean gradient of g0 (scale-free).
    A new scene leaves a residual no flow can explain; camera motion, shadows and fades mostly do not."""

    def __init__(self):
        self.dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST)
        self.prev, self.grid, self.out = None, None, []

    def push(self, frame: np.ndarray) -> None:
        g = cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY)
        if self.prev is not None and g.shape == self.prev.shape:
            h, w = g.shape
            flow = self.dis.calc(self.prev, g, None)
            if self.grid is None:
                ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
                self.grid = (xs, ys)
            warped = cv2.remap(g, self.grid[0] + flow[..., 0], self.grid[1] + flow[..., 1], cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_REPLICATE)
            res = float(np.abs(warped.astype(np.float32) - self.prev.astype(np.float32)).mean())
            grad = float(np.abs(cv2.Sobel(self.prev, cv2.CV_32F, 1, 0)).mean()
                         + np.abs(cv2.Sobel(self.prev, cv2.CV_32F, 0, 1)).mean())
            self.out.append(res / (grad + 1.0))
        self.prev = g


def flow_residuals(frames: Iterable[np.ndarray]) -> np.ndarray:
    """``(N-1,)`` flow residuals of consecutive RGB frames (see ``_FlowResiduals``)."""
    r = _FlowResiduals()
    for f in frames:
        r.push(f)
    return np.asarray(r.out, np.float64)


def _peaks(r: np.ndarray, ratio: float, min_len: int, half_window: int = 12) -> list[int]:
    """Frames ``i + 1`` where pair ``i``'s residual is a local maximum above ``ratio`` x its neighbours' median."""
    cuts: list[int] = []
    for i in range(len(r)):
        nb = np.concatenate([r[max(0, i - half_window):i], r[i + 1:i + 1 + half_window]])
        base = float(np.median(nb)) if len(nb) else 0.0
        if r[i] > max(ratio * base, FLOW_MIN_RESIDUAL) and r[i] >= max(r[max(0, i - 2):i + 3]):
            if not cuts or i + 1 - cuts[-1] >= max(1, min_len):
                cuts.append(i + 1)
    return cuts
