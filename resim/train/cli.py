"""`resim train NAME ...` (one subcommand per model with presets) and `resim train launch`; `resim train idm` is
joined to this group by resim/cli.py (its code, with its held-out report, is in resim/eval/cli.py).

Light module: every `resim` call imports this module to register its subcommands, so what needs torch, numpy or the
models is imported inside the handler that uses it, to keep `resim --help` fast.
"""
from __future__ import annotations

import argparse
import errno
import os
import sys
from pathlib import Path

import yaml

from resim.config import ConfigError, to_dict
from resim.media.files import OUTPUT_ERRNOS
from resim.train.launch import add_launch_arguments, main_launch
from resim.train.presets import PRESETS, recipes_dir
from resim.train.tasks.policy_cli import add_train_parser as add_policy_parser
from resim.train.tasks.reward.cli import add_train_parser as add_reward_parser

TRAIN_EPILOG = """\
examples:
  resim train world --preset tiny --shards out/shards --out runs/wm             # seconds on a CPU
  resim train world --preset tiny --shards out/shards --out runs/wm --resume    # continue the latest checkpoint
  resim train world --preset stage2 --shards /data/resim --out runs/s2 \\
      --set model.init_weights=runs/s1/final/model.safetensors --set data.num_workers=8
  resim train launch --nnodes 5 --nproc-per-node 8 --dry-run -- world --preset stage1 --shards D --out R
  resim train distill --preset synth --shards out/shards --out runs/student \
      --set model.teacher=runs/wm --steps 1500                               # a 4-step student, no CFG

An --out that holds a run of the same model is refused unless --resume (continue; a run already at
trainer.steps has nothing to do and exits 0) or --overwrite (delete it, start over); an --out that holds
another kind of run (e.g. `resim train reward`'s) or a dataset is always refused.
The run folder gets config.yaml (resolved), metrics.jsonl (one JSON object per optimizer step),
tensorboard/, checkpoints/step_XXXXXXXX/ (sharded, atomic), final/model.safetensors and loss_curve.png.
Exit codes: 0 ok, 2 bad config or --out refused, 3 non-finite loss (message names the last good checkpoint), 4 bad data,
5 a refused or unreadable checkpoint, 6 the run folder cannot be written (disk full, read-only), 130 Ctrl-C.
"""


_WHAT = {"distill": "a few-step student of a world model (guidance + step distillation)"}
_MORE = {"distill": (" The teacher (model.teacher: a world-model run or a shipped name; default synth-world) rolls "
                     "each clip out once with its guided DDIM (model.teacher_steps, model.guidance); the student "
                     "learns to reach the same frames in model.student_steps steps without guidance (CausVid's ODE "
                     "regression, resim/train/tasks/distill.py). The run's final/ is a world model that `resim sample`, "
                     "`resim plan` and `resim eval` sample at its own steps, unguided.")}


def add_train_arguments(p: argparse.ArgumentParser, presets: list[str]) -> None:
    if presets:
        p.add_argument("--preset", default=presets[0], choices=presets,
                       help=f"named config to start from (default {presets[0]}); one YAML file each in configs/train/")
    else:   # no configs/train beside this install (a wheel outside a checkout): the command says so when run
        p.add_argument("--preset", default=None,
                       help=f"named config to start from: none found, no {recipes_dir()} (run from a checkout)")
    p.add_argument("--shards", help="dataset folder (shards/, index/, prompts/) = data.shards")
    p.add_argument("--out", required=True, help="run folder (created; checkpoints, metrics, final weights)")
    p.add_argument("--config", help="YAML file applied over the preset (same keys as config.yaml of a run)")
    p.add_argument("--steps", type=int, help="total optimizer steps = trainer.steps")
    p.add_argument("--checkpoint-every", type=int, help="checkpoint interval in steps = trainer.checkpoint_every_steps")
    p.add_argument("--resume", action="store_true", help="continue from the latest complete checkpoint in --out "
                   "(a run already at trainer.steps: nothing to do, exit 0; raise --steps to go on)")
    p.add_argument("--overwrite", action="store_true",
                   help="--out holds a run of this model: delete its checkpoints, final weights, metrics and "
                        "config, then start over (without --resume or --overwrite such a folder is refused)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override any config value, e.g. --set optim.lr=1e-4 --set data.num_workers=4 (repeatable)")
    p.add_argument("--print-config", action="store_true", help="print the resolved config as YAML and exit")


def _cmd_train(args: argparse.Namespace) -> int:
    from resim.train.run import resolve_config

    try:
        cfg = resolve_config(args.model_name, args.preset, config_file=args.config, overrides=args.overrides,
                             shards=args.shards, steps=args.steps, checkpoint_every=args.checkpoint_every)
    except ConfigError as e:
        print(f"resim train {args.model_name}: config error: {e}", file=sys.stderr)
        return 2
    if args.print_config:
        print(yaml.safe_dump(to_dict(cfg), sort_keys=False))
        return 0
    from resim.train.run import RunFolderError, check_out_dir, finished_step, remove_run, run_training
    from resim.train.stream import DataError

    prog = f"resim train {args.model_name}"
    try:
        held = check_out_dir(args.model_name, args.out, resume=args.resume, overwrite=args.overwrite)
    except RunFolderError as e:
        print(f"{prog}: {e}", file=sys.stderr)
        return 2
    if held is not None and args.resume:
        at = finished_step(args.out)
        if at is not None and at >= cfg.trainer.steps:
            print(f"{prog}: {args.out} is already at step {at} (trainer.steps = {cfg.trainer.steps}); nothing to do, "
                  f"raise --steps above {at} to continue", file=sys.stderr)
            return 0
    if held is not None and args.overwrite:
        removed = remove_run(args.out)
        if removed:
            print(f"[resim] --overwrite: removed {', '.join(removed)} of the {args.model_name} run in {args.out}",
                  file=sys.stderr)
    from resim.train.checkpoint import CheckpointError
    from resim.train.trainer import NonFiniteLossError

    try:
        run_training(cfg, args.out, resume=args.resume)
    except ConfigError as e:
        print(f"resim train {args.model_name}: config error: {e}", file=sys.stderr)
        return 2
    except NonFiniteLossError as e:
        print(f"resim train {args.model_name}: {e}", file=sys.stderr)
        return 3
    except DataError as e:
        print(f"resim train {args.model_name}: data error: {e}", file=sys.stderr)
        return 4
    except CheckpointError as e:   # a refused or unreadable checkpoint is input, not our bug: one line
        print(f"resim train {args.model_name}: checkpoint error: {e}", file=sys.stderr)
        return 5
    except KeyboardInterrupt:
        print(f"{prog}: interrupted (Ctrl-C); `--resume` continues from the last checkpoint in {args.out}",
              file=sys.stderr)
        return 130
    except OSError as e:
        if not output_error(e, args.out):   # anything else is a bug: the traceback says where
            raise
        print(f"{prog}: cannot write the run folder: {e.filename or args.out}: {e.strerror}; free space or give a "
              f"writable --out, then `--resume` (the last complete checkpoint is kept)", file=sys.stderr)
        return 6
    return 0


def output_error(e: OSError, out: str | Path) -> bool:
    """``e`` says the run folder cannot be written: disk full, quota, read-only mount (``OUTPUT_ERRNOS``), or no
    permission on a path inside ``out``."""
    if e.errno in OUTPUT_ERRNOS:
        return True
    inside = e.filename is not None and Path(os.path.abspath(e.filename)).is_relative_to(os.path.abspath(out))
    return e.errno in (errno.EACCES, errno.EPERM) and inside


def _add_model_commands(sub) -> None:
    """`resim train NAME` for every trainable model, on the subparsers ``sub``."""
    for name, table in PRESETS.items():
        what = _WHAT.get(name, f"the {name} model")
        s = sub.add_parser(name, help=f"train {what} (presets: {', '.join(table)})",
                           description=f"Train {what}. Presets: {', '.join(table)}." + _MORE.get(name, ""),
                           epilog=TRAIN_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
        add_train_arguments(s, list(table))
        s.set_defaults(func=_cmd_train, model_name=name)
    add_reward_parser(sub)  # Video2Reward has its own data path (clips with infraction scores), see docs/reward.md
    add_policy_parser(sub)  # the pixel driving policy: expert clips held in memory, see docs/closed_loop.md


def train_parser() -> argparse.ArgumentParser:
    """A parser of what follows `resim train` (``world --preset P ...``): the launcher reads the command it wraps
    with it, without the whole CLI."""
    p = argparse.ArgumentParser(prog="resim train")
    _add_model_commands(p.add_subparsers(dest="train_command", metavar="SUBCOMMAND"))
    return p


def _cmd_launch(args: argparse.Namespace) -> int:
    return main_launch(args, train_parser)


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "train", help="train a model from shards (world model, VAE, Video2Reward, policy, IDM; launch on many GPUs)",
        description="Train a model from shards on one CPU/GPU, or on many with `resim train launch`.",
        epilog=TRAIN_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="train_command", metavar="SUBCOMMAND")
    _add_model_commands(sub)
    lp = sub.add_parser(
        "launch", help="run `resim train ...` on N nodes x G processes with torchrun, print a SLURM script, or dry-run",
        description="Wrap torchrun around `resim train NAME ...` (the arguments after `--`).",
        epilog="examples:\n  resim train launch --nproc-per-node 8 -- world --preset stage2 --shards D --out R\n"
               "  resim train launch --nnodes 5 --nproc-per-node 8 --slurm -- world --preset stage1 --shards D --out R\n"
               "  resim train launch --nnodes 5 --nproc-per-node 8 --dry-run -- world --preset stage3 --shards D --out R",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    add_launch_arguments(lp)
    lp.set_defaults(func=_cmd_launch)
    p.set_defaults(func=lambda a: (p.print_help(), 2)[1])
