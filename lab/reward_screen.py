"""Screen Video2Reward head settings on a `resim synth` world (docs/lab/2026-11-22-reward-synthetic-world.md,
"Screening").

Two steps, both on the shared CPU with one torch thread:

    PYTHONPATH=. python lab/reward_screen.py cache W/carla feats56.npz          # per-frame features, once
    PYTHONPATH=. python lab/reward_screen.py screen feats56.npz \\
        '[{"name": "sig+diff", "temporal_diff": true}]' --splits 1

``cache`` runs the frozen tiny placeholder backbone (56 px) on all 80 frames of every CARLA-layout route
(one whole-episode clip each, the last frame held like ``--hold-last``) and stores (routes, 80, N, D)
float16 features. ``screen`` trains the head (preset ``synthetic``'s model + the variant's model keys)
with a plain AdamW loop like the Trainer's (constant lr 1e-3, weight decay 0.01, batch 16, 100 epochs,
same shuffling seeds) for each split_seed, holding 20 % of the split's *training* episodes aside as
validation, and prints validation and held-out Spearman / AUC every ``--eval-every`` epochs plus what
early stopping on validation MSE would have given. Choose on validation; held-out is printed for the record.
"""
from __future__ import annotations

import argparse
import copy
import json
import time

import numpy as np
import torch

from resim.config import from_dict
from resim.models.reward.config import RewardModelConfig
from resim.train.tasks.reward.config import PRESETS
from resim.models.reward.model import Video2Reward
from resim.pipeline.sources.carla import CarlaConfig, CarlaReader
from resim.train.smallfit import split_by_episode as _split
from resim.train.tasks.reward.data import RewardClip, clips_from_episode, frames_to_tensor
from resim.train.tasks.reward.metrics import reward_metrics


def cache(root: str, out: str, size: int = 56) -> None:
    m = Video2Reward(RewardModelConfig(image_size_px=size, num_frames=80, frame_step=1)).eval()
    reader = CarlaReader(CarlaConfig(root=root))
    items = reader.list_items()
    feats, score, hazard, ids = [], [], [], []
    t0 = time.time()
    for it in items:
        (c,) = clips_from_episode(reader.open(it), 80, 80, hold_last=True)
        with torch.no_grad():
            feats.append(m.encode(frames_to_tensor(c.frames)[None])[0].half().numpy())
        score.append(c.infraction_score), hazard.append(c.hazard), ids.append(c.item_id)
    np.savez(out, feats=np.stack(feats), score=np.array(score), hazard=np.array(hazard), items=np.array(ids))
    print(f"{len(items)} routes in {time.time() - t0:.0f} s -> {out}")


def run(feats, score, hazard, items, mcfg, split: int, epochs=100, lr=1e-3, wd=0.01, bs=16, seed=0,
        eval_every=10) -> dict:
    clips = [RewardClip(key=str(items[i]), item_id=str(items[i]), infraction_score=float(score[i]),
                        hazard=bool(hazard[i]), dino=np.array([i])) for i in range(len(score))]
    # the hazard-stratified split this screen was run with (the datasets' split.json came later)
    def split_by_episode(cs, fraction, seed):
        return _split(cs, fraction, seed, stratum=lambda c: bool(c.hazard))

    train, held = split_by_episode(clips, 0.25, split)
    train, val = split_by_episode(train, 0.2, 1000 + split)  # validation from the training episodes only
    idx = (feats.shape[1] - mcfg.window_frames) + mcfg.frame_step * np.arange(mcfg.num_frames)  # last window

    def xy(cs):
        x = torch.from_numpy(feats[[int(c.dino[0]) for c in cs]][:, idx].astype(np.float32))
        return x, torch.tensor([c.infraction_score for c in cs]), np.array([c.hazard for c in cs])

    (xt, yt, ht), (xv, yv, hv), (xh, yh, hh) = xy(train), xy(val), xy(held)
    torch.manual_seed(seed)
    m = Video2Reward(mcfg)
    opt = torch.optim.AdamW([p for p in m.parameters() if p.requires_grad], lr=lr, weight_decay=wd)

    def pred(x):
        m.eval()
        with torch.no_grad():
            return torch.cat([m(features=x[i:i + 64]) for i in range(0, len(x), 64)]).numpy()

    best, curve = (float("inf"), None, -1), []
    for e in range(epochs):
        m.train()
        order = np.random.default_rng(seed * 1000 + e).permutation(len(xt))
        for i in range(0, len(order), bs):
            b = order[i:i + bs]
            loss = torch.nn.functional.mse_loss(m(features=xt[b]), yt[b])
            opt.zero_grad()
            loss.backward()
            opt.step()
        if (e + 1) % eval_every == 0 or e == epochs - 1:
            pv, ph = pred(xv), pred(xh)
            vm, hm = reward_metrics(pv, yv.numpy(), hv), reward_metrics(ph, yh.numpy(), hh)
            vmse = float(((pv - yv.numpy()) ** 2).mean())
            curve.append((e + 1, vmse, vm["spearman"], vm["hazard_auc"], hm["spearman"], hm["hazard_auc"]))
            if vmse < best[0]:
                best = (vmse, copy.deepcopy(m.state_dict()), e + 1)
    out = {"curve": curve, "train_mae": reward_metrics(pred(xt), yt.numpy(), ht)["mae"],
           "held": reward_metrics(pred(xh), yh.numpy(), hh)}
    m.load_state_dict(best[1])
    out["es_epoch"], out["es_held"] = best[2], reward_metrics(pred(xh), yh.numpy(), hh)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("cache", help="per-frame features of every route")
    c.add_argument("carla_root")
    c.add_argument("out")
    c.add_argument("--size-px", type=int, default=56)
    s = sub.add_parser("screen", help="train head variants on cached features")
    s.add_argument("features")
    s.add_argument("variants", help='JSON list of {"name", model keys..., optional "train": {epochs, lr, wd, ...}}')
    s.add_argument("--splits", default="0,1,2")
    s.add_argument("--eval-every", type=int, default=10)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    if args.cmd == "cache":
        cache(args.carla_root, args.out, args.size_px)
        return 0

    z = np.load(args.features)
    data = (z["feats"], z["score"], z["hazard"], z["items"])
    for v in json.loads(args.variants):
        name, tr = v.pop("name"), v.pop("train", {})
        mcfg = from_dict(RewardModelConfig, {**PRESETS["synthetic"]["model"], **v})
        for split in (int(x) for x in args.splits.split(",")):
            t0 = time.time()
            r = run(*data, mcfg, split, eval_every=args.eval_every, **tr)
            h, eh = r["held"], r["es_held"]
            print(f"{name} split {split}: held-out Spearman {h['spearman']:.3f} AUC {h['hazard_auc']:.3f} "
                  f"MAE {h['mae']:.3f}; train MAE {r['train_mae']:.3f}; early stop @{r['es_epoch']}: "
                  f"Spearman {eh['spearman']:.3f} AUC {eh['hazard_auc']:.3f} ({time.time() - t0:.0f} s)", flush=True)
            for row in r["curve"]:
                print("  epoch %d  val MSE %.4f  val Spearman %.3f AUC %.3f  |  held-out Spearman %.3f AUC %.3f" % row)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
