"""`resim eval ...`: video quality, controllability, planning; and `resim train idm` (the inverse dynamics model
they read trajectories with, trained and evaluated on held-out episodes: ``add_idm_parser``).

Light module: every `resim` call imports this module to register its subcommands, so what needs torch, numpy or the
models is imported inside the handler that uses it, to keep `resim --help` fast.

Every command prints its protocol with the numbers and writes DIR/<name>.json + DIR/<name>.png. See docs/eval.md.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

from resim.argtypes import add_settings_args, local_dir as _local_dir, positive_int as _positive_int
from resim.argtypes import torch_device as _torch_device
from resim.config import ConfigError, apply_overrides, from_dict, to_dict
from resim.models.policy.variants import HELP as CL_VARIANTS_HELP, VARIANTS as CL_VARIANTS
from resim.sample.cli import UsageError, resolve_device
from resim.shards.errors import ShardReadError   # standard library only: `resim --help` stays fast
from resim.shards.schema import COMMANDS   # standard library only: `resim --help` stays fast
from resim.shipped import PLACEHOLDER_T5, shipped_dir, shipped_model


EPILOG = """\
typical flow (held-out = the episodes the IDM did not train on):
  resim pipeline run configs/pipeline/synthetic.yaml --out DATA     # the synthetic world: exact trajectories
  resim train idm --shards DATA --out runs/idm                     # IDM (future frames -> 8 waypoints)
  resim train idm --shards DATA --out runs/vo --window history     # VO-style planner (history only)
  resim eval control  --checkpoint runs/wm --idm runs/idm --shards DATA --out out/control
  resim eval planning --checkpoint runs/wm --idm runs/idm --planner runs/vo --shards DATA --out out/planning
  resim eval commands --checkpoint runs/wm --shards DATA --all-clips --limit 20 --out out/commands
  resim eval drift    --checkpoint runs/wm --shards DATA --all-clips --limit 4 --out out/drift   # 30 s rollouts
  resim eval quality  --checkpoint runs/wm --shards DATA --out out/quality \\
      --allow-placeholder-networks                                 # plumbing check, random-init networks
  resim eval quality  --checkpoint runs/wm --shards DATA --out out/quality \\
      --set quality.fid_weights=W/pt_inception-2015-12-05-6726825d.pth --set quality.fvd_weights=W/rgb_imagenet.pt \\
      --set quality.lpips_trunk_weights=W/vgg16-397923af.pth --set quality.lpips_head_weights=W/lpips_vgg_v0.1.pth

Weights are never downloaded; docs/eval.md says where to get the standard ones. Without them quality runs
only with --allow-placeholder-networks (random-init networks, marked as such everywhere).
Settings beyond the flags of each command: --set rollout.* / runtime.* (resim sample --help lists them) and the
command's own section (quality.*, commands.*, planning.*, closed_loop.*), or a --config YAML file.
"""


QUALITY_EPILOG = """\
examples:
  resim pipeline run configs/pipeline/synthetic.yaml --out DATA       # the synthetic world's shards
  resim train idm --shards DATA --out runs/idm --preset tiny           # the IDM and its held-out split
  resim eval quality --checkpoint runs/wm --shards DATA --out out/quality \\
      --allow-placeholder-networks                 # no weights needed: random-init networks (plumbing only)
  resim eval quality --checkpoint runs/wm --shards DATA --out out/quality \\
      --set quality.fid_weights=W/pt_inception-2015-12-05-6726825d.pth --set quality.fvd_weights=W/rgb_imagenet.pt \\
      --set quality.lpips_trunk_weights=W/vgg16-397923af.pth --set quality.lpips_head_weights=W/lpips_vgg_v0.1.pth

Weights are never downloaded (docs/eval.md says where to get them); without them, or without
--allow-placeholder-networks, FID/FVD/LPIPS are refused before anything is loaded.  The clips are the held-out
side of --shards' own split (its split.json: `resim shards split DATA`); --all-clips takes every episode.
Writes OUT/quality.json (per-horizon metrics + the protocol: clips, world model, rollout, networks) and
OUT/quality.png (metrics per horizon).
Settings (--set quality.KEY=VALUE; resim.eval.quality.QualityConfig): horizons_s (default 1 2 4 ... s),
resolution_hw ([H, W] to score at; default the recorded frames'), fid_weights, fvd_weights, lpips_net (vgg|alex),
lpips_trunk_weights, lpips_head_weights, dreamsim_dir, feature_batch_size. Also rollout.* and runtime.*.
"""

CONTROL_EPILOG = """\
example:
  resim eval control --checkpoint runs/wm --idm runs/idm --shards DATA --out out/control

--idm is a `resim train idm` run. The held-out side of --shards' split is evaluated (the episodes the IDM, which
reads the same split, never trained on), or every episode with --all-clips. Writes OUT/control.json (Trajectory Difference for expert / non-expert trajectories, the IDM on
the recorded video as the floor, the expert rollouts and the recorded video against another episode's trajectory,
one they were not given, and the two bounds: expert <= 1.5 x floor, expert < 0.5 x against the one not given;
command accuracy, the protocol) and OUT/control.png (bar chart).
"""

COMMANDS_EPILOG = """\
example (the shipped synthetic-world model on a world of seeds it never saw):
  resim pipeline run configs/pipeline/synthetic.yaml --out data/heldout --set sources.synthetic.seed=1000 \
      --set sources.synthetic.root=data/heldout-world --set sources.synthetic.preset=demo
  resim eval commands --checkpoint synth-world --shards data/heldout --all-clips --limit 20 \
      --out out/commands

Each clip's history is rolled out under "Turning left", "Moving forward" and "Turning right" (no trajectory)
and under the null prompt; the optical-flow labeler (and --idm, if given) reads which way each generated
future turns. Writes OUT/commands.json (confusion matrices, accuracy, per-clip labels, fidelity per horizon
beside copy-last-frame, the protocol), OUT/commands.png, OUT/commands_strip.png and OUT/commands.gif (one
history under the three commands beside the recorded future). Clips are picked with the recorded commands
in turn, so straight-road histories are asked to turn too.

Forks (one history recorded under several commands: resim synth --set fork_fraction=F) are also scored
without the labeler: each rollout lands on the nearest recorded sibling future (latents), right when that
sibling had the command it was given ("counterfactual branches"; the VAE does not cap it). Only the fork clips:
  resim eval commands --checkpoint synth-world --shards data/forks --all-clips --counterfactual-only \
      --steps 25 --out out/branches
Add --set commands.trajectory_branches=true to score ReSim's trajectory conditioning the same way: the forks
whose clips carry a recorded trajectory (CARLA layout) are also rolled out with the null prompt under each
sibling's trajectory (about 3 more rollouts per such clip).
Settings (--set commands.KEY=VALUE; resim.eval.command_following.CommandsEvalConfig): horizons_s (fidelity
horizons after the last history frame, default [0.5, 1, 2, 4]), trajectory_branches, group_ends (diagnostic:
also read every video with the frames inside each latent group redrawn by optical-flow interpolation between
the group ends; ~1 s more per video). Also rollout.* and runtime.*.
"""

COMMAND_LOSS_EPILOG = """\
example (held-out clips of a world the model never saw):
  resim eval command-loss --checkpoint synth-world --shards data/heldout --all-clips --limit 48 --out out/closs

No sampling and no labeler: each clip's future is noised to each --levels value (one noise draw, history
clean) and denoised under "Turning left", "Moving forward", "Turning right" and the null prompt. Accuracy =
share of clips whose recorded command gives the lowest v-loss of the three (chance 0.33); worth = how much
higher the loss is under the opposite turn / the null prompt. It reads the model itself, where `resim eval
commands` reads decoded rollouts (capped by the VAE, see its recorded_through_vae). Writes
OUT/command_loss.json (per level, per command, per clip) and OUT/command_loss.png.
"""

CLOSED_LOOP_EPILOG = """\
example (the shipped synthetic-world models: world model, policy and IDM, trained on fork worlds of other seeds):
  resim eval closed-loop --checkpoint synth-world --shards data/forks --policy synth-policy --idm synth-idm \\
      --out out/closed-loop --steps 10
with your own policy (and an under-trained one beside it) and IDM:
  resim train policy --shards data/forks --out runs/policy
  resim train policy --shards data/forks --out runs/policy-1-epoch --epochs 1
  resim train idm --shards data/forks --out runs/idm --preset tiny
  resim eval closed-loop --checkpoint synth-world --shards data/forks --policy runs/policy \\
      --also runs/policy-1-epoch --idm runs/idm --reward runs/reward --out out/closed-loop --steps 10
--shards gives the prompt table and the VAE the world model was trained with; the starting states are built
from closed_loop.state_seed, not read from it.
Settings (--set closed_loop.KEY=VALUE; resim.eval.policy_ranking.ClosedLoopRun): states (starting states,
default 6), state_seed (default 5000: use one no training data came from), variants (which graded policies
drive, default all: {variants}), true_only (the true world only, no world model), world_command (prompt the
world model with the itinerary's command too; default the null prompt, so the policy's plan alone says where
the car goes), replay (also drive the world model with the true loop's own plans: tells the world model's
answer to an action apart from the policy's answer to its frames; twice the world-model time). Writes OUT/closed_loop.json and OUT/closed_loop.png (true score against
each world-model reading, one point per policy).
"""

DRIFT_EPILOG = """\
example (the shipped synthetic-world model, 30 s from held-out histories):
  resim eval drift --checkpoint synth-world --shards data/heldout --all-clips --limit 4 --out out/drift

Each history is rolled out autoregressively for --seconds (chunks of 10 latent frames, the history window
sliding over the model's own output) under --command. Per frame: sharpness (mean intensity gradient),
contrast (intensity std) and brightness; the drift is their mean distance to the real frames' mean, in real
standard deviations (0 = real-looking on these statistics), per second. Writes OUT/drift.json, OUT/drift.png
(statistics vs time beside the real band) and OUT/drift_strip.png (frames at 0, 2, 5, 10, 20, 30 s).
"""

PLANNING_EPILOG = """\
example:
  resim train idm --shards DATA --out runs/vo --window history     # the VO-style planner baseline
  resim eval planning --checkpoint runs/wm --idm runs/idm --planner runs/vo --shards DATA --out out/planning

Writes OUT/planning.json (ADE/FDE of the video-prediction policy, the VO planner, constant velocity and the
IDM on the recorded future; the protocol) and OUT/planning.png (bar chart).
Settings: --set planning.with_command=true gives the policy the clip's command prompt (default: none);
rollout.* and runtime.* as for every rollout command.
"""

# `resim train idm --preset` (resim.models.idm.IDM_PRESETS; listed here so that --help needs no torch import).
# Times measured on 168 clips of 32x48 (24 episodes of an earlier ground-plane test world, since replaced by the
# synthetic road world), default epochs, 2 CPU cores shared with other jobs: tiny 166-452 s (tiny-queries 166 s),
# small about 10 min.
IDM_PRESET_NAMES = ["tiny", "tiny-queries", "tiny-history", "small", "small-history"]
IDM_PRESET_HELP = ("IDM preset: tiny (32x48 input, 48 k parameters, odometry head), tiny-queries (tiny with the "
                   "query head), small (default; 48x80, 151 k parameters, odometry head), tiny-history / "
                   "small-history (history-only VO planner twins; --window history picks them). On 2 CPU cores "
                   "and 168 clips: tiny about 3-7 min, small about 10 min")


def _world_args(p: argparse.ArgumentParser, sections: tuple[str, ...] = (), clips: bool = True) -> None:
    """The world-model arguments of the commands that roll it out; ``sections``: the command's own settings sections
    (``--set NAME.KEY=VALUE``, beside rollout and runtime: resim.sample.settings); ``clips``: it reads evaluation
    clips (held-out split, limit)."""
    p.add_argument("--checkpoint", required=True,
                   help="world-model run folder (or its final/), or a shipped model name (synth-world)")
    p.add_argument("--shards", required=True, help="dataset folder with the evaluation clips (and prompt table)")
    p.add_argument("--out", required=True, help="output folder")
    if clips:
        p.add_argument("--all-clips", action="store_true",
                       help="evaluate every episode of --shards (a world held out whole), not only the held-out "
                            "side of its split (split.json; flagged in the protocol)")
        p.add_argument("--limit", type=_positive_int, default=None,
                       help="at most N clips, taken round-robin over the episodes (key order within each)")
    p.add_argument("--preset", default="resim", choices=["resim", "vid2world"], help="rollout preset (default resim)")
    p.add_argument("--steps", type=_positive_int, default=None,
                   help="DDIM steps (default: the preset's 50; a distilled student: its own, e.g. 4)")
    p.add_argument("--no-guidance", action="store_true", help="conditional branch only")
    p.add_argument("--seed", type=int, default=0, help="seed of the rollouts' noise (default 0)")
    p.add_argument("--vae", type=_local_dir, default=None,
                   help="local CogVideoX VAE folder (default: the one that encoded --shards, from its config.yaml; "
                        "nothing is downloaded)")
    p.add_argument("--device", type=_torch_device, default=None,
                   help="cpu, cuda or cuda:N (default: cuda if available)")
    add_settings_args(p, sections)


def _probe_args(p: argparse.ArgumentParser) -> None:
    """The arguments of the commands that read the model without sampling (command-loss, detail)."""
    p.add_argument("--checkpoint", required=True,
                   help="world-model run folder (or its final/), or a shipped model name (synth-world)")
    p.add_argument("--shards", required=True, help="dataset folder with the evaluation clips (and prompt table)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--all-clips", action="store_true", help="every episode of --shards, not only the held-out side "
                   "of its split (flagged in the protocol)")
    p.add_argument("--limit", type=_positive_int, default=None, help="at most N clips, the recorded commands in turn")
    p.add_argument("--text-encoder", type=_local_dir, default=str(shipped_dir(PLACEHOLDER_T5)),
                   help="local T5 folder for prompts not in the table (default: tiny placeholder)")
    p.add_argument("--device", type=_torch_device, default=None, help="cpu, cuda or cuda:N (default: cuda if available)")


def register(subparsers) -> None:
    p = subparsers.add_parser("eval", help="evaluate world models: quality, controllability, planning, closed loop",
                              description="Evaluate world models. Each command prints its protocol next to "
                                          "the numbers and writes a JSON + PNG report into --out.",
                              epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="eval_command", metavar="EVAL_COMMAND")

    q = sub.add_parser("quality", help="PSNR/SSIM/LPIPS/FID/FVD/DreamSim of rollouts vs ground truth, per horizon",
                       description="Roll the world model out from each evaluation clip's history (its recorded "
                                   "command) and compare the generated future with the recorded one, per horizon.",
                       epilog=QUALITY_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    _world_args(q, ("quality",))
    q.add_argument("--metrics", nargs="+", default=["psnr", "ssim", "lpips", "fid", "fvd", "dreamsim"])
    q.add_argument("--allow-placeholder-networks", action="store_true",
                   help="use random-init networks where no weights are given (plumbing only; marked in the report)")
    q.set_defaults(func=_cmd_quality)

    c = sub.add_parser("control", help="Trajectory Difference under expert / non-expert trajectories (+ command acc.)",
                       description="Controllability: roll out each clip under its own (expert) trajectory and under "
                                   "another episode's (non-expert), recover the driven path from the generated "
                                   "video with the IDM, and report its L2 distance to the conditioning trajectory.",
                       epilog=CONTROL_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    _world_args(c)
    c.add_argument("--idm", required=True, help="IDM run folder (resim train idm)")
    c.set_defaults(func=_cmd_control)

    cm = sub.add_parser("commands", help="command accuracy: one history under left / forward / right (+ null prompt)",
                        description="Controllability of the command: roll each clip's history out under each of "
                                    "the three commands and the null prompt, classify each generated future with "
                                    "the optical-flow labeler (and the IDM), report confusion matrices, accuracy "
                                    "and fidelity per horizon against copy-last-frame.",
                        epilog=COMMANDS_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    _world_args(cm, ("commands",))
    cm.add_argument("--idm", default=None, help="IDM run folder: also classify by the IDM's trajectory")
    cm.add_argument("--counterfactual-only", action="store_true",
                    help="only the clips whose history other clips share under another command (the synthetic "
                         "world's forks), whole groups; --limit then caps the clips, group by group")
    cm.set_defaults(func=_cmd_commands)

    cl = sub.add_parser("command-loss", help="does the model use the command? its loss under each command (no sampling)",
                        description="Read the command off the world model's own denoising loss: each clip's future "
                                    "under left / forward / right and the null prompt, same noise; accuracy of the "
                                    "lowest loss against the recorded command, and the worth of the command.",
                        epilog=COMMAND_LOSS_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    _probe_args(cl)
    cl.add_argument("--levels", type=int, nargs="+", default=[950, 700, 400],
                    help="noise levels of the future, 0..N-1 of the run's schedule (default 950 700 400)")
    cl.add_argument("--batch-size", type=_positive_int, default=8, help="clips per forward pass")
    cl.add_argument("--seed", type=int, default=0, help="seed of the noise draws (default 0)")
    cl.set_defaults(func=_cmd_command_loss)

    d = sub.add_parser("drift", help="long autoregressive rollouts (30 s): frame statistics vs real frames, per second",
                       description="Roll each clip's history out far past the training horizon and measure how the "
                                   "frames drift from real ones (sharpness, contrast, brightness), per second.",
                       epilog=DRIFT_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    _world_args(d)
    d.add_argument("--seconds", type=float, default=30.0, help="seconds to generate after the history (default 30)")
    d.add_argument("--command", default="Moving forward",
                   help='command for the whole rollout (default "Moving forward"; "none": the null prompt)')
    d.set_defaults(func=_cmd_drift)

    v = sub.add_parser("vae", help="VAE reconstruction PSNR/SSIM per frame on held-out clips, with a picture",
                       description="Encode each clip's recorded frames with the VAE as the pipeline does and decode "
                                   "them as the sampler does; report PSNR/SSIM per frame of the clip and show "
                                   "originals beside reconstructions. Motion: the optical-flow labeler reads each "
                                   "clip's future on the originals and on the reconstructions; its accuracy on the "
                                   "reconstructions is the ceiling of any world model's command accuracy (resim "
                                   "eval commands) through this VAE.",
                       epilog="examples:\n  resim eval vae --vae synth-vae --shards data/heldout --out out/vae\n"
                              "  resim eval vae --vae runs/dec/final/vae --shards data/heldout --out out/dec "
                              "--against out/vae/vae.json\n\n"
                              "--vae: a folder or a shipped model name (configs/models/NAME). Writes OUT/vae.json "
                              "and OUT/vae.png. --against: the difference from another VAE on the same clips "
                              "(same --shards and --limit), with paired bootstrap intervals.", formatter_class=argparse.RawDescriptionHelpFormatter)
    v.add_argument("--vae", required=True, help="VAE folder or shipped model name (e.g. synth-vae)")
    v.add_argument("--shards", required=True, help="dataset folder with the held-out clips (frames.mp4)")
    v.add_argument("--out", required=True, help="output folder")
    v.add_argument("--limit", type=_positive_int, default=None, help="at most N clips, round-robin over episodes")
    v.add_argument("--device", type=_torch_device, default=None, help="cpu, cuda or cuda:N (default: cuda if available)")
    v.add_argument("--against", default=None,
                   help="another VAE's vae.json read on the same clips: report this VAE minus that one (PSNR, "
                        "labeler accuracy through the VAE, heading kept) with paired bootstrap intervals")
    v.add_argument("--group-ends", action="store_true",
                   help="diagnostic: also read the motion with the frames inside each 4-frame latent group redrawn "
                        "by optical-flow interpolation between the group ends (how much of the heading the decoder "
                        "loses inside a group), on reconstructions and originals")
    v.set_defaults(func=_cmd_vae)

    pl = sub.add_parser("planning", help="video-prediction policy (rollout + IDM) vs VO planner vs CV: ADE/FDE",
                        description="Planning: imagine each clip's future with the world model, read the driven "
                                    "path off it with the IDM, and compare it (ADE/FDE) with the recorded one, next "
                                    "to a history-only VO planner and a constant-velocity baseline.",
                        epilog=PLANNING_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    _world_args(pl, ("planning",))
    pl.add_argument("--idm", required=True, help="IDM run folder (resim train idm)")
    pl.add_argument("--planner", default=None, help="VO-style planner run folder (resim train idm --window history)")
    pl.set_defaults(func=_cmd_planning)

    cl = sub.add_parser("closed-loop", help="policies driven in the true synthetic world and inside the world model: "
                                            "do both rank them alike?",
                        description="Drive a pixel policy and its degraded versions (steering noise, steering bias, "
                                    "constant velocity) from fork-world starting states of a fresh seed, in the true "
                                    "simulator and inside the world model; score each by the true rules and by the "
                                    "IDM proxy on the video; report Spearman's rho across policies with a bootstrap "
                                    "over states (docs/closed_loop.md).",
                        epilog=CLOSED_LOOP_EPILOG.replace("{variants}", CL_VARIANTS_HELP),
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    _world_args(cl, ("closed_loop",), clips=False)
    cl.add_argument("--policy", required=True,
                    help="policy run folder (resim train policy) or synth-policy (shipped)")
    cl.add_argument("--also", nargs="*", default=[], metavar="POLICY_RUN",
                    help="more policy runs to rank beside it (e.g. an under-trained one)")
    cl.add_argument("--idm", required=True,
                    help="IDM run folder (resim train idm) or synth-idm (shipped): reads the driven path off video")
    cl.add_argument("--reward", default=None, metavar="REWARD_RUN",
                    help="Video2Reward run (resim train reward): a second world-model reading, beside the IDM proxy")
    cl.add_argument("--seconds", type=float, default=8.0, help="seconds the policy drives after the 0.8-s history "
                    "(>= 4; default 8)")
    cl.set_defaults(func=_cmd_closed_loop)

    p.set_defaults(func=lambda a: (p.print_help(), 2)[1])


# ------------------------------------------------------------------------------------------ helpers
def _device(args, name: str, sections: dict | None = None) -> bool:
    """Resolve --device in place (cuda on a CPU-only build, a missing cuda:N: one line, before any loading), and,
    for a command that rolls the world model out, its settings into ``args.settings`` (--config / --set:
    resim.sample.settings; ``sections``: the command's own, name -> config class)."""
    from resim.sample.settings import resolve_settings

    try:
        args.device = resolve_device(args.device)
        if hasattr(args, "overrides"):
            args.settings = resolve_settings(args, sections)
    except (UsageError, ConfigError) as e:
        print(f"{'resim' if name == 'simulate' else 'resim eval'} {name}: {e}", file=sys.stderr)
        return False
    return True


def add_idm_parser(sub) -> None:
    """`resim train idm ...`: it trains a model, so it sits under `resim train` (joined there by resim/cli.py: the
    train package sits below eval in the layers of docs/architecture.md); its held-out report is eval's."""
    i = sub.add_parser("idm", help="train + evaluate the inverse dynamics model (or the VO planner) on shards",
                       description="Trains through the common Trainer on clips with traj.npy of the train side of "
                                   "the dataset's split (split.json, `resim shards split`); "
                                   "reports held-out ADE/FDE next to the constant-velocity baseline.")
    i.add_argument("--shards", required=True, help="dataset folder")
    i.add_argument("--out", required=True, help="run folder (final/ weights, idm_report.json/.png)")
    i.add_argument("--preset", default="small", choices=IDM_PRESET_NAMES, metavar="PRESET",
                   help=IDM_PRESET_HELP)
    i.add_argument("--window", default="future", choices=["future", "history"],
                   help="future: the IDM; history: the VO-style planner baseline (same architecture)")
    i.add_argument("--epochs", type=_positive_int, default=None)
    i.add_argument("--batch-size", type=_positive_int, default=None)
    i.add_argument("--lr", type=float, default=None, help="peak learning rate = optim.lr (default 2e-3; AdamW, warmup "
                   "then cosine)")
    i.add_argument("--val-fraction", type=float, default=None,
                   help="share of the training episodes set aside for early stopping (default 0.15; 0: off)")
    i.add_argument("--hflip-prob", type=float, default=None,
                   help="probability of mirroring a training clip left-right (default 0.5; 0: off)")
    i.add_argument("--decoded-vae", default=None, metavar="VAE",
                   help="also train on each clip's shard latents decoded by this VAE (folder or shipped name, e.g. "
                        "synth-vae): the frames a world model's rollouts are read from; reports the held-out "
                        "error on both (decoding takes ~0.5 s per clip on a 2-core CPU)")
    i.add_argument("--decoded-prob", type=float, default=None,
                   help="with --decoded-vae: probability that an epoch shows a clip decoded (default 0.5)")
    i.add_argument("--seed", type=int, default=0)
    i.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="IDMConfig override, e.g. --set input_hw=[64,112] (repeatable)")
    i.set_defaults(func=_cmd_idm)


def _eval_items(args) -> list[str] | None:
    """The episodes to evaluate: the held-out side of --shards' own split (its split.json, resim/shards/split.py),
    or every episode with --all-clips (a whole world held out from training). Sets ``args.split_record``, what
    the report's protocol keeps."""
    if args.all_clips:
        args.split_record = {"side": "all", "note": "ALL CLIPS of --shards (--all-clips)"}
        return None
    from resim.shards import split

    try:
        s = split.read(args.shards)
    except (FileNotFoundError, ShardReadError) as e:
        raise SystemExit(f"resim eval: --shards: {e}") from None
    args.split_record = s.record("heldout")
    return sorted(s.heldout)


def _runner(args):
    """The rollout set-up of every `resim eval` protocol (and of `simulate` / `eval closed-loop`, through
    ``make_runner``): the world model as one bundle (``WorldModelBundle.for_rollout``, as `resim sample` builds
    it), its rollout config (``args.settings``, resolved by :func:`_device`), the runner."""
    from resim.eval.worldeval import WorldRollouts
    from resim.sample.bundle import BundleLoadError, WorldModelBundle

    device, st = args.device, args.settings
    rt, cfg = st.runtime, st.rollout
    say = lambda m: print(f"[resim eval] {m}", file=sys.stderr, flush=True)   # noqa: E731
    try:
        wm = WorldModelBundle.for_rollout(args.checkpoint, st, device=device, vae=args.vae, shards=args.shards,
                                          log=say)
    except BundleLoadError as e:
        raise SystemExit(f"resim eval: --{e.part}: {e}") from None
    except ConfigError as e:   # steps and levels against the run's noise schedule
        raise SystemExit(f"resim eval: {e}") from None
    model, vae, info = wm.model, wm.vae, wm.info
    prompts = wm.prompts()   # --shards' prompt table, else the text encoder
    runner = WorldRollouts(model, vae, cfg, lambda c: prompts(c), device=device, seed=args.seed,
                           batch_size=rt.batch_size, schedule=wm.objective.schedule, log=say)
    guidance = args.preset if cfg.guidance.enabled else "none"
    meta = {**info, "vae_id": vae.info.vae_id, "vae_placeholder": vae.info.placeholder, "device": device,
            "rollout": {k: v for k, v in to_dict(cfg).items() if k != "guidance"},
            "guidance": guidance, "guidance_scale_start": cfg.guidance.scale_start if guidance != "none" else None,
            "guidance_schedule": cfg.guidance.schedule if guidance != "none" else None,
            "runtime": to_dict(rt), "seed": args.seed}
    return runner, meta


def _clips(args, items, need_trajectory: bool = True, round_robin_limit: bool = True, fits=None):
    """The clips of --shards (held-out ``items``; ``fits``: those a reader such as the IDM can read); --limit
    takes them round-robin over episodes unless ``round_robin_limit`` is False (the caller then applies it, e.g.
    balanced over commands)."""
    from resim.eval.worldeval import eval_clips_from_dataset

    try:
        clips = eval_clips_from_dataset(args.shards, items=items, limit=args.limit if round_robin_limit else None,
                                        need_trajectory=need_trajectory, fits=fits)
    except (FileNotFoundError, ShardReadError) as e:
        raise SystemExit(f"resim eval: --shards: {e}") from None
    if not clips:
        raise SystemExit(f"resim eval: no clips{' with a trajectory' if need_trajectory else ''} in {args.shards}"
                         + (f" among the {len(items)} held-out episodes" if items else ""))
    return clips


def _read_against(path: str | None, cmd: str) -> dict | None:
    """The ``--against`` report of ``resim eval CMD`` (None without one). Read before anything is loaded, so a wrong
    path fails in a second, not after the evaluation."""
    if not path:
        return None
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError) as e:
        raise SystemExit(f"resim eval {cmd}: --against {path}: cannot read it as a {cmd}.json ({e})") from None


def _finish(out: Path, name: str, report: dict, text: str, png_fn) -> None:
    from resim.shards.safejson import write_json

    report.pop("_videos", None)
    write_json(report, out / f"{name}.json")
    png_fn(out / f"{name}.png")
    print(text)
    print(f"wrote {out / (name + '.json')} and {out / (name + '.png')}")


# ------------------------------------------------------------------------------------------ commands
def _cmd_quality(args) -> int:
    from resim.eval.quality import QualityConfig, build_networks
    from resim.eval.report import format_quality, plot_quality
    from resim.eval.worldeval import quality_eval

    # inputs first (clips, config, weight files), so a mistake costs no model load and no rollout
    if not _device(args, "quality", {"quality": dict}):
        return 2
    clips = _clips(args, _eval_items(args))
    # what the clips and the flags decide is not a setting: the rest of QualityConfig is (--set quality.KEY=VALUE)
    given = {"value_range": "uint8", "fps_hz": clips[0].fps_hz, "num_conditioning_frames": clips[0].num_history_frames,
             "metrics": list(args.metrics), "allow_placeholder_networks": args.allow_placeholder_networks,
             "device": args.device}
    user = args.settings.section("quality")
    try:
        taken = sorted(set(user) & set(given))
        if taken:
            raise ConfigError(f"quality.{taken[0]}: set by the clips or the flags, not a setting (the settings of "
                              f"quality: the other keys of QualityConfig)")
        qcfg = from_dict(QualityConfig, {**user, **given}, prefix="quality")
        nets = build_networks(qcfg, qcfg.device)
    except ConfigError as e:
        print(f"resim eval quality: {e}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    runner, meta = _runner(args)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        # the evaluator's warnings (e.g. FID/FVD from few samples) are in rep["warnings"], which the summary
        # prints: letting Python print them as well said each twice
        warnings.simplefilter("ignore", UserWarning)
        rep = quality_eval(runner, clips, qcfg, nets)
    rep["protocol"]["world_model"] = meta
    rep["protocol"]["split"] = args.split_record
    rep["protocol"]["seconds"] = round(time.perf_counter() - t0, 2)
    _finish(out, "quality", rep, format_quality(rep),
            lambda p: plot_quality(rep, p, title=f"rollouts vs recorded ({Path(args.checkpoint).name})"))
    return 0


def _load_idm(path, device):
    from resim.train.tasks.idm import load_idm

    try:
        return load_idm(path, device)
    except (FileNotFoundError, ValueError) as e:   # load_idm turns corrupt files into ValueError naming them
        raise SystemExit(f"resim eval: {e}")


def _traj_table(rows: dict) -> str:
    lines = []
    for name, v in rows.items():
        if isinstance(v, dict) and "ade_m" in v:
            lines.append(f"  {name:32s} ADE {v['ade_m']:.3f} m  FDE {v['fde_m']:.3f} m  yaw {v['yaw_err_deg']:.2f} deg"
                         f"  (n={v['n']})")
        elif isinstance(v, dict) and "trajectory_difference_m" in v:
            lines.append(f"  {name:32s} L2 {v['trajectory_difference_m']:.3f} m  at 4 s "
                         f"{v['trajectory_difference_final_m']:.3f} m  (n={v['n']})")
        elif isinstance(v, str):
            lines.append(f"  {name:32s} {v}")
    return "\n".join(lines)


def _slope(v: float | None) -> str:
    return "n/a (the given end points do not vary)" if v is None else f"{v:+.2f}"


# control.json's Trajectory Difference rows: the two rollouts, then the IDM's floors on the recorded video and on
# the recorded latents decoded through the VAE (what a perfect world model would score through this VAE)
CONTROL_ROWS = ("expert", "non_expert", "idm_on_recorded_video", "idm_on_recorded_through_vae")
# the controls of the second bound: the expert rollouts and the recorded video, each read against another
# episode's trajectory, one they were not given (resim/eval/worldeval.py, trajectory_bounds)
NOT_GIVEN_ROWS = ("expert_vs_not_given", "recorded_video_vs_not_given")


def _bounds_line(b: dict) -> str:
    ok = lambda m: "met" if m else "not met"  # noqa: E731
    return (f"bounds: expert / IDM floor {b['expert_over_idm_floor']:.2f} (<= 1.5: {ok(b['expert_over_idm_floor_met'])}); "
            f"expert / same rollouts vs a trajectory not given {b['expert_over_not_given']:.2f} "
            f"(< 0.5: {ok(b['expert_over_not_given_met'])}; the recorded video reads "
            f"{b['recorded_video_over_not_given']:.2f})")


def _cmd_control(args) -> int:
    from resim.eval.report import format_protocol
    from resim.train.metrics import plot_bars
    from resim.eval.worldeval import check_idm_window, control_eval, idm_fits, non_expert_pairs


    # inputs first: clips, their non-expert pairs and the IDM's window are checked before any rollout
    if not _device(args, "control"):
        return 2
    items = _eval_items(args)
    idm, idm_info = _load_idm(args.idm, args.device)
    clips = _clips(args, items, fits=idm_fits(idm))
    try:
        non_expert_pairs(clips, args.seed)
        check_idm_window(idm, clips)
    except ValueError as e:   # only input checks run here
        print(f"resim eval control: {e}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    runner, meta = _runner(args)
    t0 = time.perf_counter()
    rep = control_eval(runner, idm, clips, seed=args.seed)
    rep["protocol"] = {"clips": len({c.key for c in clips}), "episodes": len({c.item_id for c in clips}),
                       "split": args.split_record,
                       "idm": idm_info, "world_model": meta,
                       "non_expert": "trajectory + command of a clip of another episode (seeded hash)",
                       "trajectory_difference": "L2 (x, y) between IDM(generated video) and the conditioning "
                                                "trajectory, mean over the 8 waypoints; also at 4 s",
                       "seconds": round(time.perf_counter() - t0, 2)}
    ca = rep["command_accuracy"]
    acc = ca if isinstance(ca, str) else "  ".join(
        f"{k}: {v['accuracy']:.3f} (n={v['n']})" for k, v in ca.items() if v["accuracy"] is not None)
    text = "\n".join([format_protocol(rep["protocol"]), "Trajectory Difference (lower = more controllable):",
                      _traj_table({k: rep[k] for k in CONTROL_ROWS}),
                      "against a trajectory they were not given (another episode's):",
                      _traj_table({k: rep[k] for k in NOT_GIVEN_ROWS}),
                      f"  non-expert trajectory vs recorded: {rep['non_expert_vs_recorded_trajectory_m']:.3f} m",
                      _bounds_line(rep["bounds"]),
                      "how far the read end point moves with the given one (slope; 1: followed, 0: ignored):",
                      *(f"  {k:32s} forward {_slope(v['forward_slope'])}  lateral {_slope(v['lateral_slope'])}  "
                        f"(n={v['n']})" for k, v in rep["followed"].items()),
                      f"command accuracy (flow labeler): {acc}"])
    groups = {"L2 mean": {k: rep[k]["trajectory_difference_m"] for k in CONTROL_ROWS},
              "L2 at 4 s": {k: rep[k]["trajectory_difference_final_m"]
                            for k in CONTROL_ROWS}}
    _finish(out, "control", rep, text, lambda p: plot_bars(groups, p, title=f"Trajectory Difference, {len(clips)} clips"))
    return 0


def _cmd_commands(args) -> int:
    # commands.py imports counterfactual_groups from resim.eval.branches (one import line here, as for the others)
    from resim.eval.command_following import (CommandsEvalConfig, balanced_clips, commands_eval,
                                              counterfactual_groups)
    from resim.eval.command_following_report import command_gif, command_strip, format_commands, plot_commands
    from resim.eval.report import format_protocol
    from resim.eval.worldeval import eval_clips_from_dataset, flow_labeler_status

    if not _device(args, "commands", {"commands": CommandsEvalConfig}):
        return 2
    items = _eval_items(args)
    try:
        clips = eval_clips_from_dataset(args.shards, items=items, need_trajectory=False)
    except (FileNotFoundError, ShardReadError) as e:
        raise SystemExit(f"resim eval commands: --shards: {e}") from None
    clips = [c for c in clips if c.command is not None]
    if args.counterfactual_only:
        groups = counterfactual_groups(clips)
        if not groups:
            raise SystemExit(f"resim eval commands: --counterfactual-only: no two clips of {args.shards} share a "
                             "history under different commands (resim synth --set fork_fraction=... makes them)")
        keep: list[int] = []
        for g in groups:                   # whole groups: a fork's siblings are what its rollouts are scored on
            if args.limit is not None and len(keep) + len(g) > args.limit:
                break
            keep += g
        if not keep:
            raise SystemExit(f"resim eval commands: --limit {args.limit} is smaller than the first fork's "
                             f"{len(groups[0])} sibling clips")
        clips = [clips[i] for i in sorted(keep)]
    elif args.limit is not None:
        clips = balanced_clips(clips, args.limit)
    if not clips:
        raise SystemExit(f"resim eval commands: no clips with a command in {args.shards}")
    labeler, reason = flow_labeler_status()
    if labeler is None:
        raise SystemExit(f"resim eval commands: {reason}")
    idm, idm_info = (_load_idm(args.idm, args.device) if args.idm else (None, None))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    runner, meta = _runner(args)
    print(f"[resim eval commands] {len(clips)} clips x 4 prompts = {4 * len(clips)} rollouts of "
          f"{clips[0].latents.shape[0]} latent frames, {runner.cfg.num_steps} DDIM steps ...", file=sys.stderr)
    t0 = time.perf_counter()
    opts = args.settings.section("commands")
    rep = commands_eval(runner, clips, labeler, idm=idm, horizons_s=opts.horizons_s,
                        trajectory_branches=opts.trajectory_branches, group_ends=opts.group_ends)
    nh, fps = clips[0].num_history_frames, clips[0].fps_hz
    recorded = [c.command for c in clips]
    rep["protocol"] = {"clips": len(clips), "episodes": len({c.item_id for c in clips}),
                       "recorded_commands": {c: recorded.count(c) for c in sorted(set(recorded))},
                       "shards": str(args.shards),
                       "split": args.split_record,
                       "world_model": meta, "idm": idm_info,
                       "conditions": "each history x {left, forward, right} (no trajectory) + the null prompt" +
                                     ("; forks with trajectories: the null prompt x each sibling's recorded "
                                      "trajectory" if opts.trajectory_branches else ""),
                       "labeler": "resim.labeling.flow.FlowLabeler preset default on the last history frame + the "
                                  "generated future",
                       "seconds": round(time.perf_counter() - t0, 2)}
    vids = rep["_videos"]
    # the strip/GIF show the first clip whose history was recorded going straight: the turns are counterfactual
    idx = next((i for i, c in enumerate(clips) if c.command == "Moving forward"), 0)
    command_strip(vids, idx, nh, fps, out / "commands_strip.png")
    command_gif(vids, idx, fps, out / "commands.gif")
    rep["figure_clip"] = clips[idx].key
    _finish(out, "commands", rep, "\n".join([format_protocol(rep["protocol"]), format_commands(rep)]),
            lambda p: plot_commands(rep, p, title=f"{len(clips)} held-out histories x 3 commands"))
    return 0


def _cmd_command_loss(args) -> int:
    from resim.eval.command_loss import CommandLossInputError, plot_command_loss, run_command_loss

    if not _device(args, "command-loss"):
        return 2
    items = _eval_items(args)
    try:
        rep, text = run_command_loss(args.checkpoint, args.shards, items, limit=args.limit, levels=args.levels,
                                     seed=args.seed, batch_size=args.batch_size, text_encoder=args.text_encoder,
                                     device=args.device, split=args.split_record)
    except CommandLossInputError as e:
        raise SystemExit(f"resim eval command-loss: {e}") from None
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    _finish(out, "command_loss", rep, text,
            lambda p: plot_command_loss(rep, p, title=f"{rep['clips']} clips: the command read by the model's loss"))
    return 0


def _cmd_drift(args) -> int:
    from resim.eval.drift import drift_eval, drift_strip, format_drift, plot_drift
    from resim.eval.report import format_protocol

    if not _device(args, "drift"):
        return 2
    if not args.seconds > 0:
        raise SystemExit(f"resim eval drift: --seconds must be > 0, got {args.seconds}")
    command = None if args.command.lower() == "none" else args.command
    if command is not None and command not in COMMANDS:
        raise SystemExit(f"resim eval drift: --command {args.command!r} is not one of {list(COMMANDS)} or 'none'")
    clips = _clips(args, _eval_items(args), need_trajectory=False)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    runner, meta = _runner(args)
    print(f"[resim eval drift] {len(clips)} histories x {args.seconds:g} s under {command or 'the null prompt'}, "
          f"{runner.cfg.num_steps} DDIM steps per chunk ...", file=sys.stderr)
    t0 = time.perf_counter()
    rep = drift_eval(runner, clips, seconds=args.seconds, command=command)
    nh, fps = clips[0].num_history_frames, clips[0].fps_hz
    rep["protocol"] = {"clips": len(clips), "episodes": len({c.item_id for c in clips}), "shards": str(args.shards),
                       "split": args.split_record,
                       "world_model": meta, "seconds": round(time.perf_counter() - t0, 2)}
    drift_strip(rep["_videos"], nh, fps, out / "drift_strip.png",
                times_s=[s for s in (0, 2, 5, 10, 20, 30) if s <= args.seconds])
    _finish(out, "drift", rep, "\n".join([format_protocol(rep["protocol"]), format_drift(rep)]),
            lambda p: plot_drift(rep, p, title=f"{len(clips)} held-out histories, {args.seconds:g} s"))
    return 0


def _cmd_closed_loop(args) -> int:
    from resim.eval.policy_ranking import ClosedLoopInputError, ClosedLoopRun, plot_closed_loop, run_closed_loop

    if not _device(args, "closed-loop", {"closed_loop": ClosedLoopRun}):
        return 2
    try:
        true_only = args.settings.section("closed_loop").true_only
        rep, text = run_closed_loop(args, None if true_only else _runner)
    except ClosedLoopInputError as e:
        print(f"resim eval closed-loop: {e}", file=sys.stderr)
        return 2
    _finish(Path(args.out), "closed_loop", rep, text, lambda p: plot_closed_loop(rep, p))
    return 0


def _cmd_vae(args) -> int:
    from resim.media.encoders import VideoVAE
    from resim.shards.safejson import write_json
    from resim.eval.vae_eval import (format_vae_difference, format_vae_eval, paired_vae_difference,
                                        plot_vae_eval, vae_eval)
    from resim.eval.worldeval import eval_clips_from_dataset, flow_labeler_status

    if not _device(args, "vae"):
        return 2
    against = _read_against(args.against, "vae")
    folder = shipped_model(args.vae)
    if not Path(folder).is_dir():
        print(f"resim eval vae: --vae {args.vae}: no such folder or shipped model", file=sys.stderr)
        return 2
    try:
        clips = eval_clips_from_dataset(args.shards, limit=args.limit, need_trajectory=False)
    except (FileNotFoundError, ShardReadError) as e:
        raise SystemExit(f"resim eval vae: --shards: {e}") from None
    if not clips:
        raise SystemExit(f"resim eval vae: no clips in {args.shards}")
    vae = VideoVAE(folder, device=args.device)
    print(f"[resim eval vae] {len(clips)} clips of {len(clips[0].frames)} frames through {vae.info.vae_id} ...",
          file=sys.stderr)
    t0 = time.perf_counter()
    labeler, why_not = flow_labeler_status()
    if labeler is None:
        print(f"[resim eval vae] motion through the VAE not measured: {why_not}", file=sys.stderr)
    rep = vae_eval(vae, clips, labeler=labeler, group_ends=args.group_ends)
    rep["protocol"] = {"vae": str(folder), "vae_placeholder": vae.info.placeholder, "shards": str(args.shards),
                       "episodes": len({c.item_id for c in clips}), "resolution_hw": list(clips[0].frames.shape[1:3]),
                       "round_trip": "VideoVAE.encode (posterior sample x scaling factor, seed = clip index) -> "
                                     "decode_latents", "seconds": round(time.perf_counter() - t0, 2)}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    plot_vae_eval(rep, out / "vae.png", clips[0].fps_hz)
    rep.pop("_examples")
    diff = None
    if against is not None:
        try:
            diff = rep["against"] = {"report": str(args.against), **paired_vae_difference(rep, against)}
        except ValueError as e:
            write_json(rep, out / "vae.json")
            print(f"resim eval vae: --against {args.against}: {e} (wrote {out / 'vae.json'} without the comparison)",
                  file=sys.stderr)
            return 2
    write_json(rep, out / "vae.json")
    print(format_vae_eval(rep))
    if diff is not None:
        print(format_vae_difference(diff, args.against))
    print(f"wrote {out / 'vae.json'} and {out / 'vae.png'}")
    return 0


def _cmd_planning(args) -> int:
    from resim.eval.report import format_protocol
    from resim.train.metrics import plot_bars
    from resim.eval.worldeval import PlanningEvalConfig, check_idm_window, idm_fits, planning_eval


    # inputs first: clips and the IDM's / planner's windows are checked before any rollout
    if not _device(args, "planning", {"planning": PlanningEvalConfig}):
        return 2
    device = args.device
    idm, idm_info = _load_idm(args.idm, device)
    planner, planner_info = _load_idm(args.planner, device) if args.planner else (None, None)
    if planner is not None and planner.cfg.window != "history":
        print(f"resim eval planning: --planner {args.planner} sees window={planner.cfg.window!r}; the VO-style "
              "planner must see history frames only (train it with `resim train idm --window history`)",
              file=sys.stderr)
        return 2
    clips = _clips(args, _eval_items(args), fits=idm_fits(*[m for m in (idm, planner) if m is not None]))
    try:
        check_idm_window(idm, clips)
        if planner is not None:
            check_idm_window(planner, clips, "VO planner")
    except ValueError as e:   # only the window checks run here
        print(f"resim eval planning: {e}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    runner, meta = _runner(args)
    t0 = time.perf_counter()
    with_command = args.settings.section("planning").with_command
    rep = planning_eval(runner, idm, planner, clips, with_command=with_command)
    rep["protocol"] = {"clips": len(clips), "episodes": len({c.item_id for c in clips}),
                       "split": args.split_record,
                       "idm": idm_info, "planner": planner_info,
                       "policy_conditions": "clip command prompt" if with_command
                       else "none (null prompt, no trajectory)",
                       "constant_velocity": "straight at |waypoint_1| / 0.5 s (oracle initial speed)",
                       "world_model": meta, "seconds": round(time.perf_counter() - t0, 2)}
    names = ("video_prediction_policy", "vo_planner_history_only", "constant_velocity", "idm_on_recorded_future")
    text = "\n".join([format_protocol(rep["protocol"]), "ADE/FDE vs the recorded future:",
                      _traj_table({k: rep[k] for k in names})])
    groups = {m.upper(): {k: (rep[k][f"{m}_m"] if isinstance(rep[k], dict) else None) for k in names}
              for m in ("ade", "fde")}
    _finish(out, "planning", rep, text, lambda p: plot_bars(groups, p, title=f"planning, {len(clips)} clips"))
    return 0


def _cmd_idm(args) -> int:
    from resim.train.tasks.idm import IDMTrainConfig, run_idm_training

    d = {"preset": args.preset if args.window == "future" or args.preset.endswith("-history")
         else f"{args.preset}-history", "seed": args.seed}
    if args.lr is not None:
        d["optim"] = {"lr": args.lr}   # over the IDM's own optimiser defaults (resim.config.from_dict)
    for k, v in (("epochs", args.epochs), ("batch_size_per_gpu", args.batch_size),
                 ("val_fraction", args.val_fraction), ("hflip_prob", args.hflip_prob),
                 ("decoded_vae", args.decoded_vae), ("decoded_prob", args.decoded_prob)):
        if v is not None:
            d[k] = v
    try:
        ov = apply_overrides({}, args.overrides)
        cfg = from_dict(IDMTrainConfig, {**d, "overrides": ov})
        cfg.model_cfg()
    except ConfigError as e:
        print(f"resim train idm: config error: {e}", file=sys.stderr)
        return 2
    from resim.train.tasks.idm import IDMDataError, prepare_idm_data

    try:   # the data and its split are checked before anything is trained
        data = prepare_idm_data(args.shards, cfg)
    except (FileNotFoundError, ShardReadError, IDMDataError) as e:
        print(f"resim train idm: --shards: {e}", file=sys.stderr)
        return 1
    res = run_idm_training(args.shards, cfg, args.out, progress=True, data=data)
    res.pop("_model")
    from resim.eval.report import format_protocol

    print(format_protocol(res["protocol"]))
    print(f"model: {res['model']['architecture']}, {res['model']['parameters']:,} parameters")
    print("held-out:")
    print(_traj_table(res["heldout"]))
    print(f"wrote {Path(args.out) / 'idm_report.json'}, idm_report.png and final/ (weights)")
    return 0
