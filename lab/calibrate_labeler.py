"""Calibrate the flow labeler's turn threshold on the synthetic world and measure it.

1. Makes (or reads, --data) a synthetic world (``resim synth``) and reads its video episodes
   back through the real readers: OpenDV (mp4, resampled to 10 Hz) and CARLA (10 Hz jpg).
2. Runs ``FlowLabeler`` over every episode (per-pair yaw at 10 Hz) and cuts 4 s windows every
   1 s; the truth is the exact heading change from ``ground_truth.json``.
3. The *definition* of a turn is the true heading change over 4 s against --ref-threshold-deg
   (15 deg, the synthetic world's own definition); the flow threshold is then chosen on the
   calibration episodes (even index) to reproduce it best, and everything is reported on the
   held-out episodes (odd index): confusion matrix, accuracy, yaw error median / p90.
4. Flow-vs-trajectory agreement: on episodes with poses (CARLA), the command from flow against
   ``command_from_trajectory`` (lateral-offset rule, the default, and the heading rule).

    PYTHONPATH=. python lab/calibrate_labeler.py [--data DIR [--data DIR2 ...] | --episodes 48 --seed 11] [--hfov-deg 80] [--plot held_out.png]
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from resim.config import apply_overrides, from_dict, to_dict  # noqa: E402
from resim.labeling.commands import command_from_trajectory, command_from_yaw  # noqa: E402
from resim.labeling.config import CommandConfig, FlowConfig, LabelerConfig, preset  # noqa: E402
from resim.labeling.flow import FlowLabeler  # noqa: E402
from resim.labeling.trajectory import trajectory_from_poses  # noqa: E402
from resim.pipeline.sources.carla import CarlaConfig, CarlaReader  # noqa: E402
from resim.pipeline.sources.opendv import OpenDVConfig, OpenDVReader  # noqa: E402
from resim.pipeline.sources.synth.ground_truth import GroundTruth  # noqa: E402
from resim.shards.schema import COMMANDS  # noqa: E402

WIN, STRIDE, FPS = 40, 10, 10.0


def episodes(root: Path):
    for name, reader in (("opendv", OpenDVReader(OpenDVConfig.preset("synthetic", root=root / "opendv"))),
                         ("carla", CarlaReader(CarlaConfig(root=root / "carla")))):
        for item in reader.list_items():
            yield name, item, reader.open(item)


def cmd_of(yaw, thr):
    return command_from_yaw(yaw, CommandConfig(turn_threshold_deg=thr))[0]


def confusion(true, pred):
    m = np.zeros((3, 3), int)
    for t, p in zip(true, pred):
        m[COMMANDS.index(t), COMMANDS.index(p)] += 1
    return m


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", action="append", default=None,
                    help="an existing `resim synth` output folder; repeat for several worlds (each calibrated on its "
                         "own, then also reported together: every held-out window of every world)")
    ap.add_argument("--episodes", type=int, default=48)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--preset", default="default", help="labeler preset (resim.labeling.config.PRESETS)")
    ap.add_argument("--hfov-deg", type=float, default=None, help="labeler's assumed FOV (default: config's)")
    ap.add_argument("--known-rig", action="store_true",
                    help="give the labeler the world's camera rig (ground_truth.json 'camera': forward_m, height_m): "
                         "flow.camera_ahead_m / camera_height_m; OpenDV video has no such record")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a labeler config field, e.g. --set flow.work_width_px=192")
    ap.add_argument("--ref-threshold-deg", type=float, default=15.0)
    ap.add_argument("--json-out", help="write the numbers here")
    ap.add_argument("--plot", metavar="PNG", help="draw the held-out windows here: flow vs true heading change with "
                                                   "the thresholds, the error against the truth, and the error "
                                                   "distribution (needs matplotlib)")
    args = ap.parse_args()

    tmp = tempfile.TemporaryDirectory()
    roots = [Path(d) for d in args.data] if args.data else [Path(tmp.name) / "synth"]
    if not args.data:
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "resim", "synth", "--out", str(roots[0]), "--episodes", str(args.episodes),
                        "--seed", str(args.seed), "--quiet"], check=True, cwd=REPO, stdout=subprocess.DEVNULL,
                       env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"})
        print(f"synthetic world: {args.episodes} episodes, seed {args.seed}, {time.perf_counter() - t0:.0f} s")
    results, errs, correct, held = {}, [], 0, {}
    for root in roots:
        if len(roots) > 1:
            print(f"== {root}")
        key = root.name if root.name not in held else str(root)      # the plot's legend
        out, err_w, correct_w, held[key] = calibrate_world(root, args)
        results[str(root)] = out
        errs.append(err_w)
        correct += correct_w
    if len(roots) > 1:
        err = np.concatenate(errs)
        union = {"worlds": len(roots), "held_out_windows": int(len(err)), "held_out_accuracy": correct / len(err),
                 "yaw_err_deg_held_out": {"median": float(np.median(err)), "p90": float(np.percentile(err, 90))}}
        print(f"== all {len(roots)} worlds together ({len(err)} held-out windows, each world's own threshold): "
              f"accuracy {union['held_out_accuracy']:.3f}, yaw error median {union['yaw_err_deg_held_out']['median']:.2f}, "
              f"p90 {union['yaw_err_deg_held_out']['p90']:.2f} deg")
    if args.json_out:
        doc = results[str(roots[0])] if len(roots) == 1 else {"worlds": results, "all_worlds": union}
        Path(args.json_out).write_text(json.dumps(doc, indent=2))
    if args.plot:
        plot_held_out(held, args.ref_threshold_deg, f"preset {args.preset!r}", Path(args.plot))
        print(f"plot: {args.plot}")
    return 0


def plot_held_out(held: dict, ref_deg: float, title: str, path: Path) -> None:
    """Left: flow vs true heading change per held-out window (wrong commands in red), the turn definition (dashed,
    vertical) and each world's calibrated flow threshold (dotted, horizontal). Middle: the error against the true
    heading change (a scale error is a slope; noise of the yaw / FOE split a band). Right: |error| distribution."""
    import matplotlib   # slow to import: only for the figure

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, cx, bx) = plt.subplots(1, 3, figsize=(17, 5.5))
    lim = max(max(np.abs(h["true"]).max(), np.abs(h["est"]).max()) for h in held.values()) * 1.05
    ax.plot([-lim, lim], [-lim, lim], color="0.7", lw=0.8)
    for x in (-ref_deg, ref_deg):
        ax.axvline(x, color="0.4", ls="--", lw=0.8)
    for name, h in held.items():
        ok = h["correct"]
        ax.scatter(h["true"][ok], h["est"][ok], s=6, alpha=0.5, label=f"{name} ({len(ok)} windows)")
        ax.scatter(h["true"][~ok], h["est"][~ok], s=22, marker="x", color="red")
        cx.scatter(h["true"][ok], h["est"][ok] - h["true"][ok], s=6, alpha=0.5)
        cx.scatter(h["true"][~ok], h["est"][~ok] - h["true"][~ok], s=22, marker="x", color="red")
        for y in (-h["threshold_deg"], h["threshold_deg"]):
            ax.axhline(y, color="0.4", ls=":", lw=0.8)
    err = np.concatenate([np.abs(h["est"] - h["true"]) for h in held.values()])
    acc = np.mean(np.concatenate([h["correct"] for h in held.values()]))
    ax.set(xlim=(-lim, lim), ylim=(-lim, lim), xlabel="true heading change over 4 s (deg, left +)",
           ylabel="flow estimate (deg)", title=f"{title}: held-out accuracy {acc:.3f} (x = wrong command)")
    if len(held) <= 10:
        ax.legend(fontsize=7, loc="upper left", markerscale=2)
    cx.axhline(0, color="0.7", lw=0.8)
    for x in (-ref_deg, ref_deg):
        cx.axvline(x, color="0.4", ls="--", lw=0.8)
    cx.set(xlim=(-lim, lim), xlabel="true heading change over 4 s (deg, left +)", ylabel="flow - true (deg)",
           title="error against the true heading change")
    bins = np.linspace(0, max(np.percentile(err, 99), 1.0), 60)
    bx.hist(err, bins=bins, color="tab:blue", alpha=0.8)
    for q, ls in ((50, "-"), (90, "--")):
        v = np.percentile(err, q)
        bx.axvline(v, color="k", ls=ls, lw=1, label=f"p{q} {v:.2f} deg")
    bx.axvline(1.0, color="tab:green", lw=1, label="target median 1 deg")
    bx.set(xlabel="|flow - true| per 4-s window (deg)", ylabel="held-out windows", title="yaw error")
    bx.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def calibrate_world(root: Path, args) -> tuple[dict, np.ndarray, int, dict]:
    """One world: calibrate on its even episodes, report on its odd ones. Returns (numbers, held-out |error| deg,
    held-out windows labelled right, held-out arrays for the plot)."""
    gt = GroundTruth.load(root)
    cam = gt.data.get("camera", {})

    raw = to_dict(preset(args.preset))
    if args.hfov_deg is not None:
        raw["flow"]["hfov_deg"] = args.hfov_deg
    if args.known_rig:
        raw["flow"]["camera_ahead_m"] = float(cam["forward_m"])
        raw["flow"]["camera_height_m"] = float(cam["height_m"])
    cfg = from_dict(LabelerConfig, apply_overrides(raw, args.set))
    flow_cfg = cfg.flow
    rig = (f"rig known: camera {flow_cfg.camera_ahead_m:g} m ahead of the axle, {flow_cfg.camera_height_m:g} m high"
           if flow_cfg.camera_ahead_m is not None else f"rig unknown (FOE {flow_cfg.foe_model})")
    print(f"labeler: hfov assumed {flow_cfg.hfov_deg:g} deg (synthetic camera: {cam}), "
          f"{flow_cfg.work_width_px} px, DIS {flow_cfg.flow_preset} (finest scale {flow_cfg.dis_finest_scale or 'preset'}"
          f"{', warm start' if flow_cfg.dis_warm_start else ''}), "
          f"preset {args.preset!r}; {rig}")
    rows = []   # (split, reader, item, start, true_deg, est_deg, traj_cmd_offset, traj_cmd_heading, quality)
    t_flow = 0.0
    for k, (name, item, ep) in enumerate(tqdm(list(episodes(root)), desc=f"flow {root.name}", unit="episode",
                                              disable=not sys.stderr.isatty())):
        if abs(ep.fps_hz - FPS) > 1e-6:
            continue
        t0 = time.process_time()
        lab = FlowLabeler(cfg)
        inc = lab.yaw_rates_deg(ep.frames(), ep.fps_hz) / ep.fps_hz
        t_flow += time.process_time() - t0
        yaw_true = gt.yaw_for(name, item)
        n = min(len(yaw_true), len(inc) + 1)
        gt_poses = gt.poses_for(name, item)
        split = "cal" if k % 2 == 0 else "test"
        for s in range(0, n - WIN, STRIDE):
            true = float(np.degrees(yaw_true[s + WIN] - yaw_true[s]))
            est = float(inc[s:s + WIN].sum())
            tc = th = None
            poses = ep.poses if ep.poses is not None else None
            if poses is not None and s + WIN < len(poses):
                traj = trajectory_from_poses(poses, s, ep.fps_hz)
                tc = command_from_trajectory(traj, CommandConfig())[0]
                th = command_from_trajectory(traj, CommandConfig(trajectory_rule="heading"))[0]
            rows.append((split, name, item, s, true, est, tc, th, float(np.median(lab.last_quality[s:s + WIN]))))
    if not rows:
        sys.exit("no 10 Hz episodes found")
    true = np.array([r[4] for r in rows])
    est = np.array([r[5] for r in rows])
    split = np.array([r[0] for r in rows])
    ref = [cmd_of(t, args.ref_threshold_deg) for t in true]
    cal, test = split == "cal", split == "test"
    cands = np.arange(5.0, 30.01, 0.5)
    acc_cal = [np.mean([cmd_of(e, c) == r for e, r, m in zip(est, ref, cal) if m]) for c in cands]
    best = float(cands[int(np.argmax(acc_cal))])
    # ties: take the middle of the best plateau
    plateau = cands[np.isclose(acc_cal, max(acc_cal))]
    best = float(plateau[len(plateau) // 2])
    pred = [cmd_of(e, best) for e in est]
    m = confusion([r for r, t in zip(ref, test) if t], [p for p, t in zip(pred, test) if t])
    err = np.abs(est - true)
    acc = float(np.trace(m) / m.sum())
    out = {
        "windows": {"calibration": int(cal.sum()), "held_out": int(test.sum())},
        "hfov_assumed_deg": flow_cfg.hfov_deg, "reference_threshold_deg": args.ref_threshold_deg,
        "labeler_config": to_dict(cfg), "preset": args.preset, "known_rig": bool(args.known_rig),
        "calibrated_threshold_deg": best, "calibration_accuracy": float(max(acc_cal)),
        "held_out_accuracy": acc, "confusion_held_out": m.tolist(),
        "yaw_err_deg_held_out": {"median": float(np.median(err[test])), "p90": float(np.percentile(err[test], 90)),
                                 "max": float(err[test].max())},
        "true_abs_yaw_deg_held_out": {"median": float(np.median(np.abs(true[test]))),
                                      "max": float(np.abs(true[test]).max())},
        "scale_fit": float(np.sum(est * true) / np.sum(true * true)),
        "flow_cpu_s": round(t_flow, 1),
        "held_out_errors": [{"reader": r[1], "item": r[2], "start_frame": r[3], "true_deg": round(r[4], 2),
                             "est_deg": round(r[5], 2), "quality": round(r[8], 3)}
                            for r, rf, p, t in zip(rows, ref, pred, test) if t and rf != p],
    }
    for rule, idx in (("lateral_offset", 6), ("heading", 7)):
        pairs = [(p, r[idx]) for p, r in zip(pred, rows) if r[idx] is not None]
        if pairs:
            out[f"agreement_flow_vs_trajectory_{rule}"] = {
                "windows": len(pairs), "agree": float(np.mean([a == b for a, b in pairs]))}
    print(f"windows: {out['windows']}; calibrated flow threshold: {best:g} deg "
          f"(calibration accuracy {out['calibration_accuracy']:.3f})")
    print(f"held-out accuracy: {acc:.3f}   yaw error (deg / 4 s window): median {out['yaw_err_deg_held_out']['median']:.2f}, "
          f"p90 {out['yaw_err_deg_held_out']['p90']:.2f}, max {out['yaw_err_deg_held_out']['max']:.2f}; "
          f"est/true scale {out['scale_fit']:.3f}")
    print("confusion (rows true, cols flow; left / forward / right):")
    for name, row in zip(("left", "forward", "right"), m):
        print(f"  {name:>8} " + " ".join(f"{v:6d}" for v in row))
    for k in ("agreement_flow_vs_trajectory_lateral_offset", "agreement_flow_vs_trajectory_heading"):
        if k in out:
            print(f"{k}: {out[k]['agree']:.3f} of {out[k]['windows']} windows")
    for e in out["held_out_errors"]:
        print(f"  held-out error: {e['reader']} {e['item']} frame {e['start_frame']}: true {e['true_deg']:+.1f}, "
              f"flow {e['est_deg']:+.1f} deg (quality {e['quality']:.2f})")
    ok = np.array([r == p for r, p in zip(ref, pred)])
    held = {"true": true[test], "est": est[test], "correct": ok[test], "threshold_deg": best}
    return out, err[test], int(np.trace(m)), held


if __name__ == "__main__":
    sys.exit(main())
