"""`resim score ...`, `resim train reward ...`, `resim shards features ...`: the Video2Reward commands.

`resim score` is registered here (``register``), `resim train reward` by resim/train/cli.py
(``add_train_parser``), `resim shards features` by resim/cli.py (``add_features_parser``: the shards package stays
below train in the layers of docs/architecture.md, so the face joins them).

Light module: torch/transformers are imported inside the handlers.
"""
from __future__ import annotations

import argparse
import json
import sys
import textwrap

from resim.argtypes import non_negative_int as _non_negative_int, positive_int as _positive_int


def _load_train_cfg(args):
    from resim import config as rconfig
    from resim.train.tasks.reward.config import PRESETS, RewardTrainConfig

    if args.preset not in PRESETS:
        raise rconfig.ConfigError(f"unknown preset {args.preset!r}; known: {', '.join(PRESETS)}")
    return rconfig.load(RewardTrainConfig, args.config, args.set or (), base=PRESETS[args.preset])


def _train_cfg_or_none(args, prog: str):
    """The resolved config, or None after printing the config error (bad --preset / --config / --set)."""
    from resim.config import ConfigError

    try:
        return _load_train_cfg(args)
    except ConfigError as e:
        print(f"{prog}: config error: {e}", file=sys.stderr)
        return None


def _cmd_score(args: argparse.Namespace) -> int:
    from pathlib import Path

    from resim.shards.reader import ShardReadError
    from resim.shards.video import VideoError
    from resim.models.reward.checkpoint import CheckpointError, load_checkpoint
    from resim.sample.reward_score import ScoreError, read_video_file, score_videos

    try:
        model = load_checkpoint(args.checkpoint)
        results = []
        for target in args.inputs:
            if Path(target).is_file():
                frames, kind = read_video_file(target), "video"
            else:
                if not args.shards:
                    raise ScoreError(f"{target}: not a file; to score a shard sample by key pass --shards DIR")
                from resim.shards.reader import find_sample
                from resim.shards.video import decode_mp4

                try:
                    s = find_sample(args.shards, target, attach_prompts=False)
                    frames = decode_mp4(s["frames.mp4"])
                except KeyError as e:
                    raise ScoreError(str(e.args[0])) from None
                except (ShardReadError, VideoError) as e:  # a corrupt shard / frames.mp4 of the dataset
                    raise ScoreError(f"{target} in {args.shards}: {e}") from None
                kind = "shard sample"
            (score,) = score_videos(model, [frames], stride=args.stride, names=[target])
            results.append({"input": target, "kind": kind, "frames": int(len(frames)), "score": float(score)})
    except (ScoreError, CheckpointError) as e:
        print(f"resim score: error: {e}", file=sys.stderr)
        return 1
    meta = model.metadata()
    if args.json:
        print(json.dumps({"model": meta, "results": results}, indent=2))
    else:
        for r in results:
            print(f"{r['score']:.4f}  {r['input']}  ({r['kind']}, {r['frames']} frames)")
        if meta["backbone_placeholder"]:
            print("note: this model's backbone is a random-init PLACEHOLDER, not pretrained DINOv2", file=sys.stderr)
    return 0


# what `resim shards features` writes in OUT: a folder holding only these is an earlier run (a rerun redoes it)
FEATURES_OUT_NAMES = {"shards", "index", "manifest", "prompts", "quarantine", "config.yaml"}


def _check_features_out(out) -> None:
    """ValueError when OUT is a non-empty folder that is not a shard dataset (the copy would mix into it)."""
    from pathlib import Path

    from resim.shards.layout import foreign_entries

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"output folder {out} exists and is not a folder")
    shown = foreign_entries(out, FEATURES_OUT_NAMES)
    if shown:
        raise ValueError(f"output folder {out} is not empty and is not a shard dataset (it holds {shown}); "
                         "give an empty or new folder")


def _cmd_features(args: argparse.Namespace) -> int:
    import torch

    from resim.shards.reader import ShardReadError
    from resim.models.reward.backbone import BackboneError
    from resim.train.tasks.reward.features import add_features_to_dataset, check_feature_paths
    from resim.models.reward.model import Video2Reward

    prog = "resim shards features"
    torch.set_num_threads(args.threads) if args.threads else None
    cfg = _train_cfg_or_none(args, prog)
    if cfg is None:
        return 2
    try:
        check_feature_paths(args.src, args.out)  # raises ValueError only for the two folders it checks
        _check_features_out(args.out)
        model = Video2Reward(cfg.model)
    except (ValueError, BackboneError) as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 1
    try:
        summary = add_features_to_dataset(args.src, args.out, model, where=cfg.data.clip_window, progress=True)
    except ShardReadError as e:  # a corrupt source shard (unreadable clips are quarantined, the job goes on)
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 1
    print(json.dumps(summary, indent=2))
    return 0 if summary["samples"] else 1


# What `resim train reward` read before it read only shards: refused with the way to get the same clips as shards.
PIPELINE_FIRST = ("reward training reads only shards: cut the routes with the pipeline, then train on its shards: "
                  "`resim pipeline run configs/pipeline/carla-reward.yaml --set sources.carla.root=DIR --out SHARDS` "
                  "and `resim train reward --shards SHARDS --out OUT` (docs/reward.md)")
REMOVED_FLAGS = {"carla": ("--carla", ""),
                 "clip_frames": ("--clip-frames", " (clip length: the pipeline's clip.num_history_frames + "
                                                  "clip.num_future_frames)"),
                 "clip_stride_frames": ("--clip-stride-frames", " (the pipeline's clip.stride_frames)"),
                 "hold_last": ("--hold-last", " (the pipeline's clip.max_held_frames)")}


def _removed_flag(args) -> str | None:
    """The one-line error for a flag of the old CARLA-folder path, or None."""
    for dest, (flag, instead) in REMOVED_FLAGS.items():
        if getattr(args, dest, None) not in (None, False):
            return f"{flag} was removed{instead}; {PIPELINE_FIRST}"
    return None


def _cmd_train(args: argparse.Namespace) -> int:
    from pathlib import Path

    from resim import config as rconfig
    from resim.shards.reader import ShardReadError, iter_samples
    from resim.models.reward.backbone import BackboneError
    from resim.train.tasks.reward.data import ClipError, clips_from_samples
    from resim.train.tasks.reward.train import SplitError, prepare_training, train_reward

    prog = "resim train reward"
    removed = _removed_flag(args)
    if removed:
        print(f"{prog}: error: {removed}", file=sys.stderr)
        return 2
    cfg = _train_cfg_or_none(args, prog)
    if cfg is None:
        return 2
    if not args.shards:
        print(f"{prog}: error: --shards DIR is required (a dataset written by `resim pipeline run`)", file=sys.stderr)
        return 2
    from resim.train.run import REWARD_RUN_FILES, RunFolderError, check_out_dir, remove_run

    try:
        held = check_out_dir("reward", args.out, overwrite=args.overwrite, can_resume=False)
    except RunFolderError as e:
        print(f"{prog}: {e}", file=sys.stderr)
        return 2
    src = args.shards
    if not Path(src).is_dir():
        print(f"{prog}: error: {src}: no such folder", file=sys.stderr)
        return 1
    try:
        clips = list(clips_from_samples(iter_samples(args.shards, attach_prompts=False, latent_as="stored")))
    except (ShardReadError, ClipError) as e:   # corrupt shard, dino.npy without dino_id
        print(f"{prog}: error: {src}: {e}", file=sys.stderr)
        return 1
    if not clips:
        print(f"{prog}: error: {src} has no clip with an infraction score", file=sys.stderr)
        return 1
    # the split and the backbone are checked before anything is written or trained
    from resim.shards import split as dataset_split

    try:
        split = dataset_split.read(args.shards)
        prepared = prepare_training(clips, cfg, split)
    except (SplitError, ShardReadError) as e:
        print(f"{prog}: error: {src}: {e}", file=sys.stderr)
        return 1
    except BackboneError as e:
        print(f"{prog}: config error: model.backbone_dir: {e}", file=sys.stderr)
        return 2
    for note in prepared.notes:
        print(f"note: {note}", file=sys.stderr)
    out = Path(args.out)
    if held is not None:   # --overwrite (checked above); the old run stays until the new one is known to start
        removed = remove_run(out, REWARD_RUN_FILES)
        print(f"note: --overwrite: removed {', '.join(removed)} of the reward run in {out}", file=sys.stderr)
    out.mkdir(parents=True, exist_ok=True)
    rconfig.save(cfg, out / "config.yaml")
    r = train_reward(clips, cfg, split, out, progress=not args.no_progress, prepared=prepared)
    m = r["metrics"]
    print(f"trained on {r['n_train']} clips, held out {r['n_heldout']} clips of {len(r['heldout_items'])} episodes "
          f"({'stored features' if r['used_features'] else 'backbone on pixels'})")
    print(f"held-out: MAE {m['mae']:.4f}  Spearman {m['spearman']:.4f}  hazard AUC {m['hazard_auc']:.4f}")
    for sk in r["skipped"]:
        print(f"skipped clip {sk['key']}: {sk['reason']}", file=sys.stderr)
    print(f"checkpoint, predictions and plot in {out}")
    return 0


def _add_cfg_args(p):
    p.add_argument("--preset", default="tiny", help="named preset: tiny (placeholder backbone, 56 px), synthetic (tiny, 8 frames every 11 = whole 8 s synth episode, temporal_diff) or resim (224 px)")
    p.add_argument("--config", default=None, help="YAML RewardTrainConfig file applied over the preset")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override a config value, e.g. --set model.image_size_px=224 --set epochs=5")


TRAIN_DESCRIPTION = ("Train Video2Reward: regression to each clip's infraction score (ReSim B.2: AdamW, lr 1e-3). "
                     "Held-out split by episode (item_id). Uses stored dino.npy features when present and matching "
                     "the backbone, else computes them once (frozen backbone). Writes checkpoint, config, held-out "
                     "predictions (MAE, Spearman, hazard AUC) and a predicted-vs-true plot.")


def add_train_parser(sub) -> None:
    """`resim train reward ...` (registered by resim/train/cli.py under `train`)."""
    t = sub.add_parser("reward", help="train Video2Reward on the labelled clips of a shard dataset",
                       description=TRAIN_DESCRIPTION)
    t.add_argument("--shards", default=None, help="shard dataset folder (labelled clips: infraction_score set); "
                   "CARLA routes become one with `resim pipeline run configs/pipeline/carla-reward.yaml`")
    # the old CARLA-folder path: hidden, and refused with the two commands that replace it (_removed_flag)
    for dest, (flag, _) in REMOVED_FLAGS.items():
        if dest == "hold_last":
            t.add_argument(flag, dest=dest, action="store_true", help=argparse.SUPPRESS)
        else:
            t.add_argument(flag, dest=dest, default=None, help=argparse.SUPPRESS)
    t.add_argument("--out", required=True, help="output folder (trainer logs and loss curve under OUT/trainer); "
                   "a folder holding a reward run is refused unless --overwrite, one holding another kind of run always")
    t.add_argument("--overwrite", action="store_true", help="--out holds a reward run: delete it (checkpoint, "
                   "predictions, trainer/) once the new run's data and split are checked, then train")
    t.add_argument("--no-progress", action="store_true", help="no progress bar")
    _add_cfg_args(t)
    t.set_defaults(func=_cmd_train)


def register(subparsers) -> None:
    """`resim score` (top level)."""
    p = subparsers.add_parser(
        "score", help="score videos or shard samples with a trained Video2Reward model",
        description="Predict the infraction score (1 = clean driving, lower = collisions / red lights / off-road / "
        "too slow) of videos with a trained Video2Reward checkpoint. Each input is a video file (anything "
        "OpenCV reads) or, with --shards, a shard sample key. Longer videos are scored by sliding windows "
        "(averaged). A video shorter than the model's window, or with an unreadable frame, is an error.")
    p.add_argument("inputs", nargs="+", metavar="VIDEO_OR_SHARD_KEY")
    p.add_argument("--checkpoint", required=True, help="folder written by `resim train reward`")
    p.add_argument("--shards", default=None, help="shard dataset folder to look sample keys up in "
                   "(list them with `resim shards ls DIR --samples`)")
    p.add_argument("--stride", type=_positive_int, default=None, help="frames between window starts (default: window span)")
    p.add_argument("--json", action="store_true", help="print JSON (model metadata + one result per input)")
    p.set_defaults(func=_cmd_score)


def add_features_parser(sub) -> None:
    """`resim shards features ...` (joined to `resim shards` by resim/cli.py)."""
    f = sub.add_parser(
        "features", help="copy a shard dataset adding DINOv2 features (dino.npy) for Video2Reward",
        description=textwrap.fill(width=90, text="Store per-frame DINOv2 features of the reward model's window (float16 (T, N_tokens, D), "
        "meta.dino_id names backbone, input size and window) for every sample with an infraction score, "
        "writing a new dataset. Clips that cannot be featurised are copied without features and quarantined."),
        epilog="example:\n  resim shards features out/shards --preset tiny --out out/shards-dino\n"
        "  resim train reward --preset tiny --shards out/shards-dino --out runs/reward   # uses the stored features",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    f.add_argument("src", help="source shard dataset folder")
    f.add_argument("--out", required=True, help="destination dataset folder (must differ from src; new, empty, "
                   "or an earlier `resim shards features` output)")
    f.add_argument("--threads", type=_non_negative_int, default=0, help="torch threads (0: torch's default)")
    _add_cfg_args(f)
    f.set_defaults(func=_cmd_features)
