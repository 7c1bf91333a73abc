"""Keep a long world-model run across machines: its EMA weights as one file at one path, with its progress.

A session may end on a machine that does not come back, with every uncommitted file. So at the end of each session
the run's EMA weights are committed as ``lab/runs/<name>/ema.safetensors`` (overwritten each time: one file,
~9 MB in float32: the weights the readings are made with, not a folder of checkpoints) beside ``progress.json``:
steps, CPU-hours spent (wall x threads, summed over the segments), the loss curve per 500 steps and the dev readings.
Where the machine survives, the run resumes exactly from its own checkpoint (``--resume``); where it does not, from this file
(``--set model.init_weights=lab/runs/<name>/ema.safetensors``; the optimiser restarts, the step count goes on
from ``progress.json``).

  python lab/milestone.py save RUN --name synth-world [--threads 2] [--segment-wall-s S] [--diag sizing.jsonl]
  python lab/milestone.py show --name synth-world
"""
from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

ROOT = Path(__file__).resolve().parent / "runs"


def save(run: Path, name: str, threads: float, segment_wall_s: float | None, diag: Path | None,
         spent_before: float | None = None) -> Path:
    dst = ROOT / name
    dst.mkdir(parents=True, exist_ok=True)
    final = run / "final"
    src = final / "ema.safetensors" if (final / "ema.safetensors").is_file() else final / "model.safetensors"
    shutil.copyfile(src, dst / "ema.safetensors.tmp")
    (dst / "ema.safetensors.tmp").replace(dst / "ema.safetensors")   # never a half-written file
    shutil.copyfile(run / "config.yaml", dst / "config.yaml")
    if (final / "data_encode.yaml").is_file():
        shutil.copyfile(final / "data_encode.yaml", dst / "data_encode.yaml")
    prev = json.loads((dst / "progress.json").read_text()) if (dst / "progress.json").is_file() else {}
    same_run = prev.get("run") == str(run.resolve())
    # a run restarted from this file (a new machine) goes on from the saved step and CPU-hours
    offset = int(prev.get("step_offset", 0)) if same_run or not prev else int(prev["step"])
    before = float(prev.get("cpu_hours_before", 0.0)) if same_run or not prev else float(prev["cpu_hours"])
    earlier = list(prev.get("earlier_runs", []))
    if spent_before is not None and not same_run:
        # a new run from scratch under the same budget: its steps start at 0, the earlier runs' CPU stays spent
        offset, before = 0, float(spent_before)
        if prev:
            earlier.append({"run": prev.get("run"), "step": prev.get("step"), "cpu_hours_counted":
                            round(float(spent_before) - sum(e["cpu_hours_counted"] for e in earlier), 2)})
    readings = [json.loads(x) for x in diag.read_text().splitlines()] if diag and diag.is_file() else []
    # the step of the weights in final/: the last reading's (written when the segment that exported them ended), else
    # the last checkpoint's; a segment still running has logged steps past it, which are not these weights'
    ckpts = sorted(int(c.name.split("_")[-1]) for c in (run / "checkpoints").glob("step_*"))
    final_step = readings[-1]["step"] if readings else (ckpts[-1] if ckpts else None)
    metrics = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines() if '"loss"' in x]
    metrics = [m for m in metrics if final_step is None or m["step"] <= final_step]
    wall = sum(m.get("step_time_s", 0.0) for m in metrics)
    curve = {}
    for m in metrics:
        curve.setdefault((offset + m["step"]) // 500 * 500, []).append(m["loss"])
    # the CPU the run's processes really used (lab/size_world.py measures it from their rusage), where recorded;
    # else wall x threads
    measured = readings[-1].get("cpu_min") if readings else None
    prog = {"name": name, "run": str(run.resolve()), "weights": src.name + " of the run",
            "step": offset + metrics[-1]["step"], "step_offset": offset,
            "cpu_hours": round(before + (measured / 60 if measured is not None else wall * threads / 3600), 2),
            "cpu_hours_from": "rusage of the training processes" if measured is not None else "wall x threads",
            "cpu_hours_before": before, "earlier_runs": earlier, "threads": threads,
            "loss_per_500_steps": {str(k): round(sum(v) / len(v), 5) for k, v in sorted(curve.items())},
            "segment_wall_s": segment_wall_s,
            "dev_readings": readings or prev.get("dev_readings", [])}
    (dst / "progress.json").write_text(json.dumps(prog, indent=1) + "\n")
    return dst


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("save")
    s.add_argument("run", type=Path)
    s.add_argument("--name", required=True)
    s.add_argument("--threads", type=float, default=2,
                   help="cores the run had (CPU-hours = wall x this; 3 runs side by side on 2 cores: 0.667)")
    s.add_argument("--segment-wall-s", type=float)
    s.add_argument("--diag", type=Path, help="a jsonl of dev readings to keep with the weights")
    s.add_argument("--spent-before", type=float,
                   help="first save of a new run from scratch under the same budget: CPU-hours the earlier runs spent")
    sh = sub.add_parser("show")
    sh.add_argument("--name", required=True)
    a = p.parse_args()
    if a.cmd == "save":
        print(f"saved {save(a.run, a.name, a.threads, a.segment_wall_s, a.diag, a.spent_before)}")
    else:
        print((ROOT / a.name / "progress.json").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
