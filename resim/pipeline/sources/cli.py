"""``resim synth``: write a synthetic driving dataset in the OpenDV / NAVSIM / CARLA layouts."""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from resim.argtypes import non_negative_int, positive_int
from resim.config import ConfigError, load

PROG = "resim synth"

HELP = """\
Generate a procedural driving world on the CPU and write it in the three real layouts
(default preset demo: 128x224 frames, 16-s episodes; --preset tiny: 64x112, 8 s):

  OUT/opendv/   synth/<episode>.mp4 + videos.csv        (videos, no poses; read with OpenDVConfig.preset("synthetic"))
  OUT/navsim/   navsim_logs/<split>/<log>.pkl + sensor_blobs/<split>/<log>/CAM_F0/*.jpg  (2 Hz logs with poses)
  OUT/carla/    <Scenario>_Town90_Route<id>_Weather<w>/{anno/*.json.gz, camera/rgb_front/*.jpg} (10 Hz)
                + simulation_results.json (leaderboard-style infraction scores)
  OUT/ground_truth.json   exact per-step poses / heading per episode, outcome, reader frame alignment

Episodes go round-robin to opendv, navsim, carla; CARLA episodes alternate expert and
hazardous explorer. With --set fork_fraction=F that share of the episodes comes as counterfactual
triples: one world and one history, identical frame for frame until a junction, then left / straight /
right (for training a world model to follow the command). Same --seed, same bytes. See docs/sources.md.
"""

EPILOG = """\
examples:
  resim synth --out data/synth --preset tiny --episodes 12     # what configs/pipeline/synthetic.yaml reads
                                                               # (with --set sources.synthetic.episodes=12)
  resim synth --out data/synth --episodes 6 --set episode_s=10 --contact-sheet sheet.png --overwrite
  resim synth --out data/forks --episodes 12 --set fork_fraction=1.0          # 4 forks of 3 episodes
"""


def register(subparsers) -> None:
    p = subparsers.add_parser("synth", help="generate a synthetic driving world in the three real layouts",
                              description=HELP, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, help="output folder (must be empty or absent unless --overwrite)")
    p.add_argument("--episodes", type=positive_int, default=12, help="number of episodes (default 12)")
    p.add_argument("--seed", type=non_negative_int, default=0, help="random seed (default 0)")
    p.add_argument("--preset", default="demo",
                   help="config preset: demo (default; 128x224, 16 s) or tiny (64x112, 8 s)")
    p.add_argument("--config", default=None, help="YAML file with SynthConfig fields")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a SynthConfig field, e.g. --set episode_s=10 (repeatable)")
    p.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
    p.add_argument("--contact-sheet", default=None, metavar="PNG",
                   help="also write a contact sheet of a few episodes (read back through the readers)")
    p.add_argument("--workers", type=positive_int, default=1, help="processes rendering episodes in parallel (default 1; "
                   "the output does not depend on it)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args) -> int:
    # numpy and OpenCV only when the command runs: every `resim` call imports this module to register `synth`
    from .synth.generate import SYNTH_PRESETS, SynthConfig, generate

    def error(msg: str, rc: int) -> int:
        print(f"{PROG}: error: {msg}", file=sys.stderr)
        return rc

    if args.preset not in SYNTH_PRESETS:
        return error(f"unknown preset {args.preset!r}; known: {', '.join(sorted(SYNTH_PRESETS))}", 2)
    try:
        cfg = load(SynthConfig, args.config, args.overrides, base=SYNTH_PRESETS[args.preset])
    except (ConfigError, ValueError, TypeError) as e:   # unknown key, bad value, missing/invalid YAML file
        return error(str(e), 2)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        return error(f"--out {out}: exists and is not a folder", 2)
    t0 = time.perf_counter()
    try:
        summary = generate(args.out, args.episodes, args.seed, cfg, overwrite=args.overwrite,
                           progress=not args.quiet, workers=args.workers)
    except ConfigError as e:        # a value only the generator checks
        return error(str(e), 2)
    except FileExistsError as e:    # a non-empty OUT without --overwrite (checked by the generator, before writing)
        return error(f"--out {e}", 2)
    except OSError as e:            # cannot create/write OUT (e.g. a parent that is a file, no permission)
        return error(f"--out {out}: cannot write there ({e.strerror or e})", 1)
    summary["seconds"] = round(time.perf_counter() - t0, 2)
    if args.contact_sheet:
        from .synth.contact_sheet import contact_sheet   # lazy, as above

        try:
            contact_sheet(args.out, args.contact_sheet)
        except OSError as e:
            return error(f"--contact-sheet {args.contact_sheet}: {e.strerror or e}", 1)
        summary["contact_sheet"] = args.contact_sheet
    print(json.dumps(summary, indent=2))
    return 0
