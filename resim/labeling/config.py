"""Typed configuration of the labeler: flow estimator + command rules.

Two parts, each validated on load with ``resim.config``:

* ``FlowConfig``: how ego yaw is estimated from video (working resolution, assumed
  field of view, DIS preset, masks, robust-fit settings).
* ``CommandConfig``: how a heading change (from flow) or a trajectory (from poses)
  becomes one of ``resim.shards.schema.COMMANDS``.

Thresholds marked *calibrated* were chosen by ``lab/calibrate_labeler.py`` on the
synthetic world's ground truth; docs/labeling.md has the numbers.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Literal, Optional

from resim.config import ConfigError, from_dict


def _check_finite(cfg) -> None:
    """Every float field of ``cfg`` (None allowed where the field is optional) is finite."""
    for f in fields(cfg):
        v = getattr(cfg, f.name)
        if isinstance(v, float) and not math.isfinite(v):
            raise ConfigError(f"{f.name} must be finite, got {v}")


@dataclass
class FlowConfig:
    """Optical-flow yaw estimator (``resim.labeling.flow.FlowLabeler``)."""

    sample_hz: float = 10.0          # frames are sampled at this rate before flow (ReSim: 10 Hz)
    decoder: Literal["auto", "pyav", "opencv"] = "auto"   # video files (resim label): PyAV when installed
    #                                  (luma plane, no deblocking, non-reference frames skipped; resim/media/video.py)
    work_width_px: int = 256         # frames are resized to this width (display aspect kept) before flow
    hfov_deg: float = 80.0           # ASSUMED horizontal field of view (OpenDV is uncalibrated); yaw scales
    #                                  ~ with tan(hfov/2): reads tan(true/2)/tan(80/2) x the truth
    flow_preset: Literal["ultrafast", "fast", "medium"] = "ultrafast"   # cv2.DISOpticalFlow preset
    dis_finest_scale: int | None = 1  # DIS overrides (None = the preset's). ultrafast stops at scale 2 (a
    #                                   64 px flow field at 256 px); scale 1 halves the yaw error
    dis_warm_start: bool = True      # each pair's DIS starts from the previous pair's flow (OpenCV's input flow: a
    #                                  candidate per patch at every scale, kept where it matches better); the flow
    #                                  of a car's camera changes little in 0.1 s. Median window error on the
    #                                  synthetic world 0.95/1.51/1.30 -> 0.81/1.10/1.01 deg (`default`, seeds
    #                                  11/14/16) for ~12 % more DIS CPU
    #                                  (docs/lab/2026-11-22-labeler-calibration.md, "Sixth look")
    dis_patch_size: int | None = None
    dis_patch_stride: int | None = None
    dis_grad_iters: int | None = None
    dis_var_iters: int | None = None
    grid_step_px: int = 6            # flow is read on a grid with this spacing (working-resolution pixels)
    mask_top_frac: float = 0.0       # rows ignored at the top (overlays)
    mask_bottom_frac: float = 0.12   # rows ignored at the bottom (hood / dashboard)
    min_texture: float = 5.0         # sqrt(min eigenvalue of the 3x3 structure tensor) x 1000 (OpenCV's
    #                                  normalisation; ~grey levels per pixel); flat
    #                                  regions (sky, plain asphalt) give unreliable flow
    static_flow_px: float = 0.05     # points moving less than this are ignored (burnt-in overlays, hood)
    max_flow_frac: float = 0.08      # points moving more than this share of the width per pair are dropped
    max_photo_err: int = 24          # grey-level difference after following the flow (occlusion/bad flow)
    robust_scale_px: float = 0.3     # lower bound on the Cauchy scale of the IRLS fit (pixels of flow)
    irls_iters: int = 2              # rotation-only IRLS steps (the first one starts from the running FOE)
    foe_iters: int = 3               # further Gauss-Newton + IRLS steps of the joint rotation + per-pair FOE fit
    foe_prior: float = 1e-7          # weight pulling each pair's FOE to the running FOE, per unit of fit weight;
    #                                  must be weak: yaw and the FOE's x are only separable through depth
    #                                  variation, and 1e-4 left half of the chord/lever-arm bias (flow.py)
    foe_model: Literal["pooled", "per_pair"] = "pooled"   # how the FOE's x is placed after the per-pair fit.
    #                                  "pooled": e_x = a - f k yaw, the car's kinematics with the camera's own
    #                                  straight-driving FOE a (mount yaw; median over the video's straight pairs)
    #                                  and k = 1/2 + L/d (chord + lever arm over distance per pair) regressed from
    #                                  the per-pair FOEs of the last foe_pool_pairs pairs; then rotation only.
    #                                  "per_pair": the free per-pair FOE (noisier: yaw trades against it). flow.py
    foe_pool_pairs: int = 300        # "pooled": trailing pairs whose per-pair FOEs give k (30 s at 10 Hz)
    straight_yaw_deg_s: float = 1.0  # "pooled": pairs whose yaw rate over +-0.5 s is below this give a
    foe_straight_pool_pairs: int = 3000   # "pooled": a is the median over at most this many trailing straight pairs
    #                                  (5 min of straight driving at 10 Hz): bounded work per chunk on hour-long videos
    foe_min_straight_s: float = 3.0  # "pooled" needs this much straight driving seen (else the chunk keeps the
    #                                  per-pair fit): a short clip all in one curve has no straight FOE to pool
    foe_k_max: float = 5.0           # "pooled": k is clipped to [0, this] (L <= ~2.5 m ahead at d >= 0.5 m per pair)
    contrast: Literal["none", "equalize", "clahe"] = "equalize"   # global histogram equalisation of the
    #                                  working frame: dark/low-contrast scenes (night, fog, plain grass) keep
    #                                  texture for DIS and the texture gate (night off-road went 0.01 -> 0.4 quality)
    camera_ahead_m: float | None = None   # KNOWN rig only: camera ahead of the rear axle, metres. None (default,
    #                                  OpenDV: unknown) fits the FOE per pair. Set, the FOE's x follows the car's
    #                                  kinematics, e_x = -f yaw (1/2 + L/d), which removes the yaw / FOE-x trade-off
    #                                  (the main remaining error); a wrong L biases turns: ~ -6 % per +0.5 m (docs).
    #                                  Validated on the synthetic world only: on real freeway video the ground-plane
    #                                  distance per pair reads ~20x short
    #                                  (docs/labeling.md, "The known rig on fast footage")
    camera_height_m: float = 1.5     # with camera_ahead_m: camera height above the road (ground-plane distance d)
    rig_iters: int = 2               # with camera_ahead_m: (distance, FOE, rotation) re-fits per chunk
    chunk_pairs: int = 60            # pairs fitted together (batched); the running FOE prior is updated per chunk

    def __post_init__(self):
        _check_finite(self)   # NaN passes every `x <= 0` check below (a NaN sample_hz ended in a traceback)
        if self.sample_hz <= 0:
            raise ConfigError(f"sample_hz must be > 0, got {self.sample_hz}")
        if not 0 < self.max_flow_frac <= 1:
            raise ConfigError(f"max_flow_frac must be in (0, 1] (0 drops every point), got {self.max_flow_frac}")
        if not 0 <= self.max_photo_err <= 255:
            raise ConfigError(f"max_photo_err must be in [0, 255] grey levels, got {self.max_photo_err}")
        if self.min_texture < 0 or self.static_flow_px < 0 or self.robust_scale_px <= 0 or self.foe_prior < 0:
            raise ConfigError("min_texture >= 0, static_flow_px >= 0, robust_scale_px > 0 and foe_prior >= 0 "
                              "are required")
        if not 32 <= self.work_width_px <= 1920:
            raise ConfigError(f"work_width_px must be in [32, 1920], got {self.work_width_px}")
        if not 20.0 <= self.hfov_deg <= 150.0:
            raise ConfigError(f"hfov_deg must be in [20, 150], got {self.hfov_deg}")
        if self.grid_step_px < 1:
            raise ConfigError(f"grid_step_px must be >= 1, got {self.grid_step_px}")
        if not (0 <= self.mask_top_frac < 0.5 and 0 <= self.mask_bottom_frac < 0.5):
            raise ConfigError("mask_top_frac and mask_bottom_frac must be in [0, 0.5)")
        if self.camera_ahead_m is not None and not -1.0 <= self.camera_ahead_m <= 6.0:
            raise ConfigError(f"camera_ahead_m must be in [-1, 6] m (or None: unknown rig), got {self.camera_ahead_m}")
        if not 0.3 <= self.camera_height_m <= 5.0:
            raise ConfigError(f"camera_height_m must be in [0.3, 5] m, got {self.camera_height_m}")
        if self.foe_straight_pool_pairs < max(3, self.foe_min_straight_s * self.sample_hz):
            raise ConfigError(f"foe_straight_pool_pairs ({self.foe_straight_pool_pairs}) must hold foe_min_straight_s "
                              f"of straight pairs at sample_hz (>= {max(3, self.foe_min_straight_s * self.sample_hz):g})")
        if (self.foe_pool_pairs < 2 or self.straight_yaw_deg_s <= 0 or self.foe_k_max < 0
                or self.foe_min_straight_s < 0):
            raise ConfigError("foe_pool_pairs >= 2, straight_yaw_deg_s > 0, foe_k_max >= 0 and "
                              "foe_min_straight_s >= 0 are required")
        if self.rig_iters < 1:
            raise ConfigError(f"rig_iters must be >= 1, got {self.rig_iters}")
        if self.irls_iters < 1 or self.foe_iters < 0 or self.chunk_pairs < 2:
            raise ConfigError("irls_iters >= 1, foe_iters >= 0 and chunk_pairs >= 2 are required")


# The window the degree thresholds below are stated for: lab/calibrate_labeler.py calibrated them on 4-s
# windows (ReSim's future). Other windows scale them by window_s / this, so a steady yaw rate is a turn or not
# whatever the window (15.5 deg per 4 s = 3.875 deg/s); at 4 s the factor is exactly 1 (labels unchanged).
TURN_THRESHOLD_REF_WINDOW_S = 4.0


@dataclass
class CommandConfig:
    """Heading change / trajectory -> command."""

    window_s: float = 4.0                  # future window a command describes (ReSim: 40 frames at 10 Hz)
    turn_threshold_deg: float = 15.5       # calibrated (lab/calibrate_labeler.py, 48 synthetic episodes, seed 11): |heading change| >= this over a 4-s window is a turn; scaled to the window (turn_threshold_for)
    confidence_scale_deg: float = 4.0      # distance from the threshold at which confidence reaches ~0.88, over 4 s; scaled like the threshold
    # trajectory rule (common practice of nuScenes/NAVSIM planners: ST-P3, UniAD, VAD): the lateral
    # offset of the last waypoint in the ego frame; >= +2 m left, <= -2 m right. "heading" uses the
    # heading change at the horizon with turn_threshold_deg (same rule as flow); "either" fires on both.
    trajectory_rule: Literal["lateral_offset", "heading", "either"] = "lateral_offset"
    lateral_threshold_m: float = 2.0

    def __post_init__(self):
        _check_finite(self)
        if self.window_s <= 0:
            raise ConfigError(f"window_s must be > 0, got {self.window_s}")
        if not 0 < self.turn_threshold_deg < 180:
            raise ConfigError(f"turn_threshold_deg must be in (0, 180), got {self.turn_threshold_deg}")
        if self.confidence_scale_deg <= 0 or self.lateral_threshold_m <= 0:
            raise ConfigError("confidence_scale_deg and lateral_threshold_m must be > 0")

    def window_factor(self, window_s: float | None = None) -> float:
        """Scale of the degree thresholds for a window of ``window_s`` (default: this config's window_s)."""
        return (self.window_s if window_s is None else window_s) / TURN_THRESHOLD_REF_WINDOW_S

    def turn_threshold_for(self, window_s: float | None = None) -> float:
        """|heading change| in degrees that is a turn over a window of ``window_s`` (default: window_s)."""
        return self.turn_threshold_deg * self.window_factor(window_s)

    @property
    def turn_rate_threshold_deg_s(self) -> float:
        """The turn threshold as a steady yaw rate, deg/s: the same at every window."""
        return self.turn_threshold_deg / TURN_THRESHOLD_REF_WINDOW_S


@dataclass
class LabelerConfig:
    flow: FlowConfig = field(default_factory=FlowConfig)
    command: CommandConfig = field(default_factory=CommandConfig)


PRESETS: dict[str, dict] = {
    "default": {},
    # higher-quality flow at about 4x the flow cost (still far below decoding at 720p)
    # DIS medium: about 3x the flow cost of the default (4.5 vs 1.5 ms per 256 px pair), median yaw error
    # 0.94 vs 1.16 deg on the synthetic world (seed 11, 2026-11-22: docs/lab/2026-11-22-labeler-calibration.md)
    "accurate": {"flow": {"flow_preset": "medium", "dis_finest_scale": None, "irls_iters": 3, "foe_iters": 6}},
    # throughput: 160 px working width (DIS at 80x45 instead of 128x72) and one rotation-only IRLS step;
    # about half the labeler's own CPU per frame, median yaw error worse on the synthetic world, command
    # accuracy about the same (docs/labeling.md, "Held-out accuracy on the synthetic world";
    # bench/label_throughput.py)
    # no DIS warm start: it costs ~0.05 ms per frame here (+1.5 % of b/a', which `fast` has little of to spare) and
    # moved `fast`'s command accuracy by -3 ... +4 windows per world for a 0.0-0.25 deg better median
    # (docs/lab/2026-11-22-labeler-calibration.md, "Sixth look")
    "fast": {"flow": {"work_width_px": 160, "grid_step_px": 4, "irls_iters": 1, "dis_warm_start": False}},
}


def preset(name: str = "default") -> LabelerConfig:
    if name not in PRESETS:
        raise ConfigError(f"unknown labeler preset {name!r}; known: {sorted(PRESETS)}")
    return from_dict(LabelerConfig, PRESETS[name])


# ------------------------------------------------------------------------------------------- scene cuts
CUT_METHODS = ("flow", "histogram", "flow+histogram", "adaptive", "content", "hash", "none")


@dataclass(frozen=True)
class CutConfig:
    """Scene-cut detection (``labels.cuts`` in a pipeline config). Default by measurement (docs/pipeline.md
    "Scene cuts"): ``flow``, the photometric residual after DIS flow, at 64 px, on the frames the label stage
    decodes (10 Hz for uploads), on uploaded video only (rendered and logged sources have no edits)."""

    method: str = "flow"
    threshold: Optional[float] = None   # the method's score threshold; None: resim's default for it (cuts.py)
    min_shot_s: float = 0.5             # two cuts closer than this are one (flashes, a flickering fade)
    width_px: int = 64                  # frames are resized to this width first (shot changes are coarse)
    kinds: tuple[str, ...] = ("opendv",)   # source layouts searched for cuts

    def __post_init__(self):
        if self.method not in CUT_METHODS:
            raise ConfigError(f"labels.cuts.method must be one of {CUT_METHODS}, got {self.method!r}")
        if self.threshold is not None and not self.threshold > 0:
            raise ConfigError(f"labels.cuts.threshold must be > 0 (or null for the method's default), got {self.threshold}")
        if not 0 <= self.min_shot_s <= 60:
            raise ConfigError(f"labels.cuts.min_shot_s must be in [0, 60] s, got {self.min_shot_s}")
        if not 16 <= self.width_px <= 1920:
            raise ConfigError(f"labels.cuts.width_px must be in [16, 1920], got {self.width_px}")


# ------------------------------------------------------------------------------------------- standing still
@dataclass(frozen=True)
class StillConfig:
    """Clips where the car stands still (``labels.still`` in a pipeline config; ``resim/pipeline/stages/label.py``).

    ReSim has three commands and none for stopping: a car at a red light reads "Moving forward" (no heading
    change), which teaches a world model that "forward" may mean standing still. Such clips are found from the
    labeler's flow (``ego_motion_pct_s`` below ``max_motion_pct_s``: the median flow of the textured points is
    ~0 however the rest of the scene moves) and ``policy`` says what to do: ``tag`` (default: kept, ``stopped:
    true`` in meta and manifest), ``drop`` (a ``dropped`` quarantine row), ``keep`` (kept untagged). Whatever
    the policy, a stopped clip is never "turning" (a turn read at standstill is a flow error, e.g. a vehicle
    crossing), so the balance stage never over-samples it."""

    policy: Literal["tag", "drop", "keep"] = "tag"
    max_motion_pct_s: float = 1.0       # % of the frame width per second; driving measured 5-23, frozen 0

    def __post_init__(self):
        if not (math.isfinite(self.max_motion_pct_s) and self.max_motion_pct_s >= 0):
            raise ConfigError(f"labels.still.max_motion_pct_s must be a finite number >= 0, got {self.max_motion_pct_s}")

