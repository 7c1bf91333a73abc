"""The one console script, ``resim``.

Each subcommand lives with the package that owns it, in a light module that
defines ``register(subparsers)``; heavy imports (torch, ray, cv2) happen inside
the command's handler, so ``resim --help`` and ``resim shards ...`` start fast.
To add a command, add one line to ``COMMANDS`` (or, for a subcommand of another
package's group, to ``JOINED``). The commands are grouped by noun: what trains a
model is under ``resim train``, what works on a dataset under ``resim shards``.
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys

from resim import __version__

# (module defining register(subparsers)); order = order in --help
COMMANDS: list[str] = [
    "resim.pipeline.sources.cli",
    "resim.labeling.cli",
    "resim.pipeline.cli",
    "resim.shards.cli",
    "resim.train.cli",
    "resim.train.tasks.reward.cli",
    "resim.sample.cli",
    "resim.eval.simulate_cli",
    "resim.eval.cli",
    "resim.demo.run",
]

# subcommands whose code lives in a package above or beside the group they sit in: (group, name) -> "module:function"
# adding the parser to that group's subparsers. The layers of docs/architecture.md keep resim.shards from importing
# resim.train and resim.train from importing resim.eval, so the face joins them here.
JOINED: dict[tuple[str, str], str] = {
    ("shards", "features"): "resim.train.tasks.reward.cli:add_features_parser",
    ("train", "idm"): "resim.eval.cli:add_idm_parser",
}

# commands that were renamed or retired: their old words answer with one line (exit 2) instead of argparse's
# "invalid choice"; the value says what to use now. Matched on the leading words of argv (options left out), so
# ("reward",) is `resim reward ...` only, never `resim train reward ...`.
RETIRED: dict[tuple[str, ...], str] = {
    ("eval", "detail"): "a probe of one investigation, retired; its code is in git history (lab/detail_probe.py)",
    ("reward",): "renamed; use `resim score`",
    ("reward-features",): "renamed; use `resim shards features`",
    ("eval", "idm"): "renamed; use `resim train idm`",
}

# flags the sampling commands no longer take: their settings moved under --set (resim.sample.settings); an old
# script gets one line naming the setting, not argparse's "unrecognized arguments". {section} is the command's own.
SETTINGS_COMMANDS: dict[tuple[str, ...], str] = {
    ("sample",): "", ("plan",): "", ("simulate",): "simulate", ("eval", "quality"): "quality",
    ("eval", "control"): "", ("eval", "commands"): "commands", ("eval", "drift"): "", ("eval", "planning"): "planning",
    ("eval", "closed-loop"): "closed_loop",
}
RETIRED_FLAGS: dict[str, str] = {
    "--chunk-frames": "rollout.chunk_frames=N", "--history-frames": "rollout.history_frames=N",
    "--history-noise-level": "rollout.history_noise_level=N", "--no-kv-cache": "rollout.kv_cache=off",
    "--guidance-scale": "rollout.guidance.scale_start=S", "--guidance-schedule": "rollout.guidance.schedule=KIND",
    "--text-encoder": "runtime.text_encoder=DIR", "--max-text-tokens": "runtime.max_text_tokens=N",
    "--size": "runtime.size_hw=[H, W]", "--dtype": "runtime.dtype=D", "--attention": "runtime.attention=KERNEL",
    "--compile": "runtime.compile=auto|on|off", "--compile-mode": "runtime.compile_mode=MODE",
    "--actions-from-trajectory": "runtime.actions_from_trajectory=true", "--batch-size": "runtime.batch_size=N",
    "--horizons": "{section}.horizons_s=[S, ...]", "--resolution": "quality.resolution_hw=[H, W]",
    "--fid-weights": "quality.fid_weights=FILE", "--fvd-weights": "quality.fvd_weights=FILE",
    "--lpips-net": "quality.lpips_net=vgg|alex", "--lpips-trunk": "quality.lpips_trunk_weights=FILE",
    "--lpips-head": "quality.lpips_head_weights=FILE", "--dreamsim-dir": "quality.dreamsim_dir=DIR",
    "--trajectory-branches": "commands.trajectory_branches=true", "--group-ends": "commands.group_ends=true",
    "--with-command": "planning.with_command=true", "--states": "closed_loop.states=N",
    "--variants": "closed_loop.variants=[NAME, ...]", "--true-only": "closed_loop.true_only=true",
    "--replay": "closed_loop.replay=true", "--state-seed": "{section}.state_seed=S",
    "--world-command": "{section}.world_command=true", "--state": "simulate.state=N",
    "--variant": "simulate.variant=NAME", "--speed-mps": "simulate.speed_mps=X",
}


# The held-out split is the dataset's own (resim/shards/split.py, written by the pipeline to DIR/split.json): the
# flags that made a run's own split answer with where it is set now.
SPLIT_FLAGS: dict[str, str] = {
    "--heldout-fraction": "--heldout-fraction F", "--min-heldout-episodes": "--min-heldout-episodes N",
    "--split-seed": "--seed S", "--heldout-from": None,
}
SPLIT_FLAG_COMMANDS = (("train", "idm"), ("train", "policy"), ("eval",))


def retired_flag(argv: list[str]) -> str | None:
    """The one-line answer to a flag a command no longer takes (``RETIRED_FLAGS``: now a setting of a sampling
    command; ``SPLIT_FLAGS``: the held-out split, now the dataset's), else None."""
    words = tuple(a for a in argv if not a.startswith("-"))
    if any(words[:len(c)] == c for c in SPLIT_FLAG_COMMANDS):
        for a in argv:
            flag = a.split("=", 1)[0]
            if flag in SPLIT_FLAGS:
                how = (f"`resim shards split DIR {SPLIT_FLAGS[flag]}` rewrites it" if SPLIT_FLAGS[flag] else
                       "the held-out side of --shards is evaluated, every episode with --all-clips")
                return (f"resim {' '.join(words[:2])}: {flag} is gone: the held-out split is the dataset's own "
                        f"(DIR/split.json, written by the pipeline); {how}")
    cmd = next((c for c in SETTINGS_COMMANDS if words[:len(c)] == c), None)
    if cmd is None:
        return None
    for a in argv:
        flag = a.split("=", 1)[0]
        if flag not in RETIRED_FLAGS:
            continue
        own = SETTINGS_COMMANDS[cmd]
        now = RETIRED_FLAGS[flag].format(section=own)
        if now.split(".")[0] not in ("rollout", "runtime", own or "rollout"):   # another command's: argparse says
            continue
        return f"resim {' '.join(cmd)}: {flag} is now a setting: --set {now} (or a --config file; --help lists them)"
    return None


EPILOG = """\
typical flow (from the repository root, in this order; small settings that run on a CPU in minutes):
  resim synth --out data/synth --preset tiny --episodes 12     # a synthetic world in the three real layouts
  resim pipeline run configs/pipeline/synthetic.yaml --set sources.synthetic.episodes=12 --out out/shards
  resim shards stats out/shards                                # inspect what was written
  resim shards ls out/shards --samples --limit 5               # sample keys: use one as KEY below
  resim train world --preset tiny --shards out/shards --out runs/wm
  resim train reward --preset tiny --shards out/shards --out runs/reward
  resim sample --checkpoint runs/wm --shards out/shards --history KEY --command "Turning left" --steps 4 --out out/samples
  resim plan --checkpoint runs/wm --reward runs/reward --shards out/shards --history KEY --steps 4 --out out/plan
  resim train idm --preset tiny --epochs 1 --shards out/shards --out runs/idm  # on the split in split.json
  resim eval quality --checkpoint runs/wm --shards out/shards --limit 2 --steps 4 \\
      --allow-placeholder-networks --out out/eval              # random-init metric networks: plumbing only
  resim demo                                                   # all of the above, small, with an HTML report

Every subcommand has its own --help.
"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="resim",
        description="resim: build driving world models from heterogeneous video "
        "(data pipeline, shards, training, sampling, evaluation).",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )

    parser.add_argument("--version", action="version", version=f"resim {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for mod in COMMANDS:
        importlib.import_module(mod).register(sub)
    for (group, _name), where in JOINED.items():
        mod, func = where.split(":")
        getattr(importlib.import_module(mod), func)(subcommands(sub.choices[group]))
    return parser


def subcommands(parser: argparse.ArgumentParser) -> argparse._SubParsersAction:
    """The subparsers of a command group (``resim train``, ``resim shards``, ...)."""
    return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))


def main(argv: list[str] | None = None) -> int:
    # FFmpeg (inside OpenCV) prints its own complaint about every bad video ("moov atom not found") before we
    # quarantine it or stop with a one-line reason that names the file: quiet unless the user asked for it.
    # Set before cv2 opens its first video; Ray workers started by this process inherit it.
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")
    words = tuple(a for a in (sys.argv[1:] if argv is None else argv) if not a.startswith("-"))
    for old, now in RETIRED.items():
        if words[:len(old)] == old:
            print(f"resim {' '.join(old)}: {now}", file=sys.stderr)
            return 2
    moved = retired_flag(list(sys.argv[1:] if argv is None else argv))
    if moved:
        print(moved, file=sys.stderr)
        return 2
    parser = build_parser()
    args = None
    try:
        args = parser.parse_args(argv)
        if not getattr(args, "func", None):
            parser.print_help()
            return 2
        rc = args.func(args)
        sys.stdout.flush()   # a closed pipe shows here, not in the interpreter's final flush
    except BrokenPipeError:
        return _stdout_closed()
    except KeyboardInterrupt:
        # Ctrl-C is the user's decision, not our bug: one line, and 130 (128 + SIGINT) as a shell reports it.
        # Training keeps its last complete checkpoint (--resume continues from it); a pipeline run keeps every
        # committed shard (a rerun skips them).
        print(f"\nresim {getattr(args, 'command', None) or ''}: interrupted (Ctrl-C)".rstrip(), file=sys.stderr)
        return 130
    return int(rc or 0)


def _stdout_closed() -> int:
    """``resim ... | head``: the reader left. Quiet exit, the usual Python way
    (https://docs.python.org/3/library/signal.html#note-on-sigpipe): point stdout at devnull so the
    interpreter's last flush does not raise again, and exit 141 (128 + SIGPIPE) like a C tool would."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError, AttributeError):   # stdout without a file descriptor (captured in tests)
        pass
    return 141


if __name__ == "__main__":
    sys.exit(main())
