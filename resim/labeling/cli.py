"""`resim label VIDEO`: driving commands from optical flow, one line per window.

Light module: cv2/numpy are imported inside the handler.
"""
from __future__ import annotations

import argparse
import json
import sys

from resim.labeling.config import TURN_THRESHOLD_REF_WINDOW_S, CommandConfig   # light: dataclasses only

EPILOG = """\
output (one line per window):
  start_s end_s command yaw_deg confidence
  yaw_deg is the heading change over the window in degrees, positive = left;
  command is "Turning left" / "Moving forward" / "Turning right" (|yaw_deg| >= turn threshold is a turn);
  confidence (0..1) is 0.5 at the threshold, near 1 far from it, times the flow quality.
  --json lines also carry the threshold applied: turn_threshold_deg (degrees over the window) and
  turn_rate_threshold_deg_s (the same as a steady yaw rate); the summary line on stderr states both.

The turn threshold is a yaw rate: command.turn_threshold_deg ({thr:g} by default) is degrees over a {ref:g}-s
window and scales with the window's length, {rate:g} deg/s at any window (--window-s 2: {thr2:g} deg).

The yaw estimate assumes a horizontal field of view (--hfov-deg, default 80): uncalibrated video
reads roughly tan(true/2)/tan(assumed/2) times the true heading change (docs/labeling.md).
The focus of expansion (where the car is heading in the image) is placed by the car's kinematics with two
numbers pooled over the video: the camera's straight-ahead point, learnt from >= 3 s of straight driving (a
clip that is one curve throughout keeps the per-pair fit; the summary line says which was used), and the shift
in turns. If you know the camera rig (how far the camera sits ahead of the rear axle, and its height), say so:
the shift then comes from the rig and the road surface, which removes most of the remaining error on the
synthetic world (median 0.5-0.8 deg per 4 s).
Not for fast footage: there the distance per frame pair, read from the road surface, comes out far too
short (real freeway clips: ~20x) and the correction overshoots (docs/labeling.md, "The known rig on fast footage").

examples:
  resim label clip.mp4
  resim label clip.mp4 --window-s 4 --stride-s 2 --json > labels.jsonl
  resim label clip.mp4 --set flow.flow_preset=fast --set command.turn_threshold_deg=10
  resim label clip.mp4 --set flow.camera_ahead_m=1.8 --set flow.camera_height_m=1.35   # known rig
"""


def _run(args: argparse.Namespace) -> int:
    from resim.config import ConfigError, apply_overrides, check_positive, from_dict, to_dict
    from resim.labeling.config import LabelerConfig, PRESETS
    from resim.media.video_probe import VideoError
    from resim.labeling.windows import label_video

    try:
        if args.preset not in PRESETS:
            raise ConfigError(f"unknown preset {args.preset!r}; known: {sorted(PRESETS)}")
        raw = to_dict(from_dict(LabelerConfig, PRESETS[args.preset]))
        if args.hfov_deg is not None:
            raw["flow"]["hfov_deg"] = args.hfov_deg
        raw = apply_overrides(raw, args.set)
        if args.window_s is not None:
            raw["command"]["window_s"] = args.window_s   # --window-s wins over --set command.window_s
        cfg = from_dict(LabelerConfig, raw)                # validates window_s with the rest
        check_positive("--stride-s", args.stride_s)
    except ConfigError as e:
        print(f"resim label: bad configuration: {e}", file=sys.stderr)
        return 2
    try:
        res = label_video(args.video, cfg, stride_s=args.stride_s,
                          progress=not args.quiet and sys.stderr.isatty())
    except VideoError as e:
        print(f"resim label: cannot label {e.path}: {e.reason}", file=sys.stderr)
        return 1
    cc = cfg.command
    thr_deg, rate = cc.turn_threshold_for(), cc.turn_rate_threshold_deg_s
    if args.json:
        for w in res.windows:
            print(json.dumps({"start_s": w.start_s, "end_s": w.end_s, "command": w.command,
                              "yaw_deg": round(w.yaw_deg, 3), "confidence": round(w.confidence, 3),
                              "turn_threshold_deg": round(thr_deg, 4), "turn_rate_threshold_deg_s": round(rate, 4)}))
    else:
        print(f"{'start_s':>8} {'end_s':>7}  {'command':<15} {'yaw_deg':>8} {'confidence':>10}")
        for w in res.windows:
            print(f"{w.start_s:8.2f} {w.end_s:7.2f}  {w.command:<15} {w.yaw_deg:8.2f} {w.confidence:10.3f}")
    info = res.info
    full = [w for w in res.windows if w.end_s - w.start_s + 1e-6 >= cfg.command.window_s]
    n_dec = res.decode.get("frames_decoded", 0)
    skipped = (" (non-reference frames not decoded)"
               if res.decode.get("nonref_skipped") and n_dec < info.num_frames - 1 else "")
    if res.decode.get("nonref_skipped_until_s") is not None:
        skipped = (f" (non-reference frames not decoded until {res.decode['nonref_skipped_until_s']:g} s, every frame "
                   f"after it: reference frames alone were {res.decode['nonref_gap_s']:g} s apart there)")
    if res.decode.get("timestamps") == "frame count / fps":
        skipped += f" (no usable frame times in the file: times are frame count / {info.fps_hz:g} fps)"
    note = "" if full else f" (shorter than the {cfg.command.window_s:g}-s window: one short window)"
    fc = cfg.flow
    rig = (f"rig: camera {fc.camera_ahead_m:g} m ahead of the rear axle, {fc.camera_height_m:g} m high"
           if fc.camera_ahead_m is not None else "rig unknown")
    src = res.foe_sources       # what placed the FOE, per chunk of pairs (resim/labeling/flow.py)
    if src:
        rig += ", FOE " + " / ".join(x if src.count(x) == len(src) else f"{x} in {src.count(x)} of {len(src)} chunks"
                                     for x in dict.fromkeys(src))
        if fc.camera_ahead_m is None and fc.foe_model == "pooled" and "per_pair" in src:
            rig += f" (per pair until {fc.foe_min_straight_s:g} s of straight driving is seen)"
    # the video is not the file's first video stream: that one is a still picture (a cover), resim/media/video_probe.py
    stream = f" (video stream {info.stream_index}; the first is a still picture)" if info.opencv_problem else ""
    print(f"# {info.path}: {info.width_px}x{info.height_px} @ {info.fps_hz:g} fps{stream}, sampled at "
          f"{res.sample_hz:g} Hz, {len(res.times_s)} samples, {len(res.windows)} windows{note}, total heading change "
          f"{res.yaw_inc_deg.sum():+.1f} deg, turn threshold {thr_deg:g} deg over {cc.window_s:g} s ({rate:g} deg/s), "
          f"hfov assumed {fc.hfov_deg:g} deg, {rig}; {res.decode.get('decoder')} "
          f"decoded {n_dec} of {info.num_frames or 'an unknown number of'} frames"
          f"{skipped}", file=sys.stderr)
    if res.decode.get("incomplete"):
        # a truncated or damaged file: the labels above cover the part that decodes (docs/labeling.md, "Odd files")
        print(f"resim label: warning: {info.path}: {res.decode['incomplete']}; "
              f"the labels cover 0-{res.times_s[-1]:.2f} s only", file=sys.stderr)
    return 0


def register(subparsers) -> None:
    c = CommandConfig()
    epilog = EPILOG.format(thr=c.turn_threshold_deg, ref=TURN_THRESHOLD_REF_WINDOW_S,
                           rate=c.turn_rate_threshold_deg_s, thr2=c.turn_threshold_for(2.0))
    p = subparsers.add_parser(
        "label", help="driving commands (left/forward/right) of a video from optical flow",
        description="Estimate ego yaw from optical flow and print one driving command per window "
                    "(start_s, end_s, command, yaw_deg [left +], confidence).",
        epilog=epilog, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("video", help="any video file OpenCV/FFmpeg can decode")
    p.add_argument("--window-s", type=float, default=None,
                   help="window length in seconds (default: command.window_s of the config, 4 = ReSim's future); "
                        f"the turn threshold scales with it ({c.turn_rate_threshold_deg_s:g} deg/s)")
    p.add_argument("--stride-s", type=float, default=2.0, help="step between window starts in seconds (default 2)")
    p.add_argument("--json", action="store_true", help="one JSON object per line instead of a table")
    p.add_argument("--quiet", action="store_true",
                   help="no progress bar (it is drawn on stderr only when stderr is a terminal)")
    p.add_argument("--hfov-deg", type=float, default=None, help="assumed horizontal field of view (default 80)")
    p.add_argument("--preset", default="default",
                   help="labeler preset: default | accurate (DIS medium, ~2.4x the CPU) | fast (160 px, ~half the CPU)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config field, e.g. --set command.turn_threshold_deg=10")
    p.set_defaults(func=_run)
