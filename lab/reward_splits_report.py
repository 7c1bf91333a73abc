"""Report Video2Reward runs trained on several held-out splits of one world (docs/reward.md).

Reads the folders written by ``resim train reward`` (final/meta.json, heldout_predictions.json; one
folder per split of the dataset, ``resim shards split DIR --seed S`` before each run) and prints a markdown
table of every split (n, MAE, Spearman, hazard AUC, train MAE), the held-out error per kind of synthetic episode (the kind is read from
the `resim synth` route name, e.g. ``SynthExplorerStop_...``), and writes one predicted-vs-true
plot with a panel per split.

    PYTHONPATH=. python lab/reward_splits_report.py runs/s0 runs/s1 runs/s2 --png docs/reward_heldout_synth.png
"""
from __future__ import annotations

import argparse
import json
import re
from collections import defaultdict
from pathlib import Path

import numpy as np


def load_run(d: Path) -> dict:
    meta_p = d / "final" / "meta.json"   # runs written before the shared export layout: d / "meta.json"
    meta = json.loads((meta_p if meta_p.is_file() else d / "meta.json").read_text())
    for split in ("heldout_metrics", "train_metrics"):   # meta.json writes an undefined metric as null
        m = meta.get(split) or {}
        meta[split] = {k: float("nan") if v is None else v for k, v in m.items()}
    preds = json.loads((d / "heldout_predictions.json").read_text())
    # the dataset's split the run read (meta.json "split", docs/reward.md "Data and split")
    return {"dir": d, "meta": meta, "preds": preds, "split": meta["split"]["seed"]}


def kind_of(item_id: str) -> str:
    m = re.match(r"Synth(\w+?)_Town", item_id)
    return m.group(1) if m else "other"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="`resim train reward` output folders")
    ap.add_argument("--png", default=None, help="write the per-split predicted-vs-true plot here")
    args = ap.parse_args(argv)
    runs = [load_run(Path(r)) for r in args.runs]
    print("| split seed | held-out n | MAE | Spearman | hazard AUC | train MAE |")
    print("|---|---|---|---|---|---|")
    for r in runs:
        h, t = r["meta"]["heldout_metrics"], r["meta"]["train_metrics"]
        print(f"| {r['split']} | {h['n']} | {h['mae']:.3f} | {h['spearman']:.3f} | {h['hazard_auc']:.3f} | {t['mae']:.3f} |")
    hs = [r["meta"]["heldout_metrics"] for r in runs]
    print(f"| mean | | {np.mean([h['mae'] for h in hs]):.3f} | {np.mean([h['spearman'] for h in hs]):.3f} | "
          f"{np.mean([h['hazard_auc'] for h in hs]):.3f} | |")
    print("\nheld-out episodes per kind, all splits pooled: n, mean true -> mean predicted, MAE")
    by = defaultdict(list)
    for r in runs:
        for p in r["preds"]:
            by[kind_of(p["item_id"])].append((p["true"], p["pred"]))
    for k, v in sorted(by.items()):
        a = np.array(v)
        print(f"  {k:20s} n={len(a):3d}  {a[:, 0].mean():.2f} -> {a[:, 1].mean():.2f}  MAE {np.abs(a[:, 0] - a[:, 1]).mean():.3f}")
    if args.png:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(1, len(runs), figsize=(3.6 * len(runs), 3.7), dpi=110, squeeze=False)
        for ax, r in zip(axes[0], runs):
            true = np.array([p["true"] for p in r["preds"]])
            pred = np.array([p["pred"] for p in r["preds"]])
            haz = np.array([p["hazard"] for p in r["preds"]], bool)
            stop = np.array([kind_of(p["item_id"]) == "ExplorerStop" for p in r["preds"]])
            ax.scatter(true[~haz], pred[~haz], s=12, alpha=0.7, label="clean")
            ax.scatter(true[haz & ~stop], pred[haz & ~stop], s=12, alpha=0.7, c="tab:red", label="hazardous")
            ax.scatter(true[stop], pred[stop], s=18, marker="x", c="tab:purple", label="hazardous: long stop")
            ax.plot([0, 1.05], [0, 1.05], "k--", lw=0.8)
            ax.set_xlim(0, 1.05)
            ax.set_ylim(0, 1.05)
            h = r["meta"]["heldout_metrics"]
            ax.set_title(f"split seed {r['split']}: MAE {h['mae']:.3f}\nSpearman {h['spearman']:.3f}  "
                         f"AUC {h['hazard_auc']:.3f}  (n={h['n']})", fontsize=8)
            ax.set_xlabel("true infraction score", fontsize=8)
        axes[0][0].set_ylabel("predicted (held-out episodes)", fontsize=8)
        axes[0][0].legend(fontsize=7, loc="lower right")
        fig.tight_layout()
        fig.savefig(args.png)
        print(f"\nplot: {args.png}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
