"""The synthetic world model's training step on a CPU: eager against torch.compile (inductor) and 1 against 2
threads, as ratios against eager at 1 thread run in the same process.

The step is the trainer's: the `synth-world` preset's model and objective (``resim.train.tasks.world_model.build_world``), wrapped
as the trainer wraps it on one process (``resim.train.distributed.wrap_model``: compile per block when on), a full
AdamW step with gradient clipping, on an in-memory batch of the preset's geometry (23 latent frames of 4 x 32 x 48,
3 of history; 64 text tokens). Each configuration times ``--steps`` steps after 3 warm-up steps (the compile
happens there; its cost is printed). On a shared machine run it twice: the ratios are what carries.

  PYTHONPATH=. python bench/cpu_train_step.py [--batch 8] [--steps 8] [--threads 1,2] [--compile off,on]
"""
from __future__ import annotations

import argparse
import time

import torch

from resim.train.data import Batch
from resim.train.distributed import init_distributed, wrap_model
from resim.train.presets import WORLD_PRESETS
from resim.train.tasks.world_model import build_world


def batch_of(b: int, frames: int, chw: tuple[int, int, int], seq: int, dim: int) -> Batch:
    g = torch.Generator().manual_seed(0)
    return Batch(latents=torch.randn(b, frames, *chw, generator=g),
                 prompt_table=torch.randn(4, seq, dim, generator=g),
                 prompt_index=torch.randint(0, 3, (b,), generator=g), null_index=torch.full((b,), 3),
                 trajectory=torch.randn(b, 8, 3, generator=g), has_trajectory=torch.ones(b, dtype=torch.bool),
                 command=torch.randint(0, 3, (b,), generator=g), source=["carla"] * b,
                 keys=[f"k{i}" for i in range(b)],
                 meta=[{"num_history_frames": 3, "num_frames": frames, "fps_hz": 5.0}] * b)


def run(threads: int, compile: bool, batch: int, steps: int, env) -> tuple[float, float]:
    torch.set_num_threads(threads)
    torch.manual_seed(0)
    mcfg = WORLD_PRESETS["synth-world"]["model"]
    model = build_world({k: v for k, v in mcfg.items() if k not in ("latent_hw", "latent_frames")}, device="cpu")
    lm, _ = wrap_model(model, env, parallel="none", compile=compile)
    opt = torch.optim.AdamW([p for p in lm.parameters() if p.requires_grad], lr=1e-4)
    chw = (model.cfg.in_channels, *mcfg["latent_hw"])
    data = batch_of(batch, mcfg["latent_frames"], chw, model.cfg.max_text_seq_length, model.cfg.text_embed_dim)

    def step():
        loss, _ = lm(data)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(lm.parameters(), 1.0)
        opt.step()
        opt.zero_grad(set_to_none=True)

    t0 = time.perf_counter()
    for _ in range(3):
        step()
    warm = time.perf_counter() - t0
    times = []
    for _ in range(steps):
        t0 = time.perf_counter()
        step()
        times.append(time.perf_counter() - t0)
    return sorted(times)[len(times) // 2], warm


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--steps", type=int, default=8)
    ap.add_argument("--threads", default="1,2")
    ap.add_argument("--compile", default="off,on")
    a = ap.parse_args()
    env = init_distributed(device="cpu")
    print(f"device: CPU, torch {torch.__version__}, batch {a.batch}, median of {a.steps} steps after 3 warm-up")
    base = None
    print("| threads | compile | step (s) | vs eager, 1 thread | warm-up (s) |")
    print("|---|---|---|---|---|")
    for th in [int(x) for x in a.threads.split(",")]:
        for c in [x == "on" for x in a.compile.split(",")]:
            s, warm = run(th, c, a.batch, a.steps, env)
            base = base or s
            print(f"| {th} | {'on' if c else 'off'} | {s:.3f} | {base / s:.2f}x | {warm:.1f} |", flush=True)


if __name__ == "__main__":
    main()
