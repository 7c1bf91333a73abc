"""What a representation costs: the world model's training step on its latents and the VAE's encode per clip,
as ratios against the shipped layout (CogVideoX's 4x temporal VAE at 10 Hz) run in the same process.

Layouts (the synthetic world's 64 x 96 clips; docs/lab/2026-12-07-representation.md):
  R4@10   4x temporal VAE, 10 Hz, 9 + 40 frames -> 13 latent frames of 16 x 8 x 12   (baseline)
  R2@5    2x temporal VAE,  5 Hz, 5 + 20 frames -> 13 latent frames
  R1@5    per-frame VAE,    5 Hz, 3 + 20 frames -> 23 latent frames
  R1s@5   per-frame VAE at 4x spatial (3 levels), 23 latent frames of C x 16 x 24 (C = 4 or 8), 4 x 4 patches:
          the same 24 tokens per frame as at 8x
  px@5    pixels (no VAE),  5 Hz, 3 + 20 frames of 3 x 64 x 96, 8 x 8 patches: the reference ceiling
The step is the world model's forward + backward on a batch (random weights and inputs: the cost does not depend
on them), the synth preset (width 192, 6 blocks) with 64 text tokens. Encode: the VAE's widths as trained
((16, 32, 64, 64) at 8x, (16, 32, 64) at 4x), random weights, one clip per call as the pipeline's actors run it.

Usage: PYTHONPATH=. python bench/representation_cost.py [--batch 8] [--threads 2] [--repeats 3]
"""
from __future__ import annotations

import argparse
import timeit

import torch
from diffusers import AutoencoderKLCogVideoX

from resim.models.world.config import preset
from resim.models.world.dit import WorldModel
from resim.train.tasks.vae import VaeTrainConfig, diffusers_config

# name: (VAE temporal ratio or None for pixels, pixel frames, latent frames, (C, h, w) per frame, patch, VAE widths)
WIDE = (16, 32, 64, 64)
LAYOUTS = {"R4@10": (4, 49, 13, (16, 8, 12), 2, WIDE), "R2@5": (2, 25, 13, (16, 8, 12), 2, WIDE),
           "R1@5": (1, 23, 23, (16, 8, 12), 2, WIDE),
           "R1s@5 C4": (1, 23, 23, (4, 16, 24), 4, (16, 32, 64)), "R1s@5 C8": (1, 23, 23, (8, 16, 24), 4, (16, 32, 64)),
           "px@5": (None, 23, 23, (3, 64, 96), 8, None)}


def _best_ms(fn, repeats: int) -> float:
    """Best of ``repeats`` calls after one warm-up call, in ms (the stdlib's timer)."""
    fn()
    return min(timeit.repeat(fn, repeat=repeats, number=1)) * 1e3


def step_ms(latent_frames: int, chw: tuple[int, int, int], patch: int, batch: int, repeats: int) -> tuple[float, int]:
    c, h, w = chw
    torch.manual_seed(0)
    model = WorldModel(preset("synth", in_channels=c, out_channels=c, patch_size=patch)).train()
    x = torch.randn(batch, latent_frames, c, h, w)
    t = torch.randint(0, 1000, (batch, latent_frames))
    text = torch.randn(batch, model.cfg.max_text_seq_length, model.cfg.text_embed_dim)

    def step():
        model.zero_grad(set_to_none=True)
        torch.nn.functional.mse_loss(model(x, t, text), x).backward()

    p = model.cfg.patch_size
    return _best_ms(step, repeats), latent_frames * (h // p) * (w // p)


def encode_ms(ratio: int, frames: int, widths: tuple[int, ...], channels: int, repeats: int) -> float:
    cfg = VaeTrainConfig(block_out_channels=widths, temporal_compression_ratio=ratio, clip_frames=9,
                         latent_channels=channels)
    torch.manual_seed(0)
    vae = AutoencoderKLCogVideoX(**diffusers_config(cfg)).eval()
    x = torch.rand(1, 3, frames, 64, 96) * 2 - 1
    with torch.inference_mode():
        return _best_ms(lambda: vae.encode(x).latent_dist.mean, repeats)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    print(f"device=cpu threads={a.threads} batch={a.batch} (best of {a.repeats} after a warm-up)")
    rows = {}
    for name, (ratio, px, lat, chw, patch, widths) in LAYOUTS.items():
        ms, tokens = step_ms(lat, chw, patch, a.batch, a.repeats)
        enc = encode_ms(ratio, px, widths, chw[0], a.repeats) if ratio is not None else None
        rows[name] = (tokens, ms, enc)
        print(f"  measured {name}", flush=True)
    base_step, base_enc = rows["R4@10"][1], rows["R4@10"][2]
    print(f"| layout | video tokens | train step (ms) | vs R4@10 | encode per clip (ms) | vs R4@10 |")
    print("|---|---|---|---|---|---|")
    for name, (tokens, ms, enc) in rows.items():
        e = "-" if enc is None else f"{enc:.0f} | {enc / base_enc:.2f}x"
        print(f"| {name} | {tokens} | {ms:.0f} | {ms / base_step:.2f}x | {e if enc is not None else '- | -'} |")


if __name__ == "__main__":
    main()
