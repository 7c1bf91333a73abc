"""Stage 3: label every candidate window (the flow labeler of ``labeling/``).

* **Flow command, every clip.** One streaming pass over the episode at the labeler's working width
  gives per-pair yaw rates (deg/s); a window's heading change is the sum over its *future* pairs
  (from the last history frame to the last frame) / fps — the same number ``FlowLabeler.label``
  computes for that window alone, without decoding overlapping windows five times.
* **Trajectory command + 8x(x, y, yaw), where the source has poses**: ego frame at the last history
  frame (``labeling.trajectory_from_poses``), command from ``command_from_trajectory``.
* **Outcome** (CARLA-like): hazard flag and infraction score come from the episode record.
* **Standing still** (``labels.still``): a window's ego motion (``ego_motion_pct_s``: the median flow of the
  textured points over its pairs, % of the frame width per second) below the threshold is ``stopped``:
  tagged (default), dropped, or kept; never turning (so never over-sampled by the balance stage).
* **Scene cuts** (uploaded video, ``labels.cuts``): the same decoding pass feeds every source frame to the
  cut detector (``resim.labeling.cuts``; by default our detector on DIS optical flow at 64 px); a window that shows frames
  of two shots is dropped (a ``dropped`` quarantine row naming the cut), and the unit's cuts are kept in
  ``state["cuts"]`` (commit marker, ``stats.json``).

``command`` is the trajectory command where poses exist (``labels.prefer``), else the flow command.
A window whose poses have NaNs is dropped into the quarantine table (status ``dropped``); the
unit's other windows go on.
"""
from __future__ import annotations

import time
import warnings

import numpy as np

from resim.labeling.commands import command_from_trajectory, command_from_yaw
from resim.labeling.cuts import CutDetector
from resim.labeling.flow import FlowLabeler, ego_motion_pct_s, window_quality
from resim.labeling.trajectory import trajectory_from_poses
from resim.media.frames import clip_frames
from resim.pipeline import quarantine
from resim.pipeline.stages.base import BadInput
from resim.pipeline.stages.cut import CutStage
from resim.pipeline.units import clip_of
from resim.shards.schema import COMMANDS

FORWARD = COMMANDS[1]


class LabelStage(CutStage):   # shares the reader cache
    name = "label"

    def __init__(self, cfg, progress=None):
        super().__init__(cfg, progress)
        self.lcfg = self.cfg.labels.labeler
        self.flow = FlowLabeler(self.lcfg)

    def flow_size_hw(self, frame_size_hw) -> tuple[int, int]:
        """Decode straight to the labeler's working width (aspect kept): no full-size frame is kept."""
        h, w = frame_size_hw
        ww = self.lcfg.flow.work_width_px
        return max(2, int(round(h * ww / w))), ww

    def process(self, state: dict) -> None:
        cfg, e, clip = self.cfg, state["episode"], clip_of(state)
        fps, step = clip.fps_hz, e["step"]
        H, N = clip.num_history_frames, clip.num_frames
        windows = state["windows"]
        end = windows[-1]["start"] + N                                 # frames needed: [0, end)
        ep = self.open(state)

        size_hw = self.flow_size_hw(e["frame_size_hw"])
        cut_cfg = cfg.labels.cuts
        t_cuts = [0.0]                  # seconds in the cut detector (curation cost, beside the labeler's)
        detector = (CutDetector(cut_cfg, e["fps_hz"]) if state["kind"] in cut_cfg.kinds and cut_cfg.method != "none"
                    else None)
        if detector is None:
            frames = clip_frames(ep, 0, end, step, size_hw)
        else:   # one decoding pass: every source frame to the cut detector, every step-th to the flow
            def frames_and_cuts():
                for i, f in enumerate(ep.frames(0, (end - 1) * step + 1, size_hw=size_hw)):
                    t0 = time.perf_counter()
                    detector.push(f)
                    t_cuts[0] += time.perf_counter() - t0
                    if i % step == 0:
                        yield f
            frames = frames_and_cuts()
        with warnings.catch_warnings():   # all-NaN residual rows on textureless frames: handled inside
            warnings.simplefilter("ignore", RuntimeWarning)
            rates = self.flow.yaw_rates_deg(frames, fps)               # (end-1,) deg/s, left +
        if len(rates) != end - 1:
            raise BadInput(f"decoded {len(rates) + 1} of {end} frames (truncated video or missing frames)")
        t0 = time.perf_counter()
        cuts = detector.finish() if detector is not None else []       # source frames starting a new shot
        t_cuts[0] += time.perf_counter() - t0
        state["timings_s"]["label.cuts"] = state["timings_s"].get("label.cuts", 0.0) + t_cuts[0]
        motion = getattr(self.flow, "last_motion_px", None)
        still = cfg.labels.still
        state["cuts"] = [{"frame": int(c), "t_s": round(c / e["fps_hz"], 3)} for c in cuts]
        heading = np.concatenate([[0.0], np.cumsum(rates) / fps])      # heading at frame i, deg
        quality = getattr(self.flow, "last_quality", None)

        poses = None
        if ep.poses is not None:
            poses = np.asarray(ep.poses, dtype=np.float64)[::step][:e["num_frames"]]

        labelled = []
        for w in windows:
            s = w["start"]
            t, last = s + H - 1, s + N - 1
            # the window shows source frames s*step .. last*step: it spans a cut c when frames on both sides
            spans = [c for c in cuts if s * step < c <= last * step]
            if spans:
                quarantine.drop_window(state, self.name, s, f"{quarantine.SPANS_CUT} at {spans[0] / e['fps_hz']:.2f} s "
                                                           f"(source frame {spans[0]})")
                continue
            yaw_flow = float(heading[last] - heading[t])
            cmd_flow, conf_flow = command_from_yaw(yaw_flow, self.lcfg)
            flow_q = None
            if quality is not None and len(quality) == len(rates):
                conf_flow *= window_quality(quality[t:last])
                flow_q = round(window_quality(quality[s:last]), 4)    # the clip's column (resim/pipeline/clip_quality.py)
            ego = (ego_motion_pct_s(motion[s:last], size_hw[1], fps)
                   if motion is not None and len(motion) == len(rates) else float("nan"))
            stopped = bool(ego < still.max_motion_pct_s) if np.isfinite(ego) else None
            out = {"start": s, "command_flow": cmd_flow, "yaw_deg_flow": yaw_flow, "confidence_flow": conf_flow,
                   "command_trajectory": None, "yaw_deg_trajectory": None, "traj": None,
                   "ego_motion_pct_s": round(ego, 4) if np.isfinite(ego) else None, "flow_quality": flow_q}
            if poses is not None:
                win = poses[s:s + N]
                bad = ~np.isfinite(win).all(axis=1)
                if bad.any():
                    idx = np.flatnonzero(bad) + s
                    quarantine.drop_window(state, self.name, s, f"NaN/inf poses at clip frames {idx[0]}..{idx[-1]} "
                                                               f"({int(bad.sum())} of {N})")
                    continue
                traj = trajectory_from_poses(poses, t, fps, clip.num_waypoints, clip.waypoint_dt_s)
                cmd_traj, yaw_traj = command_from_trajectory(traj, self.lcfg)
                out.update(command_trajectory=cmd_traj, yaw_deg_trajectory=float(yaw_traj),
                           traj=np.round(traj.astype(np.float64), 6).tolist())
            if out["command_trajectory"] is not None and cfg.labels.prefer == "trajectory":
                out.update(command=out["command_trajectory"], command_source="trajectory",
                           yaw_deg=out["yaw_deg_trajectory"], confidence=1.0)  # ground-truth poses
            else:
                out.update(command=cmd_flow, command_source="flow", yaw_deg=yaw_flow, confidence=conf_flow)
            if stopped and out["command"] != FORWARD:
                if out["command_source"] == "trajectory":
                    stopped = False     # the poses (ground truth) say the car turned: the flow saw too little
                else:
                    # a car that stands still does not turn: a turn read here is a flow error (a vehicle
                    # crossing); forward keeps it off the balance stage's fine grid (never over-sampled)
                    out.update(command=FORWARD, confidence=min(out["confidence"], 0.5))
            if stopped and still.policy == "drop":
                quarantine.drop_window(state, self.name, s, f"{quarantine.STANDS_STILL}: ego motion {ego:.2f} % of the frame "
                                                           f"width per s < labels.still.max_motion_pct_s "
                                                           f"{still.max_motion_pct_s:g}")
                continue
            out["stopped"] = stopped if still.policy == "tag" else None
            out["is_turning"] = out["command"] != FORWARD
            labelled.append(out)
        if not labelled:
            raise BadInput(f"all {len(windows)} windows dropped (NaN poses, scene cuts or standing still)")
        state["windows"] = labelled
