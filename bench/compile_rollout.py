"""Eager against compiled blocks (``resim/sample/compile.py``), one rollout each, same process, same inputs.

The baseline is the eager rollout; beside it the rollout with every transformer block ``torch.compile``d in
place (a second copy of the same weights; the two alternate, rollout by rollout, so that a shared machine's
changing load falls on both). Printed: the first compiled rollout (it compiles), the median seconds per rollout
and the ratio to eager, the number of graphs dynamo built, and the largest difference between the two rollouts' latents (the same
seed and inputs: rounding only). Histories and prompts are random tensors of the model's shapes: the time of a
rollout does not depend on their content.

    PYTHONPATH=. python bench/compile_rollout.py                          # the shipped synth-world, CPU, ReSim preset
    PYTHONPATH=. python bench/compile_rollout.py --preset vid2world       # frame by frame: the cache grows per chunk
    PYTHONPATH=. python bench/compile_rollout.py --checkpoint RUN --device cuda --mode reduce-overhead
"""
from __future__ import annotations

import argparse
import time

import torch

from resim.diffusion.guidance import guidance_preset
from resim.sample.compile import COMPILE_MODES, compile_blocks
from resim.sample.load import load_world_model
from resim.sample.rollout import ROLLOUT_PRESETS, Condition, RolloutConfig, rollout


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", default="synth-world", help="world-model run folder or shipped name")
    ap.add_argument("--preset", default="resim", choices=sorted(ROLLOUT_PRESETS))
    ap.add_argument("--steps", type=int, default=10, help="DDIM steps per chunk (default 10)")
    ap.add_argument("--future", type=int, default=10, help="latent frames to generate (default 10 = 4 s)")
    ap.add_argument("--batch", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--dtype", default="float32", choices=["float32", "bfloat16"])
    ap.add_argument("--mode", default="default", choices=COMPILE_MODES)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    dev = torch.device(args.device)
    model, _ = load_world_model(args.checkpoint, args.device, getattr(torch, args.dtype))
    c = model.cfg
    g = torch.Generator().manual_seed(0)
    hist = torch.randn(args.batch, 3, c.in_channels, c.sample_height, c.sample_width, generator=g).to(dev)
    text = torch.randn(args.batch, c.max_text_seq_length, c.text_embed_dim, generator=g).to(dev, next(model.parameters()).dtype)
    cond = Condition(text=text, null_text=torch.zeros_like(text))
    rc = RolloutConfig(**{**ROLLOUT_PRESETS[args.preset], "num_steps": args.steps},
                       guidance=guidance_preset(args.preset))

    def timed(m) -> tuple[float, torch.Tensor]:
        if dev.type == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        res = rollout(m, hist, cond, args.future, rc, seed=1)
        if dev.type == "cuda":
            torch.cuda.synchronize()
        return time.perf_counter() - t0, res.future

    # two copies of the same weights, one compiled; their rollouts alternate, so a load that comes and goes on a
    # shared machine falls on both alike
    compiled, _ = load_world_model(args.checkpoint, args.device, getattr(torch, args.dtype))
    compile_blocks(compiled, mode=args.mode)
    timed(model)                                        # warm-up: allocator, kernels
    t_first, _ = timed(compiled)                        # compiles
    t_eager, t_comp = [], []
    for _ in range(args.repeats):
        t, x_eager = timed(model)
        t_eager.append(t)
        t, x_comp = timed(compiled)
        t_comp.append(t)
    t_eager, t_comp = sorted(t_eager)[len(t_eager) // 2], sorted(t_comp)[len(t_comp) // 2]
    graphs = torch._dynamo.utils.counters["stats"]["unique_graphs"]
    diff = float((x_comp.float() - x_eager.float()).abs().max())
    print(f"{args.checkpoint}: {sum(p.numel() for p in model.parameters()) / 1e6:.1f} M parameters, "
          f"{len(model.transformer_blocks)} blocks; preset {args.preset} ({rc.chunk_frames}-frame chunks), "
          f"{args.steps} DDIM steps, {args.future} latent frames, batch {args.batch}, {args.dtype}, {dev}, "
          f"torch {torch.__version__}, {args.threads} thread(s); median of {args.repeats}, alternating")
    print(f"  eager (baseline)            {t_eager:8.3f} s per rollout   x1.00")
    print(f"  compiled, first rollout     {t_first:8.3f} s (compiles; {graphs} graph(s))")
    print(f"  compiled, mode {args.mode:<12} {t_comp:8.3f} s per rollout   x{t_eager / t_comp:.2f}   "
          f"max |latents - eager| {diff:.2e}")


if __name__ == "__main__":
    main()
