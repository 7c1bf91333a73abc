"""`resim pipeline run|check|submit|status|logs`: the Ray data pipeline from the command line.

Light at import time (argparse, PyYAML): every `resim` call imports this module to register its subcommands, so
the pipeline's modules (and Ray, torch, OpenCV, numpy behind them) are imported inside the handlers that need
them, to keep `resim --help` fast.
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import yaml

from resim.argtypes import wrap as _wrap
from resim.config import ConfigError

RUN_EPILOG = """\
examples:
  resim pipeline run configs/pipeline/synthetic.yaml --out out/synth_shards
  resim pipeline run configs/pipeline/my_videos.yaml --set sources.opendv.root=~/Videos/dashcam --out out/my_videos
  resim pipeline run configs/pipeline/opendv.yaml --set sources.opendv.root=/data/OpenDV-YouTube \\
      --vae /models/CogVideoX-2b --text-encoder /models/CogVideoX-2b --out /data/shards/opendv
  resim pipeline run CONFIG --set ray.address=auto          # join a running cluster from a head node
  resim pipeline run CONFIG --set ray.executor=local        # no Ray: sequential, for debugging

Rerunning the same command after a crash resumes: committed units are skipped, the rest redone.
A second run into an OUT that a live run is writing is refused at once (OUT/.lock); wait, or use another --out.
Output: OUT/{shards,index,manifest,prompts,quarantine,commits}/, config.yaml, split.json, stats.json, report.png.
"""


_Formatter = argparse.RawDescriptionHelpFormatter   # keeps the epilogs' example lines; descriptions go through _wrap


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", help="pipeline YAML (configs/pipeline/*.yaml)")
    p.add_argument("--out", help="output dataset folder (overrides `out:` in the config)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override any config value, e.g. --set clip.stride_frames=10 (YAML-parsed; repeatable)")
    p.add_argument("--vae", help="local CogVideoX VAE folder (diffusers; a pipeline folder with vae/ works too). "
                                 "Default: the tiny random placeholder in configs/models/")
    p.add_argument("--text-encoder", help="local T5 folder (encoder + tokenizer, or a CogVideoX pipeline folder). "
                                          "Default: the tiny random placeholder")


def _overrides(args) -> list[str]:
    ov = list(args.overrides)
    if args.vae:
        ov.append(f"encode.vae={args.vae}")
    if args.text_encoder:
        ov.append(f"encode.text_encoder={args.text_encoder}")
    return ov


def _load(args):
    from resim.pipeline.load import load_config

    return load_config(args.config, _overrides(args), out=args.out)


# What `resim pipeline run` writes in OUT (resim.pipeline.units.OUTPUT_DIRS + its files, the run lock
# resim.pipeline.out_lock.LOCK_NAME included): a folder holding only these is an earlier (maybe unfinished) run of
# the pipeline, which a rerun resumes.
RUN_OUTPUT_NAMES = {"commits", "shards", "index", "manifest", "quarantine", "prompts", "_staging", "dedup",
                    "config.yaml", "config_hash.txt", "stats.json", "report.png", "split.json", ".lock"}


def foreign_out(out) -> str | None:
    """What makes ``out`` a non-empty folder that is not a pipeline output ("a, b, ..."; None when it is absent,
    empty, or written by `resim pipeline run`: config_hash.txt is stamped before any other output)."""
    from resim.shards.layout import foreign_entries

    return None if (Path(out) / "config_hash.txt").is_file() else foreign_entries(out, RUN_OUTPUT_NAMES)


def _job_error(cmd: str, address: str, e: Exception) -> int:
    """A cluster that cannot be reached, a malformed address, an unknown job: one line, exit 1."""
    msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
    print(f"resim pipeline {cmd}: error: Ray dashboard at {address}: {msg}", file=sys.stderr)
    return 1


# what the Ray Jobs client raises for an unreachable/malformed address or an unknown job (requests' errors
# are OSErrors; a bad URL is a ValueError; an unknown job or a refused request a RuntimeError)
JOB_ERRORS = (OSError, ValueError, RuntimeError)


def _cmd_run(args) -> int:
    import logging

    from resim.pipeline import runner
    from resim.pipeline.out_lock import OutBusy
    from resim.pipeline.ray_connect import ClusterError
    from resim.pipeline.report import format_summary
    from resim.pipeline.stages.base import OUTPUT_ERRNOS, OutputError

    logging.basicConfig(level=logging.INFO, format="[pipeline] %(message)s")
    try:
        cfg = _load(args)
        if Path(cfg.out).exists() and not Path(cfg.out).is_dir():
            raise ConfigError(f"out: {cfg.out} is a file, not a folder; give a new or empty folder")
        shown = foreign_out(cfg.out)
        if shown and not args.force:
            raise ConfigError(f"out: {cfg.out} is not empty and is not a pipeline output (it holds {shown}); "
                              "give an empty or new folder (or --force to write into it anyway)")
        if args.no_progress:
            cfg = replace(cfg, ray=replace(cfg.ray, progress_bars=False))
        res = runner.run(cfg, force=args.force)
    except ConfigError as e:
        print(f"config error: {e}", file=sys.stderr)
        return 2
    except (OutBusy, ClusterError) as e:   # OUT in use / no usable cluster: not a config mistake, nothing written
        print(f"resim pipeline run: error: {e}", file=sys.stderr)
        return 1
    except (OutputError, runner.IncompleteRun) as e:   # disk full, read-only OUT, units that did not commit
        print(f"resim pipeline run: error: {e}", file=sys.stderr)
        return 1
    except OSError as e:
        if e.errno not in OUTPUT_ERRNOS:    # anything else is a bug: the traceback says where
            raise
        print(f"resim pipeline run: error: {runner.output_error(e)}", file=sys.stderr)
        return 1
    print(format_summary(res.stats, res.out, res.report_png))
    return 0


def _cmd_check(args) -> int:
    from resim.pipeline.config import to_dict
    from resim.pipeline.video_preflight import opendv_warnings

    try:
        cfg = _load(args)
    except ConfigError as e:
        print(f"config error: {e}", file=sys.stderr)
        return 2
    print(yaml.safe_dump(to_dict(cfg), sort_keys=False), end="")
    for w in opendv_warnings(cfg):   # a valid config that would make nothing from these videos
        print(f"warning: {w}", file=sys.stderr)
    return 0


def _cmd_submit(args) -> int:
    from resim.pipeline import submit   # asyncio and the job client: not at the top, every `resim` call imports this module

    try:
        cfg = _load(args)
    except ConfigError as e:
        print(f"config error: {e}", file=sys.stderr)
        return 2
    try:
        job_id = submit.submit(cfg, args.address, job_id=args.job_id)
    except JOB_ERRORS as e:
        return _job_error("submit", args.address, e)
    print(job_id)
    if args.follow:
        try:
            submit.follow_logs(args.address, job_id)
            status = submit.wait(args.address, job_id, timeout_s=args.timeout_s)
        except JOB_ERRORS as e:
            return _job_error("submit", args.address, e)
        print(f"job {job_id}: {status}", file=sys.stderr)
        return 0 if status == "SUCCEEDED" else 1
    return 0


def _cmd_status(args) -> int:
    from resim.pipeline import submit

    try:
        print(submit.status(args.address, args.job_id))
    except JOB_ERRORS as e:
        return _job_error("status", args.address, e)
    return 0


def _cmd_logs(args) -> int:
    from resim.pipeline import submit

    try:
        if args.follow:
            submit.follow_logs(args.address, args.job_id)
        else:
            print(submit.logs(args.address, args.job_id), end="")
    except JOB_ERRORS as e:
        return _job_error("logs", args.address, e)
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "pipeline", help="the Ray data pipeline: raw sources -> labelled, balanced clips -> latents -> shards",
        description="Turn driving videos/logs (OpenDV, NAVSIM, CARLA layouts, or a synthetic world) into "
                    "training shards: clips cut at 10 Hz, command labels (flow + trajectory), 5x turn balance, "
                    "CogVideoX VAE latents, T5 prompt table. Runs on an embedded local Ray or a cluster.")
    sub = p.add_subparsers(dest="pipeline_command", metavar="SUBCOMMAND")

    r = sub.add_parser("run", help="run a pipeline config (embedded local Ray by default); resumes after a crash",
                       description=_wrap("Run the data pipeline of a config (+ overrides) into OUT: enumerate the "
                                         "sources' units, cut 10 Hz clips, label commands (dropping clips across "
                                         "scene cuts, tagging the car standing still), balance turns, measure each "
                                         "clip's quality (config `quality:` filters), encode VAE latents and "
                                         "prompts, write shards, mark near-duplicates. OUT gets stats.json, "
                                         "report.png and curation.png (dropped examples per reason). OUT must be "
                                         "new, empty or an earlier output of this command (which the run resumes)."),
                       epilog=RUN_EPILOG, formatter_class=_Formatter)
    _common(r)
    r.add_argument("--force", action="store_true",
                   help="write into OUT even if it holds data made with a different config, or other files")
    r.add_argument("--no-progress", action="store_true", help="no progress bars (logs only)")
    r.set_defaults(func=_cmd_run)

    c = sub.add_parser("check", help="validate a config (+ overrides) and print it resolved; starts nothing",
                       description=_wrap("Load a pipeline config with its --set/--out/--vae/--text-encoder overrides, "
                                   "check it (keys, types, source and model folders) and print it resolved as "
                                   "YAML, paths made absolute. Probes the first few OpenDV-layout videos and "
                                   "warns (stderr) where the discards leave less than one clip or every video "
                                   "is below min_height_px. Starts no Ray and writes nothing; exit 2 on a "
                                   "config error."),
                       epilog="example:\n  resim pipeline check configs/pipeline/synthetic.yaml "
                              "--set clip.stride_frames=10 --out out/shards",
                       formatter_class=_Formatter)
    _common(c)
    c.set_defaults(func=_cmd_check)

    s = sub.add_parser("submit", help="submit a config as a job to a running Ray cluster (Ray Jobs API)",
                       description=_wrap("Ships the resolved config and resim's packages in the job's runtime env "
                                   "(working_dir + py_modules) and prints the job id. Paths in the config must "
                                   "be valid on the cluster (relative paths are made absolute here)."),
                       epilog="example:\n  resim pipeline submit configs/pipeline/synthetic.yaml "
                              "--address http://HEAD:8265 --out /shared/shards --follow",
                       formatter_class=_Formatter)
    _common(s)
    s.add_argument("--address", required=True, help="Ray dashboard address, e.g. http://HEAD:8265")
    s.add_argument("--job-id", help="job id to use (default: generated)")
    s.add_argument("--follow", action="store_true", help="stream the job's logs until it ends; exit 1 if it failed")
    s.add_argument("--timeout-s", type=float, default=None, help="with --follow: give up waiting after this long")
    s.set_defaults(func=_cmd_submit)

    st = sub.add_parser("status", help="status of a submitted job",
                        description=_wrap("Print the status of a job submitted with `resim pipeline submit` "
                                    "(PENDING, RUNNING, SUCCEEDED, FAILED or STOPPED)."),
                        epilog="example:\n  resim pipeline status raysubmit_XXXX --address http://HEAD:8265",
                        formatter_class=_Formatter)
    st.add_argument("job_id")
    st.add_argument("--address", required=True, help="Ray dashboard address, e.g. http://HEAD:8265")
    st.set_defaults(func=_cmd_status)

    lg = sub.add_parser("logs", help="logs of a submitted job",
                        description=_wrap("Print the logs of a job submitted with `resim pipeline submit` so far, "
                                    "or with --follow stream them until the job ends."),
                        epilog="example:\n  resim pipeline logs raysubmit_XXXX --address http://HEAD:8265 "
                               "--follow",
                        formatter_class=_Formatter)
    lg.add_argument("job_id")
    lg.add_argument("--address", required=True, help="Ray dashboard address, e.g. http://HEAD:8265")
    lg.add_argument("--follow", action="store_true", help="stream until the job ends")
    lg.set_defaults(func=_cmd_logs)

    p.set_defaults(func=lambda a: (p.print_help(), 2)[1])
