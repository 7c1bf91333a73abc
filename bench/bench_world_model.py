"""World-model forward costs, as ratios against a baseline run in the same process.

1. block-causal mask vs no mask (same model, same input): the cost of the boolean SDPA mask;
2. KV-cache sampling step vs recomputing history: denoise 1 new latent frame given H history frames,
   either with the cached keys/values of text + history or by running all H + 1 frames.

Usage: PYTHONPATH=. python bench/bench_world_model.py [--preset small] [--frames 8] [--repeats 5]
Prints ms per forward and ratios; device and threads are printed too. CPU numbers say nothing about GPU
kernels (on CUDA the mask selects the memory-efficient SDPA kernel, not FlashAttention).
"""
from __future__ import annotations

import argparse
import time

import torch

from resim.models.world.config import preset
from resim.models.world.dit import WorldModel


def _time(fn, repeats: int) -> float:
    fn()  # warm-up
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="small")
    ap.add_argument("--frames", type=int, default=8, help="latent frames (history + 1 new)")
    ap.add_argument("--height", type=int, default=16)
    ap.add_argument("--width", type=int, default=28)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    dev = "cuda" if torch.cuda.is_available() else "cpu"
    torch.manual_seed(0)
    causal = WorldModel(preset(a.preset)).to(dev).eval()
    full = WorldModel(preset(a.preset, causal=False)).to(dev).eval()
    full.load_state_dict(causal.state_dict())
    cfg = causal.cfg
    b, f = 1, a.frames
    x = torch.randn(b, f, 16, a.height, a.width, device=dev)
    t = torch.randint(0, 1000, (b, f), device=dev)
    text = torch.randn(b, cfg.max_text_seq_length, cfg.text_embed_dim, device=dev)
    tokens = cfg.max_text_seq_length + f * (a.height // 2) * (a.width // 2)
    print(f"device={dev} threads={a.threads} preset={a.preset} frames={f} latent={a.height}x{a.width} tokens={tokens}")
    with torch.no_grad():
        t_nomask = _time(lambda: full(x, t, text), a.repeats)
        t_mask = _time(lambda: causal(x, t, text), a.repeats)
        _, cache = causal(x[:, :-1], t[:, :-1], text, return_kv_cache=True)
        t_recompute = t_mask  # one new frame without a cache = the full causal forward over all frames
        t_cached = _time(lambda: causal(x[:, -1:], t[:, -1:], None, kv_cache=cache), a.repeats)
    print(f"no mask (full attention)      {t_nomask:9.1f} ms   1.00x")
    print(f"block-causal mask             {t_mask:9.1f} ms   {t_mask / t_nomask:.2f}x")
    print(f"new frame, recompute history  {t_recompute:9.1f} ms   1.00x")
    print(f"new frame, KV cache           {t_cached:9.1f} ms   {t_cached / t_recompute:.2f}x "
          f"({t_recompute / t_cached:.1f}x faster per denoising step)")


if __name__ == "__main__":
    main()
