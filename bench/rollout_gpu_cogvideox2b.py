"""Seconds to simulate one 4-s 512x896 clip with a CogVideoX-2B-size world model on a GPU (issue 9 benchmark).

Random weights (the timing does not depend on them), bf16, 50 DDIM steps, CFG on (both branches batched into
one forward of 2 samples), ReSim setting: 3 history latent frames (9 px frames) + 10 future latent frames
(40 px frames = 4 s at 10 Hz) denoised together; KV cache on and off. Optionally frame-by-frame (--chunk 1).
Anchors: ReSim reports 120 s per 4-s clip on one A100; CogVideoX-2B itself takes ~45 s for a 6-s clip on an
H100 (diffusers, 50 steps, CFG). Target from issue 9: <= 20 s on an H100/H200.

Model forward only (the VAE decode and T5 are not timed; the T5 embedding is random). Needs CUDA.

  PYTHONPATH=. python bench/rollout_gpu_cogvideox2b.py [--steps 50] [--chunk 10] [--repeats 2] [--compile]
"""
from __future__ import annotations

import argparse
import time

import torch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--chunk", type=int, default=10, help="latent frames denoised together (10 ReSim, 1 Vid2World)")
    ap.add_argument("--height-px", type=int, default=512)
    ap.add_argument("--width-px", type=int, default=896)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--modes", default="on,off", help="KV-cache modes to time, comma-separated")
    ap.add_argument("--compile", action="store_true", help="torch.compile the transformer blocks")
    args = ap.parse_args()
    if not torch.cuda.is_available():
        raise SystemExit("this benchmark needs a CUDA GPU (none found); the CPU benchmark is bench/rollout_kv_cache.py")

    from training.models.config import preset
    from training.models.dit import WorldModel
    from training.sampling.guidance import guidance_preset
    from training.sampling.rollout import Condition, RolloutConfig, rollout

    dev = torch.device("cuda")
    cfg = preset("cogvideox-2b")
    torch.manual_seed(0)
    with dev:
        model = WorldModel(cfg)
    model = model.to(torch.bfloat16).eval().requires_grad_(False)
    if args.compile:
        for i, blk in enumerate(model.transformer_blocks):
            model.transformer_blocks[i] = torch.compile(blk, dynamic=True)
    n_params = sum(p.numel() for p in model.parameters())
    h, w = args.height_px // 8, args.width_px // 8
    g = torch.Generator().manual_seed(0)
    hist = torch.randn(1, 3, cfg.in_channels, h, w, generator=g).to(dev)
    text = torch.randn(1, cfg.max_text_seq_length, cfg.text_embed_dim, generator=g).to(dev, torch.bfloat16)
    cond = Condition(text=text, null_text=torch.zeros_like(text), trajectory=torch.randn(1, 8, 3).to(dev))
    tokens = (h // cfg.patch_size) * (w // cfg.patch_size)
    print(f"device: {torch.cuda.get_device_name(0)}, torch {torch.__version__}; WorldModel cogvideox-2b size "
          f"({n_params / 1e9:.2f} B params, random, bf16); {args.height_px}x{args.width_px} px -> latents {h}x{w}, "
          f"{tokens} tokens/frame, 3 + 10 latent frames ({13 * tokens + cfg.max_text_seq_length} tokens), "
          f"{args.steps} steps, CFG batched (2 samples/forward), chunk {args.chunk}")
    results = {}
    for mode in args.modes.split(","):
        rc = RolloutConfig(num_steps=args.steps, history_frames=3, frames_per_round=10, chunk_frames=args.chunk,
                           kv_cache=mode, guidance=guidance_preset("resim"))
        warm = RolloutConfig(num_steps=2, history_frames=3, frames_per_round=10, chunk_frames=args.chunk,
                             kv_cache=mode, guidance=guidance_preset("resim"))
        rollout(model, hist, cond, 10, warm)               # warm-up (kernels, allocator, compile)
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
        best = float("inf")
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            res = rollout(model, hist, cond, 10, rc, seed=0)
            torch.cuda.synchronize()
            best = min(best, time.perf_counter() - t0)
        results[mode] = best
        print(f"KV cache {mode:3s}: {best:7.2f} s per 4-s clip ({res.model_forwards} forwards, "
              f"peak {torch.cuda.max_memory_allocated() / 2**30:.1f} GiB); vs ReSim's 120 s on an A100: "
              f"{120 / best:.1f}x; target 20 s: {'met' if best <= 20 else 'NOT met'}")
    if "on" in results and "off" in results:
        print(f"KV cache speed-up: {results['off'] / results['on']:.2f}x")


if __name__ == "__main__":
    main()
