"""Static vs dynamic-shape ``torch.compile`` of ``flex_attention`` at the rollout's 512x896 geometries (CUDA).

The flex backend (``resim/models/world/flex.py``) compiles with torch's default ``dynamic=None``: the first shape
compiles static, and after a shape change dynamo recompiles once with symbolic lengths (so frame-by-frame
rollouts, one key length per round, do not hit dynamo's recompile limit). This measures what that costs per
call: ``static`` compiles every geometry separately (``dynamic=False``); ``default`` is the model's setting.
Geometries (bf16, batch 2 = CFG, 30 heads x 64, 226 text tokens, 1,792 tokens per frame): A = uncached, 13
frames with text queries (23,522 x 23,522); B = KV-cached chunk, 10 new frames against text + 13 frames
(17,920 x 23,522). Order A, B, A: in ``default`` the second A runs the dynamic kernel compiled for B.
Results (H100, 2026-11-24): docs/benchmarks.md, "flex_attention backend".

    PYTHONPATH=. python bench/flex_compile_modes.py static
    PYTHONPATH=. python bench/flex_compile_modes.py default
"""
import sys
import time
from pathlib import Path

import torch
from torch.nn.attention.flex_attention import flex_attention

from resim.models.world.attention import block_causal_block_mask

sys.path.insert(0, str(Path(__file__).resolve().parent))
from rollout_gpu_cogvideox2b import _cuda_ms  # noqa: E402  (one CUDA-event timer for the bench scripts)


def main() -> None:
    mode = sys.argv[1] if len(sys.argv) > 1 else "default"
    if mode not in ("static", "default"):
        raise SystemExit("usage: flex_compile_modes.py static|default")
    if not torch.cuda.is_available():
        raise SystemExit("needs a CUDA GPU")
    fn = torch.compile(flex_attention, dynamic=False) if mode == "static" else torch.compile(flex_attention)
    L, n, b, h, d, dev = 226, 1792, 2, 30, 64, torch.device("cuda")
    geoms = {"A uncached 13f": (13, 0, True), "B cached 10 new": (10, 3, False)}
    for name in ["A uncached 13f", "B cached 10 new", "A uncached 13f"]:
        nf, pre, text_q = geoms[name]
        sq, sk = (L if text_q else 0) + nf * n, L + (pre + nf) * n
        q, k, v = (torch.randn(b, h, s, d, device=dev, dtype=torch.bfloat16) for s in (sq, sk, sk))
        bm = block_causal_block_mask(L, n, nf, pre, text_q, device=dev)
        with torch.no_grad():
            t0 = time.perf_counter()
            fn(q, k, v, block_mask=bm)
            torch.cuda.synchronize()
            first = time.perf_counter() - t0
            print(f"{mode:7s} {name}: {_cuda_ms(lambda: fn(q, k, v, block_mask=bm), iters=5):.2f} ms (first call {first:.1f} s)",
                  flush=True)


if __name__ == "__main__":
    main()
