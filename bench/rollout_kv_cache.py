"""KV-cached vs uncached rollout time, CPU, tiny world model (benchmark).

Settings (latent frames; CogVideoX: 1 latent frame = 4 pixel frames at 10 Hz):
  * ReSim:        3 history + 10 future, the 10 denoised together, 50 DDIM steps, CFG (2B batch) on;
  * frame-by-frame (Vid2World): same 3 + 10, one frame at a time (context grows to 12), 50 steps, guidance on.
Uncached runs the history + chunk through the model at every step; cached runs the history once per round
(+ one forward per finished chunk) and only the chunk at every step. Both must give the same frames; the
script checks that and prints the max difference. Prints seconds (best of --repeats) and the ratio.

  PYTHONPATH=. python bench/rollout_kv_cache.py [--threads 1] [--repeats 3] [--steps 50] [--preset tiny]
"""
from __future__ import annotations

import argparse
import platform
import time

import torch

from resim.diffusion.guidance import guidance_preset
from resim.models.world.config import preset
from resim.models.world.dit import WorldModel
from resim.sample.rollout import Condition, RolloutConfig, rollout


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--preset", default="tiny", help="world-model preset (tiny: 2 layers, 32-d, 8x12 latents)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    torch.manual_seed(0)
    cfg = preset(args.preset)
    model = WorldModel(cfg).eval()
    h, w = cfg.sample_height, cfg.sample_width
    g = torch.Generator().manual_seed(0)
    hist = torch.randn(1, 3, cfg.in_channels, h, w, generator=g)
    cond = Condition(text=torch.randn(1, 16, cfg.text_embed_dim, generator=g),
                     null_text=torch.randn(1, 16, cfg.text_embed_dim, generator=g),
                     trajectory=torch.randn(1, 8, 3, generator=g))
    acts = torch.randn(1, 10, 3, generator=g)
    print(f"device: CPU ({platform.processor() or platform.machine()}), torch {torch.__version__}, "
          f"{args.threads} thread(s); model preset {args.preset!r} ({sum(p.numel() for p in model.parameters()):,} "
          f"params), latents {cfg.in_channels}x{h}x{w}, {args.steps} DDIM steps, guidance on (batched 2B)")
    settings = [("ReSim (3 hist + 10 future, c=10, CFG 7.5->1)", 10, "resim", None),
                ("frame-by-frame (3 + 10, c=1, action guidance 2.5)", 1, "vid2world", acts)]
    print(f"{'setting':52s} {'uncached s':>11s} {'cached s':>9s} {'ratio':>6s} {'calls u/c':>10s} {'max |diff|':>10s}")
    for name, chunk, gname, a in settings:
        times, outs, calls = {}, {}, {}
        for kv in ("off", "on"):
            rc = RolloutConfig(num_steps=args.steps, history_frames=3, frames_per_round=10, chunk_frames=chunk,
                               kv_cache=kv, guidance=guidance_preset(gname))
            best = float("inf")
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                res = rollout(model, hist, cond, 10, rc, seed=0, actions=a)
                best = min(best, time.perf_counter() - t0)
            times[kv], outs[kv], calls[kv] = best, res.latents, res.model_forwards
        diff = (outs["on"] - outs["off"]).abs().max().item()
        print(f"{name:52s} {times['off']:11.3f} {times['on']:9.3f} {times['off'] / times['on']:5.2f}x "
              f"{calls['off']:>4d}/{calls['on']:<5d} {diff:10.2e}")


if __name__ == "__main__":
    main()
