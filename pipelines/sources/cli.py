"""``resim synth``: write a synthetic driving dataset in the OpenDV / NAVSIM / CARLA layouts (issue 3)."""
from __future__ import annotations

import argparse

HELP = """\
Generate a procedural driving world on the CPU and write it in the three real layouts:

  OUT/opendv/   synth/<episode>.mp4 + videos.csv        (videos, no poses; read with OpenDVConfig.preset("synthetic"))
  OUT/navsim/   navsim_logs/<split>/<log>.pkl + sensor_blobs/<split>/<log>/CAM_F0/*.jpg  (2 Hz logs with poses)
  OUT/carla/    <Scenario>_Town90_Route<id>_Weather<w>/{anno/*.json.gz, camera/rgb_front/*.jpg} (10 Hz)
                + simulation_results.json (leaderboard-style infraction scores)
  OUT/ground_truth.json   exact per-step poses / heading per episode, outcome, reader frame alignment

Episodes go round-robin to opendv, navsim, carla; CARLA episodes alternate expert and
hazardous explorer. Same --seed, same bytes. See docs/sources.md.
"""


def register(subparsers) -> None:
    p = subparsers.add_parser("synth", help="generate a synthetic driving world in the three real layouts",
                              description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, help="output folder (must be empty or absent unless --overwrite)")
    p.add_argument("--episodes", type=int, default=12, help="number of episodes (default 12)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--preset", default="demo", help="config preset: demo (128x224, 16 s) or tiny (64x112, 8 s)")
    p.add_argument("--config", default=None, help="YAML file with SynthConfig fields")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a SynthConfig field, e.g. --set episode_s=10 (repeatable)")
    p.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
    p.add_argument("--contact-sheet", default=None, metavar="PNG",
                   help="also write a contact sheet of a few episodes (read back through the readers)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args) -> int:
    import json
    import time

    from resim.config import load

    from .synth.generate import SYNTH_PRESETS, SynthConfig

    if args.preset not in SYNTH_PRESETS:
        raise SystemExit(f"unknown preset {args.preset!r}; known: {sorted(SYNTH_PRESETS)}")
    cfg = load(SynthConfig, args.config, args.overrides, base=SYNTH_PRESETS[args.preset])
    from .synth.generate import generate

    t0 = time.perf_counter()
    summary = generate(args.out, args.episodes, args.seed, cfg, overwrite=args.overwrite, progress=not args.quiet)
    summary["seconds"] = round(time.perf_counter() - t0, 2)
    if args.contact_sheet:
        from .synth.contact_sheet import contact_sheet

        contact_sheet(args.out, args.contact_sheet)
        summary["contact_sheet"] = args.contact_sheet
    print(json.dumps(summary, indent=2))
    return 0
