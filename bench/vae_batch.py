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

from media.encoders import VideoVAE
from training.sampling.outputs import decode_latents


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

    def timed(bs: int) -> tuple[float, np.ndarray]:
        best, out = float("inf"), None
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            out = decode_latents(vae, z, batch_size=bs)
            best = min(best, time.perf_counter() - t0)
        return best, out

    t_one, a = timed(1)
    rows = [("1 clip per call (baseline)", 1, t_one)]
    for bs in sorted({4, args.clips}):
        t_b, b = timed(bs)
        d = np.abs(a.astype(int) - b.astype(int))
        rows.append((f"{bs} clips per call", bs, t_b))
        print(f"batch {bs}: uint8 difference to one-per-call: max {d.max()}, share of values {float((d > 0).mean()):.1e}")
    print(f"{args.clips} clips of 13 latent frames (49 frames 64x96), {args.threads} torch thread(s), best of {args.repeats}")
    for name, _, t in rows:
        print(f"  {name:<28} {t:6.2f} s  {t / args.clips:5.2f} s/clip  x{t_one / t:4.1f}")

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
    print(f"  {'1 clip per call (slicing)':<28} {t_enc1:6.2f} s  {t_enc1 / args.clips:5.2f} s/clip  x 1.0")
    print(f"  {'4 clips per call':<28} {t_enc4:6.2f} s  {t_enc4 / args.clips:5.2f} s/clip  x{t_enc1 / t_enc4:4.1f}"
          f"   (latents differ by at most {float(np.abs(one - four).max()):.1e})")


if __name__ == "__main__":
    main()
