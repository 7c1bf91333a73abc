"""Scene-cut detectors on a labelled set built from the real dashcam clips: precision / recall per transition
kind (hard cut, fade through black, dissolve), and cost per video-hour beside the flow labeler's, in one process.

Detectors: PySceneDetect's ContentDetector (HSV + optional edges, fixed threshold), AdaptiveDetector (the content
score against its rolling average), HistogramDetector and HashDetector, and ``flow``: a detector on the labeler's
own optical flow (the photometric residual after warping by DIS flow, against its rolling median; what a cut
looks like to the flow we already compute). Frames at the labeler's working width (256 px), at the clips'
25 fps, resampled to the rate the label stage sees (the OpenDV reader's 10 Hz). Run:
    PYTHONPATH=. python lab/scene_cuts.py [--cuts 12] [--seeds 3]
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np

from resim.labeling.config import preset
from resim.labeling.cut_set import KINDS, build_cut_video, score
from resim.labeling.cuts import CutConfig, detect_cuts
from resim.labeling.flow import FlowLabeler

REPO = Path(__file__).resolve().parents[1]
DASHCAM = REPO.parent / "shared" / "data" / "dashcam"


def load(path: Path, width: int) -> np.ndarray:
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        # display aspect 16:9 for both (challenge.mp4 is 720x576 stored with 64:45 pixels), as the readers show it
        frames.append(cv2.cvtColor(cv2.resize(f, (width, width * 9 // 16), interpolation=cv2.INTER_AREA),
                                   cv2.COLOR_BGR2RGB))
    return np.stack(frames)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cuts", type=int, default=12, help="transitions per video (default 12)")
    ap.add_argument("--seeds", type=int, default=3, help="videos per kind (default 3)")
    ap.add_argument("--widths", type=int, nargs="+", default=[64, 128], help="detection widths (px)")
    ap.add_argument("--methods", nargs="+", default=["content", "adaptive", "histogram", "hash", "flow", "flow+histogram"])
    ap.add_argument("--rate", type=float, default=10.0, help="detection rate (Hz): the OpenDV reader resamples uploads "
                    "to 10 Hz (nearest frame) before any stage sees them (default 10)")
    ap.add_argument("--first-seed", type=int, default=0, help="seeds first-seed .. first-seed + seeds - 1 (tune on "
                    "some, report on others)")
    args = ap.parse_args()
    clips = [load(DASHCAM / n, 256) for n in ("solidWhiteRight.mp4", "challenge.mp4")]
    fps = 25.0
    methods = [(m, w) for w in args.widths for m in args.methods]
    videos = {k: [build_cut_video(clips, k, args.cuts, seed=s)
                  for s in range(args.first_seed, args.first_seed + args.seeds)] for k in KINDS}
    n_frames = sum(len(v) for vs in videos.values() for v, _ in vs)
    print(f"labelled set: {args.seeds} videos x {args.cuts} transitions per kind, {n_frames} frames "
          f"({n_frames / fps / 60:.1f} min at {fps:g} fps), 256 px wide")
    rows = {}
    for m, w in methods:
        m, _, thr = m.partition(":")                 # "histogram:0.1": a threshold other than the default
        cfg = CutConfig(method=m, width_px=w, threshold=float(thr) if thr else None)
        m = m + (f":{thr}" if thr else "")
        res, t = {}, 0.0
        for k in KINDS:
            tot = {"tp": 0, "fp": 0, "fn": 0}
            for v, bounds in videos[k]:
                idx = np.minimum(np.round(np.arange(int(len(v) / fps * args.rate)) * fps / args.rate).astype(int),
                                 len(v) - 1)                 # the reader's nearest-frame resampling
                t0 = time.perf_counter()
                found = [int(idx[f]) for f in detect_cuts(v[idx], args.rate, cfg)]
                t += time.perf_counter() - t0
                # a cut between output frames i-1 and i is known to within one output frame
                s = score(found, bounds, tolerance_frames=int(np.ceil(fps / args.rate)))
                for key in tot:
                    tot[key] += s[key]
            res[k] = tot
        rows[f"{m}@{w}"] = (res, t)
    # the labeler's cost on the same frames, for the curation-cost target (<= 25 % of labeling)

    lab = FlowLabeler(preset("default"))
    t0 = time.perf_counter()
    for vs in videos.values():
        for v, _ in vs:
            idx = np.round(np.arange(int(len(v) / fps * args.rate)) * fps / args.rate).astype(int)
            lab.yaw_rates_deg(v[np.minimum(idx, len(v) - 1)], args.rate)    # the label stage's flow, same frames
    t_lab = time.perf_counter() - t0
    hours = n_frames / fps / 3600
    print(f"\n{'method@px':<14} " + "  ".join(f"{k:>22}" for k in KINDS) + "   all P / R    s per video-hour  vs labeler")
    for m, (res, t) in rows.items():
        cells = []
        for k in KINDS:
            r = res[k]
            p = r["tp"] / max(1, r["tp"] + r["fp"])
            rc = r["tp"] / max(1, r["tp"] + r["fn"])
            cells.append(f"P {p:.2f} R {rc:.2f} fp {r['fp']:>3}")
        tp = sum(r["tp"] for r in res.values())
        fp = sum(r["fp"] for r in res.values())
        fn = sum(r["fn"] for r in res.values())
        print(f"{m:<14} " + "  ".join(f"{c:>22}" for c in cells) +
              f"   {tp / max(1, tp + fp):.2f} / {tp / max(1, tp + fn):.2f}   {t / hours:>10.0f}   {t / t_lab:>6.1%}")
    print(f"labeler (flow, same frames at {args.rate:g} Hz): {t_lab / hours:.0f} s per video-hour")


if __name__ == "__main__":
    main()
