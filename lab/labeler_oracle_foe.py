"""Diagnostic: how well would the flow labeler read yaw if it knew each frame pair's focus of expansion?

The labeler's remaining error on the synthetic world was traced to the yaw / FOE-x trade-off
(docs/lab/2026-11-22-labeler-calibration.md, "Fourth look").
This script replaces the fitted FOE by the *physical* one, computed from the ground-truth poses and the world's
camera rig (the camera moves along the chord and, ahead of the rear axle, sideways: its direction of travel in
the camera frame is the FOE), and fits rotation only with the labeler's own flow, masks and IRLS
(``FlowLabeler._fit_motion(..., free_foe=False)``). It reports the same held-out numbers as
``calibrate_labeler.py`` for three FOE sources: ``fitted`` (the labeler as configured), ``oracle`` (physical FOE)
and ``centre`` (FOE fixed at the principal point: what ignoring the chord and lever arm costs).
Uses ground truth: a diagnostic, not a labeler.

    PYTHONPATH=. python lab/labeler_oracle_foe.py --data SYNTH_DIR [--preset default]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "lab"))

from calibrate_labeler import FPS, STRIDE, WIN, cmd_of, episodes  # noqa: E402
from resim.labeling.config import preset  # noqa: E402
from resim.labeling.flow import FlowLabeler, prepare_frame  # noqa: E402
from resim.pipeline.sources.synth.ground_truth import GroundTruth  # noqa: E402


def physical_foe(poses: np.ndarray, ahead_m: float, f_px: float) -> np.ndarray:
    """(N, 3) poses x, y, yaw (world, left +) -> (N-1,) FOE x per pair, px right of the principal point."""
    x, y, psi = poses[:, 0], poses[:, 1], poses[:, 2]
    cx, cy = x + ahead_m * np.cos(psi), y + ahead_m * np.sin(psi)       # the camera, not the rear axle
    dx, dy = np.diff(cx), np.diff(cy)
    c, s = np.cos(psi[:-1]), np.sin(psi[:-1])
    fwd, left = dx * c + dy * s, -dx * s + dy * c                      # in the camera frame of the first frame
    return -f_px * left / np.maximum(fwd, 1e-3)


def yaw_per_pair(lab: FlowLabeler, frames, mode: str, poses: np.ndarray, ahead_m: float, ey_px: float) -> np.ndarray:
    fc = lab.flow_cfg
    greys = [prepare_frame(fr, fc.work_width_px) for fr in frames]
    if mode == "fitted":
        return lab.yaw_rates_from_grey(iter(greys), FPS) / FPS
    greys = [cv2.equalizeHist(g) for g in greys]
    h, w = greys[0].shape
    f = lab.focal_px(w)
    rows, cols = lab._grid(h, w)
    tex = [lab._texture(g, rows, cols) for g in greys]
    pairs = [lab._pair(greys[i], greys[i + 1], tex[i]) for i in range(len(greys) - 1)]
    X, Y, U, V, W0 = lab._stack(pairs)
    P = len(pairs)
    E = np.zeros((P, 2))
    E[:, 1] = ey_px
    if mode == "oracle":
        E[:, 0] = physical_foe(poses[:P + 1], ahead_m, f)
    theta = lab._fit_motion(X, Y, U, V, W0, E, f, len(rows), free_foe=False)[0]
    return np.degrees(theta[:, 0])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="a `resim synth` output folder")
    ap.add_argument("--preset", default="default")
    args = ap.parse_args()

    root = Path(args.data)
    gt = GroundTruth.load(root)
    cam = gt.data["camera"]
    cfg = preset(args.preset)
    for mode in ("fitted", "oracle", "centre"):
        errs, hits = [], []
        for k, (name, item, ep) in enumerate(episodes(root)):
            if abs(ep.fps_hz - FPS) > 1e-6 or k % 2 == 0:        # held-out (odd) episodes only
                continue
            frames = list(ep.frames())
            h_src = frames[0].shape[0]
            w_work = cfg.flow.work_width_px
            h_work = max(8, int(round(w_work * h_src / frames[0].shape[1])))
            ey = (cam["intrinsic"][1][2] - (h_src - 1) / 2) * h_work / h_src     # principal row vs the centre
            inc = yaw_per_pair(FlowLabeler(cfg), frames, mode, gt.poses_for(name, item), cam["forward_m"], ey)
            yaw = gt.yaw_for(name, item)
            for s in range(0, min(len(yaw), len(inc) + 1) - WIN, STRIDE):
                true = float(np.degrees(yaw[s + WIN] - yaw[s]))
                est = float(inc[s:s + WIN].sum())
                errs.append(abs(est - true))
                hits.append(cmd_of(est, 15.0) == cmd_of(true, 15.0))
        print(f"{mode:>7}: {len(errs)} held-out windows, accuracy at 15 deg {np.mean(hits):.3f}, "
              f"yaw error median {np.median(errs):.2f} / p90 {np.percentile(errs, 90):.2f} deg", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
