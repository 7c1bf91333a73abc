"""The one console script, ``resim``.

Each subcommand lives with the package that owns it, in a light module that
defines ``register(subparsers)``; heavy imports (torch, ray, cv2) happen inside
the command's handler, so ``resim --help`` and ``resim shards ...`` start fast.
To add a command, add one line to ``COMMANDS``.
"""
from __future__ import annotations

import argparse
import importlib
import sys

# (module defining register(subparsers)); order = order in --help
COMMANDS: list[str] = [
    "pipelines.sources.cli",
    "labeling.cli",
    "pipelines.cli",
    "shards.cli",
    "training.cli",
    "training.reward.cli",
    "training.sampling.cli",
    "training.eval.cli",
    "resim.demo",
]

EPILOG = """\
typical flow:
  resim synth --out data/synth --episodes 12        # a synthetic world in the three real layouts
  resim pipeline run configs/pipeline/synthetic.yaml --out out/shards
  resim shards stats out/shards                     # inspect what was written
  resim train world --preset tiny --shards out/shards --out runs/wm
  resim train reward --preset tiny --shards out/shards --out runs/reward
  resim sample --checkpoint runs/wm --shards out/shards --history KEY --command "Turning left" --out out/samples
  resim plan --checkpoint runs/wm --reward runs/reward --shards out/shards --history KEY --out out/plan
  resim eval quality --checkpoint runs/wm --shards out/shards --heldout-from runs/idm --out out/eval
  resim demo                                        # all of the above, small, on a CPU, with an HTML report

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
    from resim import __version__

    parser.add_argument("--version", action="version", version=f"resim {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for mod in COMMANDS:
        importlib.import_module(mod).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    rc = args.func(args)
    return int(rc or 0)


if __name__ == "__main__":
    sys.exit(main())
