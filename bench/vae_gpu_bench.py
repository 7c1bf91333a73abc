"""GPU throughput of the pipeline's VAE-encode stage with a CogVideoX-size VAE (random weights).

    PYTHONPATH=. python bench/vae_gpu_bench.py                 # all cases on cuda:0
    PYTHONPATH=. python bench/vae_gpu_bench.py --sizes 256x448 --dtypes bf16 --batch 1

Builds ``AutoencoderKLCogVideoX`` with CogVideoX-2b's real architecture (block_out_channels
128/256/256/512, 3 layers per block, 16 latent channels; ~215M params, of which the encoder runs here)
and times ``resim.media.encoders.VideoVAE.encode`` — the exact call the encode stage makes (posterior
sample x scaling factor) — on 49-frame clips at 256x448 and 512x896, fp16/bf16, with and without
slicing/tiling. Prints clips/s per GPU and the ratio against the first case measured in this process,
plus the published anchor (ReSim/CogVideoX-class encode: ~0.6-1.6 clips/s per A800 at 49x288x512).

Timed per iteration: host->device copy of the uint8 clip, encode, posterior sample, copy back to the host
(what the stage does per batch); not timed: model construction (random init on the CPU), warm-up iterations.
Needs a CUDA GPU; exits with a message otherwise. Results: docs/benchmarks.md ("GPU").
"""
from __future__ import annotations

import argparse
import gc
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from resim.media.encoders import VideoVAE  # noqa: E402

COGVIDEOX_2B_VAE = dict(
    in_channels=3, out_channels=3, latent_channels=16, block_out_channels=(128, 256, 256, 512),
    layers_per_block=3, norm_num_groups=32, temporal_compression_ratio=4,
    down_block_types=("CogVideoXDownBlock3D",) * 4, up_block_types=("CogVideoXUpBlock3D",) * 4,
    sample_height=480, sample_width=720, scaling_factor=1.15258426,
)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="256x448,512x896")
    ap.add_argument("--dtypes", default="bf16,fp16")
    ap.add_argument("--frames", type=int, default=49)
    ap.add_argument("--batch", type=int, default=1)
    ap.add_argument("--iters", type=int, default=5)
    ap.add_argument("--warmup", type=int, default=1)
    args = ap.parse_args()

    # after parsing: --help answers at once, and on a machine without the GPU stack (torch, diffusers)
    import torch
    from diffusers import AutoencoderKLCogVideoX

    if not torch.cuda.is_available():
        print("no CUDA GPU: this benchmark needs one (nothing measured)")
        return 2
    dev = torch.cuda.get_device_name(0)
    print(f"device: {dev}; torch {torch.__version__}", flush=True)
    results, base = [], None
    with tempfile.TemporaryDirectory() as tmp:
        AutoencoderKLCogVideoX(**COGVIDEOX_2B_VAE).save_config(tmp)      # config only: seeded random weights
        for size in args.sizes.split(","):
            h, w = map(int, size.split("x"))
            clips = np.random.default_rng(0).integers(0, 255, (args.batch, args.frames, h, w, 3), dtype=np.uint8)
            for dt in args.dtypes.split(","):
                for slicing, tiling in ((False, False), (True, True)):
                    vae = VideoVAE(tmp, dtype={"bf16": "bfloat16", "fp16": "float16"}[dt], device="cuda",
                                   slicing=slicing, tiling=tiling)
                    torch.cuda.reset_peak_memory_stats()
                    cps = mem = float("nan")
                    try:
                        for i in range(args.warmup):
                            vae.encode(clips, list(range(args.batch)))
                        torch.cuda.synchronize()
                        t0 = time.perf_counter()
                        for i in range(args.iters):
                            vae.encode(clips, list(range(args.batch)))
                        torch.cuda.synchronize()
                        dt_s = (time.perf_counter() - t0) / args.iters
                        cps = args.batch / dt_s
                        mem = torch.cuda.max_memory_allocated() / 2**30
                        status = "ok"
                    except torch.cuda.OutOfMemoryError:
                        status = "OOM"
                    if base is None and status == "ok":     # ratios against the first case that ran
                        base = cps
                    row = {"size": size, "frames": args.frames, "dtype": dt, "slicing_tiling": slicing,
                           "batch": args.batch, "clips_per_s": round(cps, 3), "peak_mem_gib": round(mem, 2),
                           "ratio_vs_first": round(cps / base, 3) if base else float("nan"), "status": status}
                    results.append(row)
                    print(json.dumps(row), flush=True)
                    del vae
                    gc.collect()
                    torch.cuda.empty_cache()
    print(f"device: {dev}; anchor: ~0.6-1.6 clips/s per A800 at 49x288x512 (published)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
