"""`resim pipeline run|check|submit|status|logs`: the Ray data pipeline from the command line.

Light at import time (argparse only); Ray, torch and OpenCV are imported inside the handlers.
"""
from __future__ import annotations

import argparse
import sys

RUN_EPILOG = """\
examples:
  resim pipeline run configs/pipeline/synthetic.yaml --out out/synth_shards
  resim pipeline run configs/pipeline/opendv.yaml --set sources.opendv.root=/data/OpenDV-YouTube \\
      --vae /models/CogVideoX-2b --text-encoder /models/CogVideoX-2b --out /data/shards/opendv
  resim pipeline run CONFIG --set ray.address=auto          # join a running cluster from a head node
  resim pipeline run CONFIG --set ray.executor=local        # no Ray: sequential, for debugging

Rerunning the same command after a crash resumes: committed units are skipped, the rest redone.
Output: OUT/{shards,index,manifest,prompts,quarantine,commits}/, config.yaml, stats.json, report.png.
"""


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
    from pipelines.config import load_config

    return load_config(args.config, _overrides(args), out=args.out)


def _cmd_run(args) -> int:
    import logging

    from pipelines import runner
    from pipelines.report import format_summary
    from resim.config import ConfigError

    logging.basicConfig(level=logging.INFO, format="[pipeline] %(message)s")
    try:
        cfg = _load(args)
        if args.no_progress:
            from dataclasses import replace

            cfg = replace(cfg, ray=replace(cfg.ray, progress_bars=False))
        res = runner.run(cfg, force=args.force)
    except ConfigError as e:
        print(f"config error: {e}", file=sys.stderr)
        return 2
    print(format_summary(res.stats, res.out, res.report_png))
    return 0


def _cmd_check(args) -> int:
    import yaml

    from pipelines.config import to_dict
    from resim.config import ConfigError

    try:
        cfg = _load(args)
    except ConfigError as e:
        print(f"config error: {e}", file=sys.stderr)
        return 2
    print(yaml.safe_dump(to_dict(cfg), sort_keys=False), end="")
    return 0


def _cmd_submit(args) -> int:
    from pipelines import submit
    from resim.config import ConfigError

    try:
        cfg = _load(args)
    except ConfigError as e:
        print(f"config error: {e}", file=sys.stderr)
        return 2
    job_id = submit.submit(cfg, args.address, job_id=args.job_id)
    print(job_id)
    if args.follow:
        submit.follow_logs(args.address, job_id)
        status = submit.wait(args.address, job_id, timeout_s=args.timeout_s)
        print(f"job {job_id}: {status}", file=sys.stderr)
        return 0 if status == "SUCCEEDED" else 1
    return 0


def _cmd_status(args) -> int:
    from pipelines import submit

    print(submit.status(args.address, args.job_id))
    return 0


def _cmd_logs(args) -> int:
    from pipelines import submit

    if args.follow:
        submit.follow_logs(args.address, args.job_id)
    else:
        print(submit.logs(args.address, args.job_id), end="")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "pipeline", help="the Ray data pipeline: raw sources -> labelled, balanced clips -> latents -> shards",
        description="Turn driving videos/logs (OpenDV, NAVSIM, CARLA layouts, or a synthetic world) into "
                    "training shards: clips cut at 10 Hz, command labels (flow + trajectory), 5x turn balance, "
                    "CogVideoX VAE latents, T5 prompt table. Runs on an embedded local Ray or a cluster.")
    sub = p.add_subparsers(dest="pipeline_command", metavar="SUBCOMMAND")

    r = sub.add_parser("run", help="run a pipeline config (embedded local Ray by default); resumes after a crash",
                       epilog=RUN_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    _common(r)
    r.add_argument("--force", action="store_true",
                   help="write into OUT even if it holds data made with a different config")
    r.add_argument("--no-progress", action="store_true", help="no progress bars (logs only)")
    r.set_defaults(func=_cmd_run)

    c = sub.add_parser("check", help="validate a config (+ overrides) and print it resolved; starts nothing")
    _common(c)
    c.set_defaults(func=_cmd_check)

    s = sub.add_parser("submit", help="submit a config as a job to a running Ray cluster (Ray Jobs API)",
                       description="Ships the resolved config and resim's packages in the job's runtime env "
                                   "(working_dir + py_modules) and prints the job id. Paths in the config must "
                                   "be valid on the cluster (relative paths are made absolute here).")
    _common(s)
    s.add_argument("--address", required=True, help="Ray dashboard address, e.g. http://HEAD:8265")
    s.add_argument("--job-id", help="job id to use (default: generated)")
    s.add_argument("--follow", action="store_true", help="stream the job's logs until it ends; exit 1 if it failed")
    s.add_argument("--timeout-s", type=float, default=None, help="with --follow: give up waiting after this long")
    s.set_defaults(func=_cmd_submit)

    st = sub.add_parser("status", help="status of a submitted job")
    st.add_argument("job_id")
    st.add_argument("--address", required=True, help="Ray dashboard address, e.g. http://HEAD:8265")
    st.set_defaults(func=_cmd_status)

    lg = sub.add_parser("logs", help="logs of a submitted job")
    lg.add_argument("job_id")
    lg.add_argument("--address", required=True, help="Ray dashboard address, e.g. http://HEAD:8265")
    lg.add_argument("--follow", action="store_true", help="stream until the job ends")
    lg.set_defaults(func=_cmd_logs)

    p.set_defaults(func=lambda a: (p.print_help(), 2)[1])
