"""Per-clip quality: brightness, contrast, blur, a dashboard/overlay share and the flow's quality.

OpenDV-YouTube is uploads as they come: night drives, rain on the windscreen, out-of-focus phones, a bonnet
or dashboard filling a third of the frame, burnt-in speed and GPS overlays. Open-Sora's and NeMo Curator's
pipelines filter on such scores (aesthetic, OCR, motion); we measure cheap pixel statistics on the frames
the encode stage already holds at the training resolution, and take the flow's quality from the labeler.
Every clip gets the columns (``meta.json`` and the manifest, schema v3) whatever the filters say, so a
dataset can be re-filtered at load time or the thresholds chosen from its distributions
(``resim shards stats DIR --plot``).

Measured on ``QUALITY_FRAMES`` frames evenly spaced over the clip (luma = BT.601 grey, 0..255):

* ``luma_mean_8bit``: mean luma (night, under-exposure: low; blown-out: high);
* ``luma_std_8bit``: spatial standard deviation of luma, mean over frames (fog, glare: low contrast);
* ``sharpness_lapvar``: variance of the 3×3 Laplacian of luma, mean over frames (the usual focus measure,
  Pech-Pacheco et al. 2000: blur, rain-smeared or low-bitrate video is low). It scales with the resolution,
  so thresholds belong to one ``encode`` size;
* ``static_edge_frac``: share of the frame whose temporal-mean image has an edge (gradient ≥
  ``EDGE_LEVELS``) that stays put over the clip (temporal std < ``STATIC_LEVELS``): in a moving car that is
  the bonnet, the dashboard and burnt-in overlays; a flat sky has no edge and does not count. In a clip that
  stands still every edge is static: read it beside ``ego_motion_pct_s``;
* ``flow_quality``: the labeler's share of grid points its rotation fit kept (``resim.labeling.flow.window_quality``
  over the clip's frame pairs), from the label stage.

Filters (``quality`` in the pipeline config, all off by default) drop a window before the VAE sees it:
a ``dropped`` quarantine row whose reason starts with ``LOW_QUALITY`` and names the column, its value and the
threshold.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

QUALITY_FRAMES = 8
EDGE_LEVELS = 24.0      # gradient magnitude (luma levels per pixel, central differences) that counts as an edge
STATIC_LEVELS = 2.0     # temporal std (luma levels) under which a pixel does not change over the clip
LOW_QUALITY = "low quality"   # how a quality drop's reason starts (stats.json counts drops by it)

# (config field, column, comparison): a window is dropped when ``value <op> threshold`` fails
FILTERS = (
    ("min_luma_mean_8bit", "luma_mean_8bit", ">="),
    ("max_luma_mean_8bit", "luma_mean_8bit", "<="),
    ("min_luma_std_8bit", "luma_std_8bit", ">="),
    ("min_sharpness_lapvar", "sharpness_lapvar", ">="),
    ("max_static_edge_frac", "static_edge_frac", "<="),
    ("min_flow_quality", "flow_quality", ">="),
)


def clip_quality(frames: np.ndarray) -> dict[str, float]:
    """Pixel quality of a clip ``(T, H, W, 3)`` uint8 RGB: the four pixel columns (not ``flow_quality``)."""
    idx = np.linspace(0, len(frames) - 1, min(QUALITY_FRAMES, len(frames))).round().astype(int)
    luma = np.stack([cv2.cvtColor(np.ascontiguousarray(frames[i]), cv2.COLOR_RGB2GRAY) for i in idx]).astype(np.float32)
    lap = [float(cv2.Laplacian(y, cv2.CV_32F, ksize=1).var()) for y in luma]
    mean_img = luma.mean(axis=0)
    gy, gx = np.gradient(mean_img)
    edges = np.hypot(gx, gy) >= EDGE_LEVELS
    static = luma.std(axis=0) < STATIC_LEVELS
    return {
        "luma_mean_8bit": round(float(luma.mean()), 3),
        "luma_std_8bit": round(float(luma.reshape(len(luma), -1).std(axis=1).mean()), 3),
        "sharpness_lapvar": round(float(np.mean(lap)), 3),
        "static_edge_frac": round(float((edges & static).mean()), 5),
    }


def quality_problem(values: dict, cfg) -> str | None:
    """Why a clip fails ``cfg`` (a ``QualityConfig``), in one line naming the column, or None. A column that
    could not be measured (``None``, e.g. no flow) passes: we do not drop what we could not judge."""
    for field, column, op in FILTERS:
        limit = getattr(cfg, field)
        v = values.get(column)
        if limit is None or v is None or (isinstance(v, float) and math.isnan(v)):
            continue
        ok = v >= limit if op == ">=" else v <= limit
        if not ok:
            return f"{LOW_QUALITY}: {column} {v:g} {'<' if op == '>=' else '>'} quality.{field} {limit:g}"
    return None
