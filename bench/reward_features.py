"""Benchmark: Video2Reward training from stored DINOv2 features vs through the frozen backbone.

Both paths train the same model (same seed, same clips, same batches) through the common
Trainer in this one process; the baseline is the backbone path. Printed: training samples/s of
each path, the ratio, and the one-time cost of computing the stored features.

    PYTHONPATH=. python bench/reward_features.py                 # tiny placeholder backbone, 56 px
    PYTHONPATH=. python bench/reward_features.py --small224      # + a DINOv2-small-shaped random backbone, 224 px

Backbones are random-init placeholders (timing only; no pretrained weights are used).
"""
from __future__ import annotations

import argparse
import sys
import json
import tempfile
import time
from pathlib import Path

import torch

from resim.config import from_dict
from resim.train.tasks.reward.config import RewardTrainConfig
from resim.models.reward.model import Video2Reward
from resim.train.tasks.reward.features import add_clip_features
from resim.train.tasks.reward.train import fit

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))   # the shared fixtures of tests/support
from tests.support.reward_toy import toy_clips  # noqa: E402

DINOV2_SMALL_SHAPE = {  # facebook/dinov2-small's architecture (ViT-S/14), random weights
    "model_type": "dinov2", "hidden_size": 384, "num_hidden_layers": 12, "num_attention_heads": 6,
    "mlp_ratio": 4, "image_size": 518, "patch_size": 14, "layerscale_value": 1.0, "resim_placeholder": True,
}


def bench(name: str, model_cfg: dict, clips, epochs: int, batch: int, repeats: int) -> dict:
    """Best of ``repeats`` interleaved runs per path (the machine is shared: the best is the least disturbed)."""
    cfg = from_dict(RewardTrainConfig, {"epochs": epochs, "batch_size_per_gpu": batch, "model": model_cfg})
    out = {"name": name, "clips": len(clips), "epochs": epochs, "batch": batch, "repeats": repeats}
    with tempfile.TemporaryDirectory() as tmp:
        m = Video2Reward(cfg.model)
        t0 = time.perf_counter()
        feats = add_clip_features(m, clips)
        out["extract_samples_per_s"] = len(clips) / (time.perf_counter() - t0)
        out["dino_bytes_per_sample"] = int(feats[0].dino.nbytes)
        best = {True: 0.0, False: 0.0}
        for rep in range(repeats):
            for use in (True, False):
                torch.manual_seed(0)
                r = fit(Video2Reward(cfg.model), feats if use else clips, cfg, use_features=use,
                        run_dir=Path(tmp) / f"{use}{rep}")
                best[use] = max(best[use], r["samples_per_s"])
        out["stored_samples_per_s"], out["backbone_samples_per_s"] = best[True], best[False]
    out["ratio_stored_vs_backbone"] = out["stored_samples_per_s"] / out["backbone_samples_per_s"]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--small224", action="store_true", help="also bench a DINOv2-small-shaped backbone at 224 px")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    rows = []
    clips = toy_clips(16, 4, 8, h=64, w=96, seed=0)  # 64 clips
    rows.append(bench("tiny placeholder (D=32, 2 layers), 56 px, 8 frames", {"num_frames": 8}, clips, 2, 16, args.repeats))
    if args.small224:
        with tempfile.TemporaryDirectory() as d:
            (Path(d) / "config.json").write_text(json.dumps(DINOV2_SMALL_SHAPE))
            small_clips = clips[:16]
            rows.append(bench("DINOv2-small-shaped (ViT-S/14, random), 224 px, 8 frames",
                              {"num_frames": 8, "image_size_px": 224, "backbone_dir": d, "head_dim": 128,
                               "num_heads": 4, "mlp_hidden_dim": 256}, small_clips, 2, 4, args.repeats))
    print(f"torch {torch.__version__}, {args.threads} threads, CPU")
    for r in rows:
        print(f"{r['name']}: backbone path {r['backbone_samples_per_s']:.1f} samples/s, stored features "
              f"{r['stored_samples_per_s']:.1f} samples/s -> ratio {r['ratio_stored_vs_backbone']:.1f}x; "
              f"one-time extraction {r['extract_samples_per_s']:.1f} samples/s, "
              f"dino.npy {r['dino_bytes_per_sample'] / 1024:.1f} KiB/sample")
    print(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
