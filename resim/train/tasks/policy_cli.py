"""`resim train policy`: behaviour-clone the pixel driving policy on shards (registered by resim/train/cli.py;
`resim simulate`, which drives it, is resim/eval/simulate_cli.py)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path



DESCRIPTION = """\
Train the driving policy that reads camera frames and a navigation command and answers the next 8 waypoints
(the world model's trajectory input): behaviour cloning on the expert clips of shard datasets (hazardous
clips left out), held out by episode. Writes OUT/final/ (weights + config.yaml), OUT/policy_report.json
(held-out ADE/FDE per command beside constant velocity), metrics.jsonl and a loss curve."""

EPILOG = """\
example (the synthetic world):
  resim pipeline run configs/pipeline/synthetic.yaml --out data/world
  resim train policy --shards data/world --out runs/policy --epochs 30
Closed-loop driving with it: docs/closed_loop.md."""


def add_train_parser(sub) -> None:
    t = sub.add_parser("policy", help="train the pixel driving policy (behaviour cloning on expert clips)",
                       description=DESCRIPTION, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    t.add_argument("--shards", nargs="+", required=True, metavar="DIR", help="shard dataset folder(s)")
    t.add_argument("--out", required=True, help="output folder (new or empty)")
    t.add_argument("--preset", default="tiny", help="policy preset: tiny (~0.19 M parameters) or small")
    t.add_argument("--epochs", type=int, default=30, help="passes over the training clips (default 30)")
    t.add_argument("--lr", type=float, default=2e-3, help="peak learning rate (AdamW, warmup + cosine)")
    t.add_argument("--seed", type=int, default=0, help="initialisation and shuffling seed")
    t.add_argument("--no-progress", action="store_true", help="no progress bar")
    t.set_defaults(func=_cmd_train)


def _cmd_train(args) -> int:
    from resim.config import ConfigError, from_dict
    from resim.train.tasks.policy import PolicyDataError, PolicyTrainConfig, run_policy_training

    prog = "resim train policy"
    out = Path(args.out)
    if out.exists() and any(out.iterdir()):
        print(f"{prog}: {out} exists and is not empty; choose a new folder", file=sys.stderr)
        return 2
    try:
        tcfg = from_dict(PolicyTrainConfig, {"preset": args.preset, "epochs": args.epochs, "seed": args.seed,
                                             "optim": {"lr": args.lr}})
        tcfg.model_cfg()
    except ConfigError as e:
        print(f"{prog}: config error: {e}", file=sys.stderr)
        return 2
    print(f"[resim] reading the expert clips of {', '.join(args.shards)} ...", file=sys.stderr)
    try:
        res = run_policy_training(args.shards, tcfg, out, progress=not args.no_progress)
    except (FileNotFoundError, PolicyDataError) as e:
        print(f"{prog}: {e}", file=sys.stderr)
        return 2
    p, h = res["protocol"], res["heldout"]["all"]
    print(f"[resim] policy: {res['model']['parameters']:,} parameters, {p['clips_train']} training clips "
          f"({p['episodes_train']} episodes), {res['training']['steps']} steps in {res['training']['seconds']:.0f} s")
    print(f"held-out ({p['clips_heldout']} clips, {p['episodes_heldout']} episodes):")
    for name, row in res["heldout"].items():
        print(f"  {name:15s} policy ADE {row['policy']['ade_m']:.2f} m FDE {row['policy']['fde_m']:.2f} m   "
              f"constant velocity ADE {row['constant_velocity']['ade_m']:.2f} m  (n={row['policy']['n']})")
    print(f"wrote {out}/policy_report.json and {out}/final/")
    return 0 if h["policy"]["n"] else 1
