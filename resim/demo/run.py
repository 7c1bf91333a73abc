"""`resim demo`: the whole system, small, on a CPU, with no downloads.

synthetic world → Ray pipeline → shards → tiny world model + tiny Video2Reward →
rollouts under three commands → ranking of candidate trajectories → evaluation (command accuracy of
rollouts under left / forward / right; an inverse dynamics model trained on the demo's shards;
Trajectory Difference and video quality on the episodes the IDM held out; a pixel policy and its degraded
versions driving in the true simulator and inside the world model, ranked by both) → one HTML report.

Each step runs the same entry point a user would (``resim <command> ...``, in this
process), writes into its own folder under ``--out`` and leaves a ``.done`` marker
holding the step's arguments; a second run reuses finished steps unless ``--fresh``,
unless the step's arguments changed, or unless an earlier step was redone (every
step reads what the ones before it wrote). The console gets one line per step with its time; what a step prints
goes to ``--out/logs/NN-step.log`` (``--verbose``: to the console instead), and a failed step shows the
end of its log.

Two world models: the demo trains its own small one for a few minutes (the machinery: trainer,
checkpoint, loss curve), and rolls out and evaluates the *shipped* synthetic-world model
(``configs/models/synth-world``, trained by the same commands for about 4.5 hours of CPU on worlds of
other seeds, the VAE's last stage on a GPU, docs/models/): the demo's world (seed 0) is held out from it. The
pipeline encodes with the shipped synthetic-world VAE (``configs/models/synth-vae``); the text
encoder and the reward model's DINOv2 stay tiny random-init placeholders.
"""
from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import os
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from resim.cli import main
from resim.config import ConfigError, apply_overrides, from_dict, save, to_dict
from resim.demo.report import write_report
from resim.models.policy.variants import VARIANTS
from resim.shipped import SYNTH_IDM, SYNTH_POLICY, shipped_model

REPO = Path(__file__).resolve().parents[2]


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
    # evaluation: the pipeline's split holds out `heldout_episodes` whole episodes of each (source, hazard)
    # stratum of 2 or more (split.json); the IDM trains on the train side's 10 Hz clips with trajectories
    # (CARLA-layout episodes); `resim eval control|quality` roll the world model out on `eval_clips` of the
    # held-out clips (spread over the held-out episodes) with `ddim_steps` steps
    idm_epochs: int = 15
    heldout_episodes: int = 2
    eval_clips: int = 6            # control: 2 rollouts + 2 VAE decodes per clip (~5 s per decode on 2 cores)
    quality_clips: int = 6         # quality: 1 rollout + decode per clip
    command_clips: int = 12        # commands: 4 rollouts per clip (left, forward, right, null prompt)
    # closed loop: the shipped pixel policy and its graded versions drive fork worlds of seed 5000 (never trained
    # on) in the true simulator and inside the world model, read by the shipped IDM and the demo's Video2Reward
    closed_loop_variants: tuple[str, ...] = ("policy", "bias2", "cv")
    closed_loop_states: int = 2
    closed_loop_seconds: float = 4.0
    closed_loop_steps: int = 10    # DDIM steps per 0.4-s decision
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
        if self.closed_loop_states < 2 or self.closed_loop_seconds < 4 or self.closed_loop_steps < 1:
            raise ConfigError("closed_loop_states must be >= 2 (a rank needs two), closed_loop_seconds >= 4 (the IDM "
                              "proxy reads 4-s windows) and closed_loop_steps >= 1")
        unknown = set(self.closed_loop_variants) - set(VARIANTS)
        if unknown or len(self.closed_loop_variants) < 2:
            raise ConfigError(f"closed_loop_variants: two or more of {', '.join(VARIANTS)}; got "
                              f"{list(self.closed_loop_variants)}")
        if self.heldout_episodes < 2:
            raise ConfigError("heldout_episodes must be >= 2 (non-expert trajectories come from another "
                              "held-out episode)")


PRESETS = {
    "default": {},
    "smoke": {"episodes": 9, "synth_preset": "tiny", "world_steps": 4, "reward_epochs": 1, "sample_seconds": 1.2,
              "ddim_steps": 2, "plan_candidates": ["keep_lane", "turn_left"], "idm_epochs": 1, "eval_clips": 2,
              "quality_clips": 1, "command_clips": 1, "closed_loop_variants": ["policy", "cv"],
              "closed_loop_steps": 1},
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

    def run(self, upstream: str = "", log: Path | None = None) -> float:
        """Run the step; with ``log``, everything it prints (its processes and Ray's workers too) goes there."""
        if self.dir.exists():
            shutil.rmtree(self.dir)  # an unfinished earlier attempt: start the step over
        t0 = time.perf_counter()
        with _output_to(log) if log else contextlib.nullcontext():
            rc = main(self.argv)
        if rc != 0:
            tail = "".join(log.read_text(errors="replace").splitlines(keepends=True)[-15:]) if log else ""
            raise SystemExit(f"{tail}demo step {self.name!r} failed (exit {rc}): resim {' '.join(self.argv)}"
                             + (f"\n(its whole output: {log})" if log else ""))
        dt = time.perf_counter() - t0
        self.dir.mkdir(parents=True, exist_ok=True)
        self.marker.write_text(json.dumps({"argv": self.argv, "seconds": dt, "upstream": upstream}))
        return dt


@contextlib.contextmanager
def _output_to(path: Path):
    """Point this process's stdout and stderr (the file descriptors, so that C libraries, child processes and Ray's
    forwarded worker logs follow) at ``path`` for the duration."""
    path.parent.mkdir(parents=True, exist_ok=True)
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    try:
        # the descriptors for what writes to them directly; sys.stdout/stderr too, for where they are not fds 1 and 2
        # (a caller that captured them)
        with open(path, "a", buffering=1) as f, contextlib.redirect_stdout(f), contextlib.redirect_stderr(f):
            os.dup2(f.fileno(), 1)
            os.dup2(f.fileno(), 2)
            yield
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        os.close(saved[0])
        os.close(saved[1])


class StepRunner:
    """Runs steps in order, reusing a finished one only on top of the same earlier steps: a digest of their
    markers (a redone step writes a new one) goes into each marker. E.g. --set world_steps=300 retrains the
    world model, so the rollouts, planning and evaluations of the old model are redone too, not reused.
    ``log_dir``: each step's output goes to ``log_dir/NN-<step>.log`` (None: to the console)."""

    def __init__(self, log_dir: Path | None = None):
        self._chain = hashlib.sha256()
        self.timings: dict[str, float] = {}
        self.log_dir = log_dir

    def go(self, step: Step, i: int, n: int) -> bool:
        """Runs or reuses ``step`` (``i`` of ``n``, for the log); True if it ran."""
        upstream = self._chain.hexdigest()[:16]
        ran = not step.is_done(upstream)
        if ran:
            log = None
            if self.log_dir is not None:
                log = self.log_dir / f"{i:02d}-{''.join(c if c.isalnum() else '-' for c in step.name)}.log"
                log.unlink(missing_ok=True)
                if sys.stdout.isatty():   # the step's line shows while it runs, then becomes its result
                    print(f"[demo {i}/{n}] {step.name}: running (log: {log}) ...", end="", flush=True)
            else:
                print(f"[demo {i}/{n}] {step.name}: resim {' '.join(step.argv)}", flush=True)
            try:
                self.timings[step.name] = step.run(upstream, log)
            except BaseException:
                if log and sys.stdout.isatty():
                    print(flush=True)   # end the "running" line before the error
                raise
            done = f"[demo {i}/{n}] {step.name}: done in {self.timings[step.name]:.1f} s" + (f" (log: {log})" if log else "")
            print(("\r\033[K" if log and sys.stdout.isatty() else "") + done, flush=True)
        else:
            print(f"[demo {i}/{n}] {step.name}: reusing {step.dir} (--fresh to redo)", flush=True)
            self.timings[step.name] = json.loads(step.marker.read_text())["seconds"]
        self._chain.update(step.marker.read_bytes())
        return ran


def pick_history_key(shards_dir: Path) -> str:
    """A held sample with a trajectory (NAVSIM/CARLA-like), preferring a turning clip, for rollouts/planning."""
    from resim.shards.manifest import read_manifest   # pyarrow: not at the top, every `resim` call imports this module

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
                                "--set", f"sources.synthetic.preset={cfg.synth_preset}",
                                "--set", f"split.min_heldout_episodes={cfg.heldout_episodes}"]),
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
    clips of the episodes the shards' split holds out."""
    data, ev = out / "shards", out / "eval"
    wm = ["--checkpoint", str(world_model_dir(cfg.world_model, out)), "--shards", str(data), "--steps",
          str(cfg.ddim_steps), "--seed", str(cfg.seed), "--set", "runtime.batch_size=4"]
    world = wm    # the held-out side of the shards' split, which the IDM and the demo's world model never saw
    return [
        # every clip of the demo's world is held out from the shipped model (trained on other seeds)
        Step("eval: command accuracy", ev / "commands",
             ["eval", "commands", *wm, "--all-clips", "--limit", str(cfg.command_clips), "--out", str(ev / "commands")]),
        Step("eval: inverse dynamics model", ev / "idm",
             ["train", "idm", "--shards", str(data), "--out", str(ev / "idm"), "--preset", "tiny",
              "--epochs", str(cfg.idm_epochs), "--batch-size", "8", "--seed", str(cfg.seed)]),
        Step("eval: controllability", ev / "control",
             ["eval", "control", *world, "--limit", str(cfg.eval_clips), "--idm", str(ev / "idm"),
              "--out", str(ev / "control")]),
        # PSNR/SSIM only: FID/FVD/LPIPS need the standard network weights (docs/eval.md), which the demo does
        # not download; random-init networks would give numbers that compare with nothing
        Step("eval: video quality", ev / "quality",
             ["eval", "quality", *world, "--limit", str(cfg.quality_clips), "--metrics", "psnr", "ssim",
              "--out", str(ev / "quality")]),
        Step("eval: closed loop", ev / "closed_loop",
             ["eval", "closed-loop", "--checkpoint", str(world_model_dir(cfg.world_model, out)), "--shards", str(data),
              "--policy", SYNTH_POLICY, "--idm", SYNTH_IDM, "--reward", str(out / "reward_model"),
              "--set", f"closed_loop.variants=[{', '.join(cfg.closed_loop_variants)}]",
              "--set", f"closed_loop.states={cfg.closed_loop_states}",
              "--seconds", str(cfg.closed_loop_seconds), "--steps", str(cfg.closed_loop_steps),
              "--seed", str(cfg.seed), "--out", str(ev / "closed_loop")]),
    ]


def check_fresh(out: Path) -> None:
    """--fresh deletes --out: only a folder the demo made (or an empty one), never e.g. `--out .` by mistake."""
    out = out.resolve()
    if out.is_dir() and any(out.iterdir()) and not (out / "demo_config.yaml").is_file():
        raise ConfigError(f"--fresh would delete {out}, which is not a demo output folder (no demo_config.yaml); "
                          "give an --out the demo made, or a new folder")


def run_demo(cfg: DemoConfig, out: Path, fresh: bool = False, verbose: bool = False) -> Path:
    out = out.resolve()
    if fresh and out.exists():
        check_fresh(out)
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)
    save(cfg, out / "demo_config.yaml")
    steps = build_steps(cfg, out)
    t_all = time.perf_counter()

    runner = StepRunner(None if verbose else out / "logs")
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
    run_demo(cfg, Path(args.out), fresh=args.fresh, verbose=args.verbose)
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
    p.add_argument("--verbose", action="store_true",
                   help="show each step's command and everything it prints (default: one line per step; the output "
                        "goes to OUT/logs/NN-step.log)")
    p.set_defaults(func=_cmd_demo)
