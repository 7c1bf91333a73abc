"""Sizing study of the synthetic world model: arms trained for equal CPU time, read at fixed milestones.

Each arm is `resim train world --preset synth-world` with its own model overrides, trained in segments of
``--segment-min`` minutes of wall clock (`trainer.max_wall_s`; one thread per arm, at most ``--parallel`` arms at
once, sharing the cores alike). Each arm's CPU time is measured (its training processes' rusage), not assumed
from the wall clock, and is the x axis: ``cpu_min``. The preset's learning rate is constant after warm-up, so a
segmented run is the same run as an unbroken one (`--resume` is exact). After each segment the arm's EMA weights
are read on the dev clips (never the held-out world):

* training loss: the mean of the segment's last 50 logged steps;
* the command-shuffle loss ratio: `resim eval command-loss` (loss under the opposite turn / under the recorded
  command, turning clips; and under the null prompt), > 1 when the model uses the command;
* counterfactual branches and the left - right heading as decoded: `resim eval commands --counterfactual-only`
  (each fork history under left / forward / right, read by the flow labeler), and the same rollouts' PSNR /
  SSIM at 1 s under the recorded command beside copy-last-frame (a speckled rollout reads as noise to the labeler:
  look at the segment's ``diag/ARM-N/commands/commands_strip.png`` before reading its turns);
* ``lab/x0_reading.py``: the one-step clean estimate's latent MSE at t = 200 and the plain-DDIM latents' std beside
  the recorded one (residual noise the sampler draws as speckle).

One row per (arm, milestone) goes to OUT/sizing.jsonl; OUT/sizing.png plots them against CPU minutes. Pick by the
slope of the curves, not their level (docs/lab/). Usage:

  python lab/size_world.py --data DATA --dev DEV --out OUT --arms S M L --segments 4 --segment-min 10
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

# width = heads x 32; the synth preset is M
ARMS = {
    "S": {"num_attention_heads": 4, "num_layers": 4, "time_embed_dim": 128},
    "M": {"num_attention_heads": 6, "num_layers": 6, "time_embed_dim": 128},
    "L": {"num_attention_heads": 8, "num_layers": 8, "time_embed_dim": 192},
}
RESIM = [sys.executable, "-m", "resim.cli"]


THREADS = 1   # torch threads of every command (--threads): 1 for arms side by side, 2 for the long run alone


def _run(cmd: list[str], log: Path) -> float:
    """Run ``cmd`` at ``THREADS`` threads; returns the CPU seconds it used (user + system, its own rusage from wait4), so
    arms that share the cores with each other or with anything else are compared by the CPU they really got."""
    env = {**os.environ, "OMP_NUM_THREADS": str(THREADS), "MKL_NUM_THREADS": str(THREADS)}
    with open(log, "a") as f:
        f.write(f"$ {' '.join(cmd)}\n")
        f.flush()
        proc = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, env=env)
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode:
        raise RuntimeError(f"{cmd[3:5]} exited {proc.returncode}: see {log}")
    return usage.ru_utime + usage.ru_stime


def _sets(arm: str, extra: list[str]) -> list[str]:
    out = []
    for k, v in ARMS[arm].items():
        out += ["--set", f"model.overrides.{k}={v}"]
    for s in extra:
        out += ["--set", s]
    return out


def diagnostics(run: Path, dev: Path, out: Path, limit: int, steps: int, log: Path) -> dict:
    """The dev readings of one milestone (see the module docstring)."""
    out.mkdir(parents=True, exist_ok=True)
    _run(RESIM + ["eval", "command-loss", "--checkpoint", str(run), "--shards", str(dev), "--all-clips",
                  "--limit", str(4 * limit), "--levels", "700", "400", "--device", "cpu", "--out", str(out / "closs")],
         log)
    closs = json.loads((out / "closs" / "command_loss.json").read_text())
    _run(RESIM + ["eval", "commands", "--checkpoint", str(run), "--shards", str(dev), "--all-clips",
                  "--counterfactual-only", "--limit", str(limit), "--steps", str(steps), "--device", "cpu",
                  "--out", str(out / "commands")], log)
    com = json.loads((out / "commands" / "commands.json").read_text())
    x0_rows = out / "x0.jsonl"
    x0_rows.unlink(missing_ok=True)
    _run([sys.executable, str(Path(__file__).with_name("x0_reading.py")), "--checkpoint", str(run), "--shards",
          str(dev), "--clips", "16", "--out", str(x0_rows), "--png", str(out)], log)
    x0 = json.loads(x0_rows.read_text().splitlines()[-1])
    yaw = com["flow_labeler"]["mean_yaw_deg"]
    # fidelity at 1 s under the recorded command (the target: beat copy-last); SSIM shows a speckled
    # rollout that PSNR alone can hide
    one_s = next((h for h in com["fidelity"]["per_horizon"] if h["horizon_s"] == 1.0), {})
    lv = {k: {m: v.get(m) for m in ("accuracy", "worth_opposite", "worth_null")} for k, v in closs["levels"].items()}
    return {"command_loss": lv,
            "shuffle_ratio_400": 1 + (lv["400"]["worth_opposite"] or 0.0),
            "commanded_accuracy": com["flow_labeler"]["commanded"]["accuracy"],
            "branch_accuracy": com["branches"].get("commanded", {}).get("accuracy"),
            "mean_yaw_deg": yaw,
            "left_minus_right_deg": yaw["Turning left"] - yaw["Turning right"],
            # does the output's rank bind? (x0_reading: the one-step estimate at t = 200, the sampled latents' energy)
            "x0_mse_t200": x0["levels"]["200"]["latent_mse"], "ddim_latent_std": x0["ddim"]["latent_std"],
            "recorded_latent_std": x0["ddim"]["true_latent_std"],
            "psnr_1s": one_s.get("psnr_model"), "psnr_1s_copy_last": one_s.get("psnr_copy_last_frame"),
            "ssim_1s": one_s.get("ssim_model"), "ssim_1s_copy_last": one_s.get("ssim_copy_last_frame")}


def train_arm(arm: str, a) -> None:
    run, log = a.out / arm, a.out / f"{arm}.log"
    rows = a.out / "sizing.jsonl"
    # a rerun with more --segments goes on after the milestones already read (the arm resumes from its checkpoint)
    done_before = [json.loads(x) for x in rows.read_text().splitlines()] if rows.is_file() else []
    start = 1 + max([r["segment"] for r in done_before if r["arm"] == arm], default=0)
    cpu_s = 60 * max([r.get("cpu_min", 0.0) for r in done_before if r["arm"] == arm], default=0.0)
    for seg in range(start, a.segments + 1):
        done = run / "metrics.jsonl"
        cmd = RESIM + ["train", "world", "--preset", "synth-world", "--shards", str(a.data), "--out", str(run),
                       "--steps", "1000000", *_sets(arm, [f"trainer.max_wall_s={60 * a.segment_min}",
                                                           "trainer.checkpoint_every_steps=1000000",
                                                           "trainer.progress_bar=false", *a.set])]
        t0 = time.time()
        cpu_s += _run(cmd + (["--resume"] if done.is_file() else []), log)
        metrics = [json.loads(x) for x in done.read_text().splitlines() if '"loss"' in x]
        row = {"arm": arm, "segment": seg, "cpu_min": round(cpu_s / 60, 1),
               "step": metrics[-1]["step"],
               "train_wall_s": round(time.time() - t0, 1),
               "loss": sum(m["loss"] for m in metrics[-50:]) / len(metrics[-50:]),
               "step_time_s": sum(m["step_time_s"] for m in metrics[-50:]) / len(metrics[-50:])}
        row.update(diagnostics(run, a.dev, a.out / "diag" / f"{arm}-{seg}", a.limit, a.steps, log))
        with open(rows, "a") as f:
            f.write(json.dumps(row) + "\n")
        print(f"[size_world] {arm} segment {seg}: step {row['step']}, loss {row['loss']:.4f}, shuffle ratio "
              f"{row['shuffle_ratio_400']:.3f}, branches {row['branch_accuracy']}, left-right "
              f"{row['left_minus_right_deg']:+.1f} deg, SSIM at 1 s {row['ssim_1s']} (copy-last "
              f"{row['ssim_1s_copy_last']})", flush=True)


def plot(out: Path) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [json.loads(x) for x in (out / "sizing.jsonl").read_text().splitlines()]
    keys = [("loss", "training loss"), ("shuffle_ratio_400", "loss(opposite) / loss(own), t=400"),
            ("branch_accuracy", "fork branch accuracy (latents)"), ("left_minus_right_deg", "left - right (deg)"),
            ("ssim_1s", "SSIM at 1 s (copy-last dashed)")]
    fig, axes = plt.subplots(1, len(keys), figsize=(4.2 * len(keys), 3.4))
    for ax, (k, title) in zip(axes, keys):
        for arm in sorted({r["arm"] for r in rows}):
            rr = [r for r in rows if r["arm"] == arm and r.get(k) is not None]
            ax.plot([r["cpu_min"] for r in rr], [r[k] for r in rr], "o-", label=arm)
            if k == "ssim_1s" and rr:
                ax.plot([r["cpu_min"] for r in rr], [r["ssim_1s_copy_last"] for r in rr], "--", color="grey")
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("CPU minutes")
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(out / "sizing.png", dpi=110)
    return out / "sizing.png"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, required=True, help="training dataset (resim pipeline run)")
    p.add_argument("--dev", type=Path, required=True, help="dev fork clips for the readings (not the held-out world)")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--arms", nargs="+", default=list(ARMS), choices=list(ARMS))
    p.add_argument("--segments", type=int, default=4)
    p.add_argument("--segment-min", type=float, default=10.0)
    p.add_argument("--parallel", type=int, default=2)
    p.add_argument("--limit", type=int, default=12, help="fork clips of the commands reading")
    p.add_argument("--steps", type=int, default=20, help="DDIM steps of the commands reading")
    p.add_argument("--set", action="append", default=[], help="extra config override for every arm")
    p.add_argument("--threads", type=int, default=1,
                   help="torch threads per command (default 1; the long run, one arm alone on the machine: 2)")
    a = p.parse_args()
    global THREADS
    THREADS = a.threads
    a.out.mkdir(parents=True, exist_ok=True)
    with ThreadPoolExecutor(a.parallel) as ex:
        for f in [ex.submit(train_arm, arm, a) for arm in a.arms]:
            f.result()
    print(f"[size_world] {a.out / 'sizing.jsonl'}, {plot(a.out)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
