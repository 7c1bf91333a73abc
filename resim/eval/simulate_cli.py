"""`resim simulate`: drive a pixel policy inside the world model, closed loop (docs/closed_loop.md)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from resim.eval.cli import _device, _runner, _world_args   # the world-model arguments, as `resim eval` takes them
from resim.models.policy.variants import HELP as VARIANTS_HELP
from resim.shards.schema import COMMANDS


SIMULATE_EPILOG = f"""\
variants ({VARIANTS_HELP}); constant velocity reads only the speedometer.
examples (the shipped synthetic-world models: world model, policy):
  # 30 s from the third fork world of seed 5000, the true world beside it, Video2Reward over time
  resim simulate --checkpoint synth-world --shards data/forks --policy synth-policy --set simulate.state=2 \\
      --seconds 30 --steps 10 --reward runs/reward --out out/sim
  # from a recorded history: a shard clip's (or a video file's last 9 frames), no true world to compare
  resim simulate --checkpoint synth-world --shards data/forks --history KEY --policy synth-policy --out out/sim2
From a synthetic state the expert drives the first 0.8 s (the history); the policy then decides every 0.4 s from
the frames it sees (the world model's, decoded) and the itinerary's navigation command. The same policy drives
the true world from the same start, for comparison (true_world.mp4, its score in simulate.json). Time per
generated second is in simulate.json (wall_s_per_generated_s).
Settings (--set simulate.KEY=VALUE; resim.eval.simulate_policy.SimulateRun): state (which starting state of
state_seed, default 0), state_seed (default 5000), variant (which version of the policy drives, below),
world_command (prompt the world model with the navigation command too; default: the null prompt, so the
policy's plan alone steers it, as in resim eval closed-loop; the policy is always told), speed_mps (with
--history: the speedometer at the start; default from the clip's trajectory, else 8). Also rollout.* and
runtime.* (resim sample --help)."""


def register(subparsers) -> None:
    s = subparsers.add_parser("simulate", help="drive a pixel policy inside the world model (closed loop), the true "
                                               "synthetic world beside it",
                              description="Closed-loop driving inside the world model: the policy reads the "
                                          "generated frames and answers waypoints, the world model rolls the next "
                                          "0.4 s out under them (docs/closed_loop.md).",
                              epilog=SIMULATE_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    _world_args(s, ("simulate",), clips=False)
    s.add_argument("--policy", required=True, help="policy run folder (resim train policy) or synth-policy (shipped)")
    s.add_argument("--history", default=None, metavar="VIDEO|SHARD_KEY",
                   help="start from a recorded history (a video file, or a sample key of --shards) instead of a "
                        "synthetic starting state; no true world then")
    s.add_argument("--command", default=None, choices=COMMANDS,
                   help="with --history: the navigation command the policy is told (default: the clip's own; "
                        "Moving forward for a video)")
    s.add_argument("--reward", default=None, metavar="REWARD_RUN",
                   help="Video2Reward run (resim train reward): score the drive over time")
    s.add_argument("--seconds", type=float, default=30.0, help="seconds driven after the history (default 30)")
    s.set_defaults(func=_cmd_simulate)


def _cmd_simulate(args) -> int:
    from resim.eval.simulate_policy import ClosedLoopInputError, SimulateRun, run_simulate

    if not _device(args, "simulate", {"simulate": SimulateRun}):
        return 2
    run = args.settings.section("simulate")
    if not args.seconds > 0:
        print("resim simulate: --seconds must be > 0", file=sys.stderr)
        return 2
    if args.history and not Path(args.history).is_file() and not Path(args.shards).is_dir():
        print(f"resim simulate: --history {args.history}: not a file, and --shards {args.shards} is no folder to "
              "find it as a sample key in", file=sys.stderr)
        return 2
    if not args.history and (args.command or run.speed_mps is not None):
        print("resim simulate: --command and simulate.speed_mps go with --history (a synthetic state has its "
              "itinerary and the expert's speed)", file=sys.stderr)
        return 2
    try:
        print(run_simulate(args, _runner))
    except ClosedLoopInputError as e:
        print(f"resim simulate: {e}", file=sys.stderr)
        return 2
    return 0
