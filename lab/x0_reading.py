"""Model or sampler? Decoded one-step clean estimates at several noise levels, and a plain DDIM loop.

For dev clips (one per episode in turn), with the history clean:

* at each level t the future is noised, the model predicts v once and ``x0 = sqrt(a) x_t - sqrt(1 - a) v`` is
  decoded: its future latent MSE and the PSNR of the first and fifth future frame against the VAE's decoding of
  the recorded latents (a model that removes the noise gets better as t falls);
* a 20-step DDIM loop (trailing spacing, conditional branch only) written here apart from
  ``resim.sample.rollout``: if it draws what the product's sampler draws, the sampler is not at fault;
* copy-last-frame beside them.

Writes a picture (rows: recorded, each level, DDIM; columns: the last history frame and four future frames of two
clips) and appends one JSON row per checkpoint to ``--out``.

  python lab/x0_reading.py --checkpoint RUN [RUN ...] --shards DEV [--clips 16] [--out rows.jsonl] [--png DIR]
"""
from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from resim.diffusion.ddim import ddim_step, v_to_x0_eps
from resim.diffusion.schedule import add_noise, alphas_cumprod
from resim.eval.worldeval import eval_clips_from_dataset
from resim.sample.bundle import WorldModelBundle
from resim.sample.outputs import decode_latents

LEVELS = (999, 800, 500, 200, 50)


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = ((a.astype(np.float64) - b.astype(np.float64)) ** 2).mean()
    return float(10 * np.log10(255 ** 2 / max(mse, 1e-10)))


def one_per_episode(shards: Path, n: int, keep=lambda clip: True, need_trajectory: bool = False) -> list:
    """Up to ``n`` clips of ``shards`` that ``keep`` accepts, one episode after another in turn (the dataset's order
    would give the many clips of its first episodes)."""
    by_episode: dict[str, list] = {}
    for c in eval_clips_from_dataset(shards, items=None, need_trajectory=need_trajectory):
        if keep(c):
            by_episode.setdefault(c.item_id, []).append(c)
    return [c for g in itertools.zip_longest(*by_episode.values()) for c in g if c is not None][:n]


@torch.no_grad()
def read(checkpoint: str, shards: Path, clips: int, ddim_steps: int = 20, seed: int = 0) -> tuple[dict, np.ndarray]:
    wm = WorldModelBundle.from_pretrained(checkpoint, shards=shards)
    ac = alphas_cumprod(wm.objective.schedule)
    cs = one_per_episode(shards, clips)
    x0 = torch.from_numpy(np.stack([c.latents for c in cs])).float()
    h, b = cs[0].num_history_latents, len(cs)
    prompts = wm.prompts()
    text = torch.cat([prompts(c.command) for c in cs])
    truth = decode_latents(wm.vae, x0, batch_size=4)
    g = torch.Generator().manual_seed(seed)
    row = {"checkpoint": str(checkpoint), "clips": b, "episodes": len({c.item_id for c in cs}), "levels": {},
           "copy_last_psnr": [_psnr(truth[:, h - 1], truth[:, h]), _psnr(truth[:, h - 1], truth[:, h + 4])]}
    pics = [truth]

    def frame_levels(level: int) -> torch.Tensor:
        t = torch.zeros(b, x0.shape[1], dtype=torch.long)
        t[:, h:] = level
        return t

    for level in LEVELS:
        t = frame_levels(level)
        x_t = add_noise(x0, torch.randn(x0.shape, generator=g), t, ac)
        x_t[:, :h] = x0[:, :h]
        est, _ = v_to_x0_eps(x_t, wm.model(x_t, t, text, None, None), ac[t][:, :, None, None, None])
        est[:, :h] = x0[:, :h]
        d = decode_latents(wm.vae, est, batch_size=4)
        pics.append(d)
        row["levels"][str(level)] = {"latent_mse": float(((est - x0)[:, h:] ** 2).mean()),
                                     "psnr": [_psnr(d[:, h], truth[:, h]), _psnr(d[:, h + 4], truth[:, h + 4])]}
    levels = np.linspace(ac.shape[0] - 1, 0, ddim_steps + 1).round().astype(int)[:-1]   # trailing spacing
    x = x0.clone()
    x[:, h:] = torch.randn(x[:, h:].shape, generator=g)
    for i, s in enumerate(levels):
        v = wm.model(x, frame_levels(int(s)), text, None, None)
        a_prev = ac[levels[i + 1]] if i + 1 < len(levels) else torch.tensor(1.0, dtype=ac.dtype)
        x[:, h:] = ddim_step(x, v, ac[int(s)], a_prev)[0][:, h:]
    d = decode_latents(wm.vae, x, batch_size=4)
    pics.append(d)
    row["ddim"] = {"latent_mse": float(((x - x0)[:, h:] ** 2).mean()),
                   "psnr": [_psnr(d[:, h], truth[:, h]), _psnr(d[:, h + 4], truth[:, h + 4])],
                   "latent_std": float(x[:, h:].std()), "true_latent_std": float(x0[:, h:].std())}
    sel = [h - 1, h, h + 2, h + 6, h + 12]
    pic = np.concatenate([np.concatenate([np.concatenate([r[k, f] for f in sel], 1) for k in (0, 1)], 1)
                          for r in pics], 0)
    return row, pic


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", nargs="+", required=True, help="world-model run folders (or their final/)")
    p.add_argument("--shards", type=Path, required=True, help="dev dataset folder (never the held-out one)")
    p.add_argument("--clips", type=int, default=16)
    p.add_argument("--out", type=Path, help="append one JSON row per checkpoint here")
    p.add_argument("--png", type=Path, help="folder for one picture per checkpoint")
    a = p.parse_args()
    torch.set_num_threads(1)
    for ck in a.checkpoint:
        row, pic = read(ck, a.shards, a.clips)
        print(f"{ck} ({row['clips']} clips of {row['episodes']} episodes); copy-last PSNR "
              f"{row['copy_last_psnr'][0]:.1f} / {row['copy_last_psnr'][1]:.1f} dB (first / fifth future frame)")
        for lv, r in row["levels"].items():
            print(f"  x0 at t={lv:>3}: latent MSE {r['latent_mse']:.4f}, PSNR {r['psnr'][0]:.1f} / {r['psnr'][1]:.1f}")
        r = row["ddim"]
        print(f"  plain DDIM: latent MSE {r['latent_mse']:.4f}, PSNR {r['psnr'][0]:.1f} / {r['psnr'][1]:.1f}, "
              f"latent std {r['latent_std']:.3f} (recorded {r['true_latent_std']:.3f})")
        if a.out:
            with open(a.out, "a") as f:
                f.write(json.dumps(row) + "\n")
        if a.png:
            a.png.mkdir(parents=True, exist_ok=True)
            Image.fromarray(pic).save(a.png / f"{Path(ck).name}.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
