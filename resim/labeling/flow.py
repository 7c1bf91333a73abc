"""Ego yaw from monocular video by dense optical flow.

ReSim pseudo-labels OpenDV's uncalibrated YouTube videos with "Turning left / Moving
forward / Turning right" from OpenCV flow. This module estimates the per-frame-pair
yaw rate robustly:

1. Frames are resized to ``work_width_px`` (display aspect), greyscale, histogram-equalised,
   and DIS flow (OpenCV ``ultrafast`` down to finest scale 1 by default) is read on a grid.
2. Points are dropped where the image is flat (sky, plain asphalt: unreliable flow),
   in the masked bottom/top bands (hood, dashboard, overlays), and where nothing
   moves (burnt-in overlays, the hood).
3. Pinhole model, rotation fields about the image centre, focal length from the *assumed*
   horizontal field of view ``hfov_deg``. For small rotations the flow of a static point p = (x, y) is

       flow = yaw * A(p) + pitch * B(p) + roll * C(p) + s_p * (p - e)

   with the rotation fields A = (f + x^2/f, xy/f) (yaw, left +), B = (xy/f, f + y^2/f)
   (pitch), C = (-y, x) (roll), and a translational part that is radial from the
   focus of expansion e with an unknown per-point magnitude s_p = T/Z_p (depth).
   Taking the flow component perpendicular to (p - e) removes every depth unknown:

       cross(flow, p - e) = yaw * cross(A, p - e) + pitch * cross(B, p - e) + roll * cross(C, p - e)

   Linearised in a shift of e, (yaw, pitch, roll, e_x, e_y) is fitted *per frame pair* by
   Gauss-Newton with IRLS (Cauchy weights: other vehicles, bad flow). e must be free per pair:
   in a turn the camera moves along the chord and, ahead of the rear axle, sideways, so the FOE
   shifts towards the turn with the yaw rate; a fixed e reads that as 5-15 % extra yaw.
   Yaw information comes from points above/below the FOE (road, trees, posts).
   The per-pair FOE is then replaced by a pooled model (``foe_model="pooled"``, default): the car's kinematics put
   it at e_x = a - f k yaw, with a (the FOE of straight driving) and k (1/2 + lever arm / distance per pair)
   shared by many pairs and estimated from the per-pair fits (``_pool_add``, ``_pool_params``); rotation alone is
   re-fitted with that FOE. Per-pair FOE freedom lets flow errors trade yaw against e_x pair by pair.
   With the camera rig known (``camera_ahead_m``, ``camera_height_m``: synthetic, CARLA, logged fleets;
   not OpenDV), the FOE's x is not fitted but follows the car's kinematics, and only rotation is fitted
   (``FlowLabeler._fit_rig``): that removes the yaw / FOE-x trade-off, the main remaining error.
4. Heading change over a window = sum of the per-pair yaw.

Files: steps 1-2 (frames -> flow samples per pair) in resim/labeling/flow_sampling.py (``FlowSampling``, ``prepare_frame``),
step 3 (the fits) in resim/labeling/flow_fit.py (``MotionFit``); ``FlowLabeler`` here combines the two (mixins: their
methods and the per-video state stay on the labeler), keeps the per-video state and holds the public API.

The field-of-view assumption scales the estimate roughly by tan(hfov/2): see
docs/labeling.md for how much it matters.
"""
from __future__ import annotations

from typing import Iterable

import cv2
import numpy as np

from resim.labeling.commands import FlowLabel, command_from_yaw
from resim.labeling.config import FlowConfig, LabelerConfig
from resim.labeling.flow_fit import MotionFit
from resim.labeling.flow_sampling import FlowSampling, _PairData, prepare_frame


class FlowLabeler(FlowSampling, MotionFit):
    """Callable labeler: frames -> per-pair yaw rates, or a window -> ``FlowLabel``.

    ``yaw_rates_deg(frames, fps_hz)`` returns (N-1,) yaw *rates* in deg/s (left +),
    one per consecutive pair of the frames given (the caller samples them, e.g. at
    10 Hz); the heading change over the frames is ``rates.sum() / fps_hz``.
    """

    def __init__(self, cfg: LabelerConfig | FlowConfig | None = None):
        if cfg is None:
            cfg = LabelerConfig()
        self.cfg = cfg if isinstance(cfg, LabelerConfig) else LabelerConfig(flow=cfg)
        fc = self.cfg.flow
        self.flow_cfg = fc
        self._clahe = cv2.createCLAHE(clipLimit=3.0, tileGridSize=(4, 4))
        self._grid_cache: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
        self.last_quality: np.ndarray | None = None   # per-pair share of points kept by the fit
        self.last_motion_px: np.ndarray | None = None  # per-pair median flow of textured points (px), nan: no texture
        self.last_foe: tuple[float, float] | None = None
        self.last_foe_per_pair: np.ndarray | None = None   # (N-1, 2) px from the image centre
        self.last_distance_over_height: np.ndarray | None = None   # (N-1,) d/h per pair, known rig only (else nan)
        self.last_foe_sources: list[str] = []   # per chunk: "rig", "pooled" or "per_pair" (what placed the FOE)
        self.last_rates_deg_s: np.ndarray | None = None   # (N-1,) the yaw rate per pair the last label summed
        self._start_video(10.0)

    def _start_video(self, fps_hz: float) -> None:
        """Per-video state, reset at the start of every video (``yaw_rates_from_grey``)."""
        self._fps_hz = fps_hz
        self._results: list[tuple] = []     # per chunk: (yaw rad (P,), kept (P,), FOE (P, 2), source)
        self._dhs: list[np.ndarray] = []
        self.last_foe_model: tuple[float, float] | None = None   # "pooled": (a px, k) of the last chunk
        # pooled FOE model: per chunk (FOE x, evidence) of its straight pairs, and (FOE x, yaw, evidence) of all pairs
        self._straight: list[tuple[np.ndarray, np.ndarray]] = []
        self._pool: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._pending: list[tuple] = []     # pooled FOE: chunks waiting for enough straight driving
        self._prev_flow: np.ndarray | None = None   # the last pair's flow (DIS warm start)
        self._motion: list[float] = []      # per pair: median flow of the textured grid points (px), nan if too few
        # a new DIS per video: OpenCV keeps the last input flow's pyramid (initial_Ux/Uy, the warm start) inside the
        # object and tries it on every later call, even without an input flow (collectGarbage does not clear it),
        # so the first pair of a video would start from the previous video's flow, and read a buffer of the wrong
        # size if that video's frames were larger
        self._dis = self._make_dis()

    # ---------------------------------------------------------------- public API
    def yaw_rates_from_grey(self, greys: Iterable[np.ndarray], fps_hz: float) -> np.ndarray:
        """Greyscale frames already at working resolution (see ``prepare_frame``) -> (N-1,) deg/s, left +."""
        if fps_hz <= 0:
            raise ValueError(f"fps_hz must be > 0, got {fps_hz}")
        fc = self.flow_cfg
        chunk: list[_PairData] = []
        e = (0.0, 0.0)
        self._start_video(fps_hz)
        prev = prev_tex = None
        f = n_grid = None
        for g in greys:
            if fc.contrast == "equalize":
                g = cv2.equalizeHist(g)
            elif fc.contrast == "clahe":
                g = self._clahe.apply(g)
            if prev is not None and g.shape != prev.shape:
                raise ValueError(f"frame size changed from {prev.shape} to {g.shape}")
            h, w = g.shape
            rows, cols = self._grid(h, w)
            if f is None:
                f, n_grid = self.focal_px(w), len(rows)
            tex = self._texture(g, rows, cols)
            if prev is not None:
                chunk.append(self._pair(prev, g, prev_tex))
                if len(chunk) >= fc.chunk_pairs:
                    e = self._solve_chunk(chunk, n_grid, f, e)
                    chunk = []
            prev, prev_tex = g, tex
        if chunk:
            e = self._solve_chunk(chunk, n_grid, f, e)
        res, self._results, self._pending = self._results, [], []
        self.last_foe = e
        self.last_foe_per_pair = np.concatenate([r[2] for r in res]) if res else np.zeros((0, 2))
        self.last_distance_over_height = np.concatenate(self._dhs) if self._dhs else np.zeros(0)
        self.last_quality = np.concatenate([r[1] for r in res]) if res else np.zeros(0)
        # per pair: median flow magnitude (px at the working width) of the textured grid points, moving or not:
        # ~0 when the car stands still, NaN where too little texture to tell (see ``ego_motion_pct_s``)
        self.last_motion_px = np.asarray(self._motion, np.float64)
        self.last_foe_sources = [r[3] for r in res]
        self.last_rates_deg_s = np.degrees(np.concatenate([r[0] for r in res])) * fps_hz if res else np.zeros(0)
        return self.last_rates_deg_s

    def yaw_rates_deg(self, frames: Iterable[np.ndarray], fps_hz: float, pixel_aspect: float = 1.0) -> np.ndarray:
        """RGB uint8 frames (H, W, 3), consecutive at ``fps_hz`` -> (N-1,) yaw rate per pair, deg/s, left +.

        Heading change over the frames = ``rates.sum() / fps_hz`` degrees.
        """
        w = self.flow_cfg.work_width_px
        return self.yaw_rates_from_grey((prepare_frame(fr, w, pixel_aspect) for fr in frames), fps_hz)

    def label(self, frames: Iterable[np.ndarray], fps_hz: float, pixel_aspect: float = 1.0) -> FlowLabel:
        """One window of frames (RGB uint8, at ``fps_hz``) -> FlowLabel(command, yaw_deg, confidence)."""
        rates = self.yaw_rates_deg(frames, fps_hz, pixel_aspect)
        if len(rates) == 0:
            raise ValueError("label() needs at least two frames")
        return self.label_from_rates(rates, fps_hz, self.last_quality)

    def label_from_rates(self, rates_deg_s: np.ndarray, fps_hz: float,
                         quality: np.ndarray | None = None) -> FlowLabel:
        yaw = float(np.sum(rates_deg_s) / fps_hz)
        cmd, conf = command_from_yaw(yaw, self.cfg.command)
        q = window_quality(quality)
        return FlowLabel(command=cmd, yaw_deg=yaw, confidence=conf * q, quality=q)


def window_quality(kept: np.ndarray | None) -> float:
    """Flow quality of a window in [0, 1] from the per-pair share of grid points kept as inliers.

    A pair keeping >= 25 % of its grid is fully trusted (sky and masks alone remove ~half).
    """
    if kept is None or len(kept) == 0:
        return 1.0
    return float(np.clip(np.median(kept) / 0.25, 0.0, 1.0))


def ego_motion_pct_s(motion_px: np.ndarray, width_px: int, fps_hz: float) -> float:
    """A window's ego motion from the labeler's per-pair ``last_motion_px``: the median over its pairs, in %
    of the frame width per second (resolution-free). NaN when most pairs had too little texture to tell: a car
    moving through fog or along a blank wall is not taken for one standing still."""
    m = np.asarray(motion_px, np.float64)
    if m.size == 0 or np.isnan(m).mean() > 0.5:
        return float("nan")
    return float(np.nanmedian(m) / width_px * 100.0 * fps_hz)
