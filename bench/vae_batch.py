"""The synthetic world's VAE one clip per call (diffusers' slicing) against a batch of clips per call, in the
same process: decoding (``decode_latents(batch_size=N)``, what evaluation and planning do) and encoding
(``VideoVAE.encode`` with slicing off, what the pipeline does with ``encode.batch_size`` > 1 and
``encode.vae_slicing: false``).

Clips of the shape the synthetic world uses (49 frames of 64 x 96 <-> 13 latent frames of 16 x 8 x 12); random
latents and random pixels, which cost the same as real ones. Prints seconds per clip, the ratio and how far
the results of the two ways differ.
Run: PYTHONPATH=. python bench/vae_batch.py [--clips 8] [--threads 2] [--vae configs/models/synth-vae]
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from resim.media.encoders import VideoVAE
from resim.sample.outputs import decode_latents


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--clips", type=int, default=8)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--vae", default="configs/models/synth-vae")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    vae = VideoVAE(args.vae, device="cpu")          # slicing + tiling on, as `resim eval` / `resim sample` load it
    z = torch.randn(args.clips, 13, 16, 8, 12, generator=torch.Generator().manual_seed(0))
    decode_latents(vae, z[:2], batch_size=2)        # warm-up (allocator, oneDNN primitives)

    def best_of(fn) -> tuple[float, np.ndarray]:
        best, out = float("inf"), None
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            out = fn()
            best = min(best, time.perf_counter() - t0)
        return best, out

    def diffusers_one_per_call() -> np.ndarray:
        """What decoding was: diffusers' decode of one clip per call (13 latent frames: odd, no padding)."""
        out = []
        with torch.inference_mode():
            for i in range(args.clips):
                x = vae.model.decode(z[i:i + 1].permute(0, 2, 1, 3, 4) / vae.info.scaling_factor).sample
                out.append(((x.clamp(-1, 1) + 1) * 127.5).round().to(torch.uint8).permute(0, 2, 3, 4, 1).numpy())
        return np.concatenate(out)

    t_base, a = best_of(diffusers_one_per_call)
    rows = [("diffusers, 1 clip per call (baseline)", t_base)]
    for bs in sorted({1, 4, args.clips}):
        t_b, b = best_of(lambda: decode_latents(vae, z, batch_size=bs))
        d = np.abs(a.astype(int) - b.astype(int))
        rows.append((f"decode_latents, batch_size={bs}", t_b))
        print(f"batch_size={bs}: uint8 difference to the baseline: max {d.max()}, share of values {float((d > 0).mean()):.1e}")
    print(f"decode {args.clips} clips of 13 latent frames (49 frames 64x96), {args.threads} torch thread(s), best of {args.repeats}")
    for name, t in rows:
        print(f"  {name:<38} {t:6.2f} s  {t / args.clips:5.2f} s/clip  x{t_base / t:4.1f}")

    # encoding: the pipeline's encode stage hands VideoVAE.encode up to encode.batch_size clips of one episode
    frames = np.random.default_rng(0).integers(0, 256, (args.clips, 49, 64, 96, 3), dtype=np.uint8)
    seeds = list(range(args.clips))
    vae.encode(frames[:1], seeds[:1])               # warm-up
    t0 = time.perf_counter()
    one = np.concatenate([vae.encode(frames[i:i + 1], seeds[i:i + 1]) for i in range(args.clips)])
    t_enc1 = time.perf_counter() - t0
    vae.model.disable_slicing()
    t0 = time.perf_counter()
    four = np.concatenate([vae.encode(frames[i:i + 4], seeds[i:i + 4]) for i in range(0, args.clips, 4)])
    t_enc4 = time.perf_counter() - t0
    print(f"encode {args.clips} clips of 49 frames 64x96:")
    print(f"  {'1 clip per call (slicing)':<38} {t_enc1:6.2f} s  {t_enc1 / args.clips:5.2f} s/clip  x 1.0")
    print(f"  {'4 clips per call':<38} {t_enc4:6.2f} s  {t_enc4 / args.clips:5.2f} s/clip  x{t_enc1 / t_enc4:4.1f}"
          f"   (latents differ by at most {float(np.abs(one - four).max()):.1e})")


if __name__ == "__main__":
    main()
