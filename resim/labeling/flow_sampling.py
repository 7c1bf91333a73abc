"""Flow sampling for the yaw labeler (resim/labeling/flow.py, steps 1-2): frames -> flow samples of each frame pair.

Frames are read by media's video reader (resim/media/video.py) and resized to the working width with square pixels as each
one is decoded (``prepare_frame``, ``iter_grey_samples``); DIS optical flow (OpenCV; a new
object per video, each pair warm-started from the previous pair's flow) is read on a grid that leaves out the masked
top and bottom bands, and points are dropped where the image is flat (Shi-Tomasi texture), nothing moves, the flow is
implausibly large or the photometric check fails. ``FlowSampling`` is a mixin of ``FlowLabeler`` (resim/labeling/flow.py):
it uses the labeler's ``flow_cfg``, ``_dis``, ``_prev_flow`` and ``_grid_cache`` (``__init__``, ``_start_video``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from resim.media.video import iter_samples
from resim.media.video_probe import VideoInfo

_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}


def prepare_frame(frame: np.ndarray, work_width_px: int, pixel_aspect: float = 1.0, bgr: bool = False) -> np.ndarray:
    """RGB (or BGR with ``bgr=True``) uint8 (H, W, 3), or grey (H, W) -> grey uint8, ``work_width_px`` wide.

    ``pixel_aspect`` is the sample aspect ratio (width/height of one stored pixel), e.g. 64/45
    for anamorphic PAL; the output has square pixels so that one focal length fits both axes.
    Large reductions go linear to twice the target, then area-average (cheaper than one area
    resize of a 720p frame, and still averages 2x2 at the end).
    """
    if frame.ndim == 3:
        h, w = frame.shape[:2]
    elif frame.ndim == 2:
        h, w = frame.shape
    else:
        raise ValueError(f"frame must be (H, W, 3) or (H, W), got shape {frame.shape}")
    out_h = max(8, int(round(work_width_px * h / (w * pixel_aspect))))
    if frame.ndim == 2 and (out_h, work_width_px) == (h, w):
        return frame                     # already grey at the working size: no copy
    if w > 3 * work_width_px:
        frame = cv2.resize(frame, (2 * work_width_px, 2 * out_h), interpolation=cv2.INTER_LINEAR)
    small = cv2.resize(frame, (work_width_px, out_h), interpolation=cv2.INTER_AREA)
    if small.ndim == 3:
        small = cv2.cvtColor(small, cv2.COLOR_BGR2GRAY if bgr else cv2.COLOR_RGB2GRAY)
    return small


def iter_grey_samples(path: str | Path, sample_hz: float, work_width_px: int,
                      info: VideoInfo | None = None, use_luma: bool = True,
                      decoder: str = "auto", stats: dict | None = None) -> Iterator[tuple[float, np.ndarray]]:
    """Yield (t_s, grey uint8 at working width, square pixels) for frames sampled at ``sample_hz``: media's reader
    (``resim.media.video.iter_samples``: decoders, sampling, ``stats``; raises VideoError on undecodable input), each
    sample shrunk by ``prepare_frame`` as it is decoded."""
    def prepare(frame: np.ndarray, pixel_aspect: float) -> np.ndarray:
        # the reader's frame: the luma plane (H, W), or BGR (H, W, 3) where OpenCV cannot hand over the plane
        return prepare_frame(frame, work_width_px, pixel_aspect, bgr=True)

    return iter_samples(path, sample_hz, prepare, info, use_luma, decoder, stats)


@dataclass
class _PairData:
    """Flow samples of one frame pair (coordinates relative to the principal point, pixels)."""

    x: np.ndarray
    y: np.ndarray
    u: np.ndarray
    v: np.ndarray
    w: np.ndarray       # prior weight (texture)


class FlowSampling:
    """Frames -> flow samples per pair (``_pair``) on a grid (``_grid``) with texture weights (``_texture``)."""

    def _make_dis(self):
        fc = self.flow_cfg
        dis = cv2.DISOpticalFlow_create(_PRESETS[fc.flow_preset])
        if fc.dis_finest_scale is not None:
            dis.setFinestScale(fc.dis_finest_scale)
        if fc.dis_patch_size is not None:
            dis.setPatchSize(fc.dis_patch_size)
        if fc.dis_patch_stride is not None:
            dis.setPatchStride(fc.dis_patch_stride)
        if fc.dis_grad_iters is not None:
            dis.setGradientDescentIterations(fc.dis_grad_iters)
        if fc.dis_var_iters is not None:
            dis.setVariationalRefinementIterations(fc.dis_var_iters)
        return dis

    # ---------------------------------------------------------------- per frame / per pair
    def focal_px(self, width_px: int) -> float:
        return (width_px / 2.0) / math.tan(math.radians(self.flow_cfg.hfov_deg) / 2.0)

    def _grid(self, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
        key = (h, w)
        if key not in self._grid_cache:
            fc = self.flow_cfg
            s = fc.grid_step_px
            r0 = max(s // 2, int(math.ceil(fc.mask_top_frac * h)))
            r1 = min(h - s // 2, int(math.floor((1.0 - fc.mask_bottom_frac) * h)))
            rows = np.arange(r0, r1, s)
            cols = np.arange(s // 2, w - s // 2, s)
            yy, xx = np.meshgrid(rows, cols, indexing="ij")
            self._grid_cache[key] = (yy.ravel(), xx.ravel())
        return self._grid_cache[key]

    def _texture(self, grey: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        # Shi-Tomasi measure: the smaller eigenvalue of the structure tensor; flow along an
        # edge (or in flat regions) is ambiguous, so weak points get low weight.
        # (OpenCV normalises 8-bit input; sqrt(.)*1000 is ~ a gradient in grey levels per pixel)
        ev = cv2.cornerMinEigenVal(grey, 3, 3)
        return np.sqrt(np.maximum(ev.ravel()[rows * grey.shape[1] + cols], 0.0)) * 1000.0

    def _pair(self, g0: np.ndarray, g1: np.ndarray, tex0: np.ndarray) -> _PairData:
        fc = self.flow_cfg
        h, w = g0.shape
        rows, cols = self._grid(h, w)
        # warm start (``dis_warm_start``): OpenCV's DIS takes a flow of the right size as a per-patch candidate at every
        # scale and keeps it where it matches better than its own; the output overwrites it, which is fine here
        init = self._prev_flow if self.flow_cfg.dis_warm_start else None
        flow = self._dis.calc(g0, g1, init)
        self._prev_flow = flow
        flat = rows * w + cols
        uv = flow.reshape(-1, 2)[flat]
        u, v = uv[:, 0].astype(np.float64), uv[:, 1].astype(np.float64)
        # photometric check: g1 sampled where the flow says each grid point went must look like g0 there
        # (large motions near the bottom and occlusions fail it; DIS has no confidence output)
        to = (np.clip(np.rint(rows + v), 0, h - 1).astype(np.intp) * w
              + np.clip(np.rint(cols + u), 0, w - 1).astype(np.intp))
        photo = np.abs(g1.ravel()[to].astype(np.int16) - g0.ravel()[flat].astype(np.int16))
        mag2 = u * u + v * v
        textured = tex0 >= fc.min_texture
        # ego motion, moving or not (the fit below drops static points): enough texture to tell, else nan
        self._motion.append(float(np.sqrt(np.median(mag2[textured]))) if textured.mean() >= 0.05 else float("nan"))
        keep = (textured & (mag2 >= fc.static_flow_px ** 2)
                & (mag2 <= (fc.max_flow_frac * w) ** 2) & (photo <= fc.max_photo_err))
        x = cols[keep] - (w - 1) / 2.0
        y = rows[keep] - (h - 1) / 2.0
        return _PairData(x=x.astype(np.float64), y=y.astype(np.float64), u=u[keep], v=v[keep],
                         w=np.maximum(np.minimum(tex0[keep] / (4.0 * fc.min_texture), 1.0), 1e-3))

    @staticmethod
    def _stack(pairs: list[_PairData]) -> tuple[np.ndarray, ...]:
        """Pairs' samples as (P, N) arrays X, Y, U, V, W0, zero-padded (W0 = 0 marks padding)."""
        P, N = len(pairs), max(1, max(len(d.x) for d in pairs))
        X, Y, U, V, W0 = (np.zeros((P, N)) for _ in range(5))
        for i, d in enumerate(pairs):
            k = len(d.x)
            X[i, :k], Y[i, :k], U[i, :k], V[i, :k], W0[i, :k] = d.x, d.y, d.u, d.v, d.w
        return X, Y, U, V, W0
