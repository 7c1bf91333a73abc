"""`resim demo`: the whole system, small, on a CPU, with no downloads.

synthetic world → Ray pipeline → shards → tiny world model + tiny Video2Reward →
rollouts under three commands → ranking of candidate trajectories → evaluation (command accuracy of
rollouts under left / forward / right; an inverse dynamics model trained on the demo's shards;
Trajectory Difference and video quality on the episodes the IDM held out) → one HTML report.

Each step runs the same entry point a user would (``resim <command> ...``, in this
process), writes into its own folder under ``--out`` and leaves a ``.done`` marker
holding the step's arguments; a second run reuses finished steps unless ``--fresh``,
unless the step's arguments changed, or unless an earlier step was redone (every
step reads what the ones before it wrote).

Two world models: the demo trains its own small one for a few minutes (the machinery: trainer,
checkpoint, loss curve), and rolls out and evaluates the *shipped* synthetic-world model
(``configs/models/synth-world``, trained by the same commands for about 4.5 hours of CPU on worlds of
other seeds, the VAE's last stage on a GPU, docs/models/): the demo's world (seed 0) is held out from it. The
pipeline encodes with the shipped synthetic-world VAE (``configs/models/synth-vae``); the text
encoder and the reward model's DINOv2 stay tiny random-init placeholders.
"""
from __future__ import annotations

import argparse
import hashlib
import html
import json
import os
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from resim.cli import main
from resim.config import ConfigError, apply_overrides, from_dict, save, to_dict
from resim.models import shipped_model

REPO = Path(__file__).resolve().parents[1]


@dataclass
class DemoConfig:
    """Sizes of the demo. Presets: ``default`` (< 10 min on 2 cores), ``smoke`` (the test's)."""

    episodes: int = 12
    seed: int = 0
    synth_preset: str = "demo"
    world_steps: int = 500
    reward_epochs: int = 20
    sample_seconds: float = 4.0
    ddim_steps: int = 20
    plan_candidates: tuple[str, ...] = ("keep_lane", "turn_left", "turn_right", "brake", "swerve")
    workers: int = 2
    # evaluation: the IDM trains on the shards' 10 Hz clips with trajectories (CARLA-layout
    # episodes), holding out >= 2 whole episodes; `resim eval control|quality` roll the world model out on
    # `eval_clips` of the held-out clips (spread over the held-out episodes) with `ddim_steps` steps
    idm_epochs: int = 15
    idm_heldout_episodes: int = 2
    eval_clips: int = 6            # control: 2 rollouts + 2 VAE decodes per clip (~5 s per decode on 2 cores)
    quality_clips: int = 6         # quality: 1 rollout + decode per clip
    command_clips: int = 12        # commands: 4 rollouts per clip (left, forward, right, null prompt)
    # the world model the rollouts and evaluations use: a shipped model name (configs/models/NAME) or a run
    # folder; "" = the one the demo trains itself (minutes of training: expect noise)
    world_model: str = "synth-world"

    def __post_init__(self):
        if self.episodes < 9:
            raise ConfigError("episodes must be >= 9 (a third per layout; the evaluation needs 3 CARLA-layout "
                              "episodes with 10 Hz trajectories: one to train the IDM on, two held out)")
        if min(self.world_steps, self.reward_epochs, self.ddim_steps, self.idm_epochs, self.quality_clips,
               self.command_clips) < 1:
            raise ConfigError("world_steps, reward_epochs, ddim_steps, idm_epochs, quality_clips and command_clips "
                              "must be >= 1")
        if self.world_model and not world_model_dir(self.world_model, Path(".")).is_dir():
            raise ConfigError(f"world_model={self.world_model!r}: neither a shipped model (configs/models/NAME) "
                              "nor a folder; \"\" uses the demo's own")
        if self.eval_clips < 2:
            raise ConfigError("eval_clips must be >= 2 (control pairs clips of two episodes)")
        if self.workers < 1 or not self.sample_seconds > 0 or not self.plan_candidates:
            raise ConfigError("workers must be >= 1, sample_seconds > 0 and plan_candidates not empty")
        if self.idm_heldout_episodes < 2:
            raise ConfigError("idm_heldout_episodes must be >= 2 (non-expert trajectories come from another "
                              "held-out episode)")


PRESETS = {
    "default": {},
    "smoke": {"episodes": 9, "synth_preset": "tiny", "world_steps": 4, "reward_epochs": 1, "sample_seconds": 1.2,
              "ddim_steps": 2, "plan_candidates": ["keep_lane", "turn_left"], "idm_epochs": 1, "eval_clips": 2,
              "quality_clips": 1, "command_clips": 1},
}


def world_model_dir(name: str, out: Path) -> Path:
    """The world model of the rollouts/evaluations: "" = the demo's own run (OUT/world_model), else a shipped
    model name or a folder."""
    if not name:
        return out / "world_model"
    return Path(shipped_model(name))


class Step:
    """One demo step: a folder, the argv of a `resim` command, and a done-marker."""

    def __init__(self, name: str, out: Path, argv: list[str]):
        self.name, self.dir, self.argv = name, out, argv

    @property
    def marker(self) -> Path:
        return self.dir / ".done"

    def is_done(self, upstream: str = "") -> bool:
        """Finished with these arguments on top of these earlier steps (``upstream``: a digest of their markers)."""
        if not self.marker.is_file():
            return False
        m = json.loads(self.marker.read_text())
        return m.get("argv") == self.argv and m.get("upstream", "") == upstream

    def run(self, upstream: str = "") -> float:
        if self.dir.exists():
            shutil.rmtree(self.dir)  # an unfinished earlier attempt: start the step over
        t0 = time.perf_counter()
        rc = main(self.argv)
        if rc != 0:
            raise SystemExit(f"demo step {self.name!r} failed (exit {rc}): resim {' '.join(self.argv)}")
        dt = time.perf_counter() - t0
        self.dir.mkdir(parents=True, exist_ok=True)
        self.marker.write_text(json.dumps({"argv": self.argv, "seconds": dt, "upstream": upstream}))
        return dt


class StepRunner:
    """Runs steps in order, reusing a finished one only on top of the same earlier steps: a digest of their
    markers (a redone step writes a new one) goes into each marker. E.g. --set world_steps=300 retrains the
    world model, so the rollouts, planning and evaluations of the old model are redone too, not reused."""

    def __init__(self):
        self._chain = hashlib.sha256()
        self.timings: dict[str, float] = {}

    def go(self, step: Step, i: int, n: int) -> bool:
        """Runs or reuses ``step`` (``i`` of ``n``, for the log); True if it ran."""
        upstream = self._chain.hexdigest()[:16]
        ran = not step.is_done(upstream)
        if ran:
            print(f"[demo {i}/{n}] {step.name}: resim {' '.join(step.argv)}", flush=True)
            self.timings[step.name] = step.run(upstream)
            print(f"[demo {i}/{n}] {step.name}: done in {self.timings[step.name]:.1f} s", flush=True)
        else:
            print(f"[demo {i}/{n}] {step.name}: reusing {step.dir} (--fresh to redo)", flush=True)
            self.timings[step.name] = json.loads(step.marker.read_text())["seconds"]
        self._chain.update(step.marker.read_bytes())
        return ran


def pick_history_key(shards_dir: Path) -> str:
    """A held sample with a trajectory (NAVSIM/CARLA-like), preferring a turning clip, for rollouts/planning."""
    from shards.manifest import read_manifest   # pyarrow: not at the top, every `resim` call imports this module

    rows = read_manifest(shards_dir).to_pylist()
    if not rows:
        raise SystemExit(f"demo: no samples in {shards_dir}")
    rows.sort(key=lambda r: (not r["has_trajectory"], not r["is_turning"], r["key"]))
    return rows[0]["key"]


def build_steps(cfg: DemoConfig, out: Path) -> list[Step]:
    world, data = out / "world", out / "shards"
    steps = [
        Step("synthetic world", world, ["synth", "--out", str(world), "--episodes", str(cfg.episodes),
                                        "--seed", str(cfg.seed), "--preset", cfg.synth_preset,
                                        "--workers", str(cfg.workers), "--overwrite",
                                        "--contact-sheet", str(world / "contact_sheet.png")]),
        Step("pipeline", data, ["pipeline", "run", str(REPO / "configs/pipeline/synthetic.yaml"), "--out", str(data),
                                "--set", f"sources.synthetic.root={world}",
                                "--set", f"sources.synthetic.episodes={cfg.episodes}",
                                "--set", f"sources.synthetic.seed={cfg.seed}",
                                "--set", f"sources.synthetic.preset={cfg.synth_preset}"]),
        Step("world model", out / "world_model", ["train", "world", "--preset", "tiny", "--shards", str(data),
                                                  "--out", str(out / "world_model"), "--steps", str(cfg.world_steps),
                                                  "--checkpoint-every", str(cfg.world_steps)]),
        Step("reward model", out / "reward_model", ["train", "reward", "--preset", "tiny", "--shards", str(data),
                                                    "--out", str(out / "reward_model"), "--no-progress",
                                                    "--set", f"epochs={cfg.reward_epochs}"]),
    ]
    return steps


def rollout_steps(cfg: DemoConfig, out: Path, key: str) -> list[Step]:
    data = out / "shards"
    common = ["--checkpoint", str(world_model_dir(cfg.world_model, out)), "--history", key, "--shards", str(data),
              "--seconds", str(cfg.sample_seconds), "--seed", str(cfg.seed), "--steps", str(cfg.ddim_steps)]
    steps = []
    for name, command in (("left", "Turning left"), ("forward", "Moving forward"), ("right", "Turning right")):
        d = out / "samples" / name
        steps.append(Step(f"rollout: {command}", d, ["sample", *common, "--command", command, "--out", str(d)]))
    d = out / "plan"
    steps.append(Step("planning", d, ["plan", *common, "--reward", str(out / "reward_model"),
                                      "--candidates", *cfg.plan_candidates, "--out", str(d)]))
    return steps


def eval_steps(cfg: DemoConfig, out: Path) -> list[Step]:
    """IDM on the demo's shards, then Trajectory Difference and video quality of the world model on the
    clips of the episodes the IDM held out (on a tiny trained world model)."""
    data, ev = out / "shards", out / "eval"
    wm = ["--checkpoint", str(world_model_dir(cfg.world_model, out)), "--shards", str(data), "--steps",
          str(cfg.ddim_steps), "--seed", str(cfg.seed), "--batch-size", "4"]
    world = [*wm, "--heldout-from", str(ev / "idm")]
    return [
        # every clip of the demo's world is held out from the shipped model (trained on other seeds)
        Step("eval: command accuracy", ev / "commands",
             ["eval", "commands", *wm, "--all-clips", "--limit", str(cfg.command_clips), "--out", str(ev / "commands")]),
        Step("eval: inverse dynamics model", ev / "idm",
             ["eval", "idm", "--shards", str(data), "--out", str(ev / "idm"), "--preset", "tiny",
              "--epochs", str(cfg.idm_epochs), "--batch-size", "8", "--seed", str(cfg.seed),
              "--min-heldout-episodes", str(cfg.idm_heldout_episodes)]),
        Step("eval: controllability", ev / "control",
             ["eval", "control", *world, "--limit", str(cfg.eval_clips), "--idm", str(ev / "idm"),
              "--out", str(ev / "control")]),
        # PSNR/SSIM only: FID/FVD/LPIPS need the standard network weights (docs/eval.md), which the demo does
        # not download; random-init networks would give numbers that compare with nothing
        Step("eval: video quality", ev / "quality",
             ["eval", "quality", *world, "--limit", str(cfg.quality_clips), "--metrics", "psnr", "ssim",
              "--out", str(ev / "quality")]),
    ]


def _img(path: Path, root: Path, caption: str) -> str:
    if not path.is_file():
        return f"<p><em>missing: {html.escape(str(path.relative_to(root)))}</em></p>"
    rel = html.escape(str(path.relative_to(root)))
    return f'<figure><img src="{rel}" style="max-width:100%"><figcaption>{html.escape(caption)}</figcaption></figure>'


def _stats_table(path: Path) -> str:
    """The pipeline's stats.json as two small tables (units; clips per origin and command), not a raw dump."""
    if not path.is_file():
        return ""
    st = json.loads(path.read_text())
    u, ts = st.get("units", {}), st.get("turning_share", {})
    head = (f"<p>Units: {u.get('ok', '?')} ok, {u.get('quarantined', '?')} quarantined of {u.get('total', '?')}. "
            f"Clips: {st.get('clips', {}).get('total', '?')}; turning share {ts.get('before', '?')} before, "
            f"{ts.get('after', '?')} after ReSim's {ts.get('turn_factor', '?')}x over-sampling of turns.</p>")
    by = st.get("clips", {}).get("commands_by_origin", {})
    cmds = sorted({c for v in by.values() for c in v})
    rows = [[html.escape(o), *[v.get(c, 0) for c in cmds], sum(v.values())] for o, v in sorted(by.items())]
    return head + _table(["origin", *cmds, "clips"], rows)


def _reward_metrics(path: Path) -> str:
    if not path.is_file():
        return ""
    meta = json.loads(path.read_text())
    rows = [[split.split("_")[0]] + ["n/a" if m.get(k) is None else _f(m.get(k)) if isinstance(m.get(k), float)
                                      else html.escape(str(m.get(k)))
                                      for k in ("n", "n_hazard", "mae", "spearman", "hazard_auc")]
            for split in ("train_metrics", "heldout_metrics") for m in [meta.get(split) or {}]]
    return (_table(["split", "clips", "hazardous", "MAE", "Spearman", "AUC"], rows)
            + "<p>(n/a: undefined, the split has one class only or too few clips)</p>")


def _f(v, fmt: str = ".3f") -> str:
    return format(v, fmt) if isinstance(v, (int, float)) else html.escape(str(v))


def _table(header: list[str], rows: list[list]) -> str:
    """An HTML table. Header cells are escaped; row cells are printed as given (format/escape them: ``_f``)."""
    th = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    return (f"<table><tr>{th}</tr>" + "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in rows)
            + "</table>")


def _eval_section(out: Path) -> list[str]:
    """Section 6: the IDM's held-out ADE/FDE vs constant velocity, Trajectory Difference, PSNR/SSIM per horizon."""
    ev = out / "eval"
    parts = ["<h2>7. Evaluation: Trajectory Difference and video quality</h2>",
             "<p>An inverse dynamics model (IDM: video → 8 waypoints) is trained on the shards' 10 Hz clips with "
             "trajectories, split <b>by episode</b>; the world-model evaluations run on clips of the episodes the "
             "IDM held out (the IDM is small and trained here for seconds: its floor is loose).</p>"]
    idm_p = ev / "idm" / "idm_report.json"
    if idm_p.is_file():
        r = json.loads(idm_p.read_text())
        pro = r["protocol"]
        parts.append(f"<h3>IDM</h3><p>{pro['clips_train']} training clips ({pro['episodes_train']} episodes), "
                     f"{pro['clips_heldout']} held-out clips ({pro['episodes_heldout']} episodes: "
                     f"{html.escape(', '.join(pro['heldout_items']))}); validation: {html.escape(pro['validation'])}."
                     "</p>")
        parts += [_table(["held-out", "ADE (m)", "FDE (m)", "yaw err (deg)", "clips"],
                         [[html.escape(k), _f(v["ade_m"]), _f(v["fde_m"]), _f(v["yaw_err_deg"], ".2f"), v["n"]]
                          for k, v in r["heldout"].items()]), _img(ev / "idm" / "idm_report.png", out, "IDM vs constant velocity, held-out")]
    ctl_p = ev / "control" / "control.json"
    if ctl_p.is_file():
        r = json.loads(ctl_p.read_text())
        parts.append(f"<h3>Controllability: Trajectory Difference</h3><p>{r['protocol']['clips']} held-out clips "
                     f"of {r['protocol']['episodes']} episodes, each rolled out under its recorded trajectory "
                     "(expert) and another episode's (non-expert); the IDM reads the trajectory off the generated "
                     "video. <code>idm_on_recorded_video</code> (the IDM on the real frames) is the floor; "
                     "<code>idm_on_recorded_through_vae</code> (on the recorded latents decoded through the VAE) is "
                     "what a world model that predicted the recorded future exactly would score.</p>")
        parts.append(_table(["", "L2 mean (m)", "L2 at 4 s (m)", "clips"],
                            [[k, _f(r[k]["trajectory_difference_m"]), _f(r[k]["trajectory_difference_final_m"]),
                              r[k]["n"]] for k in ("expert", "non_expert", "idm_on_recorded_video",
                                                   "idm_on_recorded_through_vae") if k in r]))
        ca = r["command_accuracy"]
        acc = (html.escape(ca) if isinstance(ca, str) else ", ".join(
            f"{html.escape(k)}: {_f(v['accuracy'], '.2f')} (n={v['n']})" for k, v in ca.items()))
        parts += [f"<p>Command accuracy (optical-flow labeler on the generated future): {acc}</p>",
                  _img(ev / "control" / "control.png", out, "Trajectory Difference")]
    q_p = ev / "quality" / "quality.json"
    if q_p.is_file():
        r = json.loads(q_p.read_text())
        pro = r["protocol"]
        parts.append(f"<h3>Video quality</h3><p>{pro['clips']} held-out clips, {pro['conditioning_frames_excluded']} "
                     f"history frames excluded, {pro['future_frames_scored']} future frames scored at "
                     f"{pro['metric_resolution_hw']} ({html.escape(str(pro.get('generated_resize')))}). PSNR and "
                     "SSIM only: FID, FVD and LPIPS need the standard network weights (docs/eval.md), which the "
                     "demo does not download.</p>")
        parts += [_table(["horizon", "frames/clip", "PSNR (dB)", "SSIM"],
                         [[f"{row['from_s']:g}–{row['horizon_s']:g} s", row["frames_per_clip"],
                           _f(row.get("psnr"), ".2f"), _f(row.get("ssim"))] for row in r["per_horizon"]]), _img(ev / "quality" / "quality.png", out, "PSNR / SSIM vs prediction horizon")]
    parts.append("<p>Full reports: " + ", ".join(
        f'<a href="{html.escape(str(p.relative_to(out)))}">{html.escape(str(p.relative_to(out)))}</a>'
        for p in (idm_p, ctl_p, q_p) if p.is_file()) + "</p>")
    return parts


def _commands_section(out: Path, cfg: DemoConfig) -> list[str]:
    """Section 4: one held-out history rolled out under the three commands, and the command accuracy table."""
    d = out / "eval" / "commands"
    p = d / "commands.json"
    if not p.is_file():
        return []
    r = json.loads(p.read_text())
    fl = r["flow_labeler"]
    rows = [[html.escape(name), _f(fl[k]["accuracy"], ".2f"), fl[k]["n"],
             ", ".join(f"{html.escape(c.split()[-1])} {_f(v, '.2f')}" for c, v in fl[k]["per_command"].items())]
            for name, k in (("commanded (left / forward / right)", "commanded"),
                            ("null prompt (control: 1/3 = ignores the command)", "null_prompt"),
                            ("recorded future (the labeler's ceiling)", "recorded_future"),
                            ("recorded future through the VAE (the ceiling of any world model with this VAE)",
                             "recorded_through_vae")) if k in fl]
    fid = [[f"{x['horizon_s']:g} s", _f(x["psnr_model"], ".2f"), _f(x["psnr_copy_last_frame"], ".2f"),
            _f(x["ssim_model"]), _f(x["ssim_copy_last_frame"])] for x in r["fidelity"]["per_horizon"]]
    return [
        "<h2>4. Does the world model follow the command?</h2>",
        f"<p>World model: <code>{html.escape(cfg.world_model or 'the demo run')}</code>. "
        f"{r['protocol']['clips']} histories of the demo's world ({r['protocol']['episodes']} episodes, none of "
        "which the shipped model trained on), each rolled out under each command with no trajectory; the "
        "optical-flow labeler that labels real video reads which way each generated future turns.</p>",
        _img(d / "commands.gif", out, "recorded future | Turning left | Moving forward | Turning right "
                                      "(one history recorded going straight: the turns are counterfactual)"),
        _img(d / "commands_strip.png", out, "the same rollouts every 0.8 s"),
        _table(["condition", "accuracy", "rollouts", "per command"], rows),
        _img(d / "commands.png", out, "confusion matrices and PSNR vs horizon"),
        "<p>Fidelity of the rollout under the recorded command against the recorded future:</p>",
        _table(["horizon", "PSNR model", "PSNR copy-last-frame", "SSIM model", "SSIM copy-last-frame"], fid),
    ]


def write_report(out: Path, cfg: DemoConfig, timings: dict[str, float], key: str) -> Path:
    """One self-contained HTML page linking the PNG/GIF outputs of every step."""
    parts = [
        "<!doctype html><meta charset='utf-8'><title>resim demo</title>",
        "<style>body{font-family:sans-serif;max-width:1100px;margin:auto}figure{margin:1em 0}"
        "pre{background:#f4f4f4;padding:.5em;overflow:auto}td,th{padding:2px 8px}</style>",
        "<h1>resim demo</h1>",
        "<p>The rollouts and evaluations use the <b>shipped synthetic-world models</b> "
        "(<code>configs/models/synth-vae</code>, <code>configs/models/synth-world</code>; model cards in "
        "docs/models/), trained on a world of other seeds. The world model and Video2Reward in section 3 are "
        "trained here for minutes, to show the machinery. T5 and DINOv2 are tiny random-init placeholders.</p>"
        if cfg.world_model else
        "<p>The rollouts use the world model trained here for minutes (<code>world_model: \"\"</code>): expect "
        "noise.</p>",
        "<h2>Steps</h2>", _table(["step", "seconds"], [[html.escape(k), f"{v:.1f}"] for k, v in timings.items()]),
        "<h2>1. Synthetic world</h2>", _img(out / "world/contact_sheet.png", out, "a few synthetic episodes"),
        "<h2>2. Pipeline → shards</h2>", _img(out / "shards/report.png", out, "pipeline report"),
        _stats_table(out / "shards/stats.json"),
        "<h2>3. Training (here, for minutes: the machinery)</h2>",
        _img(out / "world_model/loss_curve.png", out, "world model loss (the demo's own run)"),
        _img(out / "reward_model/trainer/loss_curve.png", out, "Video2Reward loss"),
        _img(out / "reward_model/heldout_pred_vs_true.png", out, "Video2Reward: held-out predicted vs true infraction score"),
        _reward_metrics(out / "reward_model/final/meta.json"),
    ]
    parts += _commands_section(out, cfg)
    parts += [f"<h2>5. Rollouts from history <code>{html.escape(key)}</code> (resim sample)</h2>"]
    for name in ("left", "forward", "right"):
        d = out / "samples" / name
        gifs = sorted(d.glob("*.gif"))
        sheets = sorted(d.glob("*contact*.png")) or sorted(d.glob("*.png"))
        parts.append(f"<h3>{name}</h3>")
        if gifs:
            parts.append(_img(gifs[0], out, f"rollout, command: {name}"))
        if sheets:
            parts.append(_img(sheets[0], out, "contact sheet"))
    parts += ["<h2>6. Planning with Video2Reward</h2>"]
    pngs = sorted((out / "plan").glob("*.png"))
    if pngs:
        parts.append(_img(pngs[0], out, "imagined futures per candidate, with reward"))
    ranking = out / "plan" / "ranking.json"
    if ranking.is_file():
        rows = json.loads(ranking.read_text())
        parts.append(_table(["rank", "candidate", "command", "reward"],
                            [[r["rank"], html.escape(r["name"]), html.escape(str(r["command"])), f"{r['reward']:.4f}"]
                             for r in rows]))
    parts += _eval_section(out)
    parts.append("<h2>Config</h2><details><summary>the demo's resolved config (also demo_config.yaml)</summary>"
                 f"<pre>{html.escape(json.dumps(to_dict(cfg), indent=2))}</pre></details>")
    path = out / "report.html"
    path.write_text("\n".join(parts))
    return path


def check_fresh(out: Path) -> None:
    """--fresh deletes --out: only a folder the demo made (or an empty one), never e.g. `--out .` by mistake."""
    out = out.resolve()
    if out.is_dir() and any(out.iterdir()) and not (out / "demo_config.yaml").is_file():
        raise ConfigError(f"--fresh would delete {out}, which is not a demo output folder (no demo_config.yaml); "
                          "give an --out the demo made, or a new folder")


def run_demo(cfg: DemoConfig, out: Path, fresh: bool = False) -> Path:
    out = out.resolve()
    if fresh and out.exists():
        check_fresh(out)
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)
    save(cfg, out / "demo_config.yaml")
    steps = build_steps(cfg, out)
    t_all = time.perf_counter()

    runner = StepRunner()
    go = runner.go
    evals = eval_steps(cfg, out)
    n = len(steps) + 4 + len(evals)
    for i, step in enumerate(steps, 1):
        go(step, i, n)
    key = pick_history_key(out / "shards")
    for i, step in enumerate(rollout_steps(cfg, out, key), len(steps) + 1):
        go(step, i, n)
    for i, step in enumerate(evals, len(steps) + 5):
        go(step, i, n)
    report = write_report(out, cfg, runner.timings, key)
    print(f"[demo] finished in {time.perf_counter() - t_all:.1f} s (steps reused count their first run)")
    print(f"[demo] report: {report}")
    return report


def _cmd_demo(args: argparse.Namespace) -> int:
    # The demo's models are tiny: thread synchronisation costs more than it saves. Measured on the 2-core
    # dev machine with the other core busy: a tiny world-model step took 33 ms on 1 thread, 1.5 s on 2.
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    # torch after OMP_NUM_THREADS is set, and not at the top: every `resim` call imports this module
    import torch

    torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    os.environ.setdefault("RAY_AUTH_MODE", "disabled")
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    data = dict(PRESETS[args.preset])

    try:
        apply_overrides(data, args.overrides)
        cfg = from_dict(DemoConfig, data)
        if args.fresh:
            check_fresh(Path(args.out))
    except ConfigError as e:
        print(f"resim demo: error: {e}", file=sys.stderr)
        return 2
    run_demo(cfg, Path(args.out), fresh=args.fresh)
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "demo", help="run the whole system small on a CPU and write an HTML report",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--out", default="demo_out", help="output folder (default: ./demo_out)")
    p.add_argument("--preset", default="default", choices=sorted(PRESETS),
                   help="default: < 10 min on 2 cores; smoke: a minute, for tests")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a DemoConfig field, e.g. --set world_steps=300")
    p.add_argument("--fresh", action="store_true", help="delete --out first and redo every step")
    p.set_defaults(func=_cmd_demo)
