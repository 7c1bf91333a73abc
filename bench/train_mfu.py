"""GPU step time and MFU of the CogVideoX-2B-size world model (random weights), FSDP2 on one GPU, bf16.

For each resolution (256x448 and 512x896 pixels -> 32x56 and 64x112 latents, 49 frames -> 13 latent
frames) and activation checkpointing off/on: builds the DiT (preset ``cogvideox-2b``), wraps it the
way the trainer does (``resim.train.distributed.wrap_model``: AC, then ``fully_shard`` per block + root
with bf16 params / fp32 reduction, in a one-rank process group), and times full optimizer steps of
``model.loss(batch)`` (the real diffusion objective) on an in-memory batch. MFU = model training FLOPs
(``flops_per_sample``: 6 x block params x tokens + attention; recompute not counted) / step time /
peak bf16 FLOP/s. An out-of-memory configuration is reported as such, not skipped silently.

    PYTHONPATH=. python bench/train_mfu.py [--batch 1] [--steps 6] [--peak-tflops 989] [--sizes 32x56,64x112]
                                           [--ac off,on,2] [--compile off,on] [--adamw fused] [--attention sdpa,flex]
                                           [--profile] [--json FILE]

``--attention``: the model's attention backend(s) for the block-causal mask (``attention_backend`` override:
``sdpa`` = SDPA with the boolean mask, ``flex`` = flex_attention with a BlockMask, compiled; the compile happens
in the 2 warm-up steps). The FLOP count is the same for both (all S^2 scores, although flex skips ~45 % of the
tiles), so their MFU ratio is their step-time ratio.

``--ac``: ``off``, ``on`` (every block) or an integer k >= 2 (selective AC: every k-th block, the trainer's
``trainer.activation_checkpointing_every_blocks``). ``--compile off,on``: each block ``torch.compile``d as the
trainer does (``trainer.compile``), the compile happening in the warm-up steps. ``--adamw``: AdamW's kernel
(``optim.implementation``; fused is the trainer's default on CUDA). Each line ends with its step time against the
first configuration of the same size (the baseline), all in this process.

``--preset tiny --device cpu --sizes 4x6``: a smoke run of this script on a CPU (seconds; MFU meaningless).

``--profile``: one extra (untimed) step per configuration under torch.profiler, printing the GPU time shares
(attention / matmul / other) and the top kernels. Results (H100, 2026-11-24): docs/benchmarks.md, "GPU".

Peak dense bf16: H100 SXM 989 TFLOP/s, H200 989 TFLOP/s (same compute), A100 312.
"""
from __future__ import annotations

import argparse
import gc
import json
import time

import torch
from torch.profiler import ProfilerActivity, profile

from resim.train.data import Batch
from resim.train.distributed import init_distributed, wrap_model
from resim.train.tasks.world_model import build_world
from resim.train.trainer import adamw_kernel


def synthetic_batch(b: int, hw: tuple[int, int], device, seq: int = 226, dim: int = 4096):
    g = torch.Generator().manual_seed(0)
    return Batch(
        latents=torch.randn(b, 13, 16, *hw, generator=g).to(device),
        prompt_table=torch.randn(2, seq, dim, generator=g).to(device),
        prompt_index=torch.zeros(b, dtype=torch.long, device=device),
        null_index=torch.ones(b, dtype=torch.long, device=device),
        trajectory=torch.randn(b, 8, 3, generator=g).to(device),
        has_trajectory=torch.ones(b, dtype=torch.bool, device=device),
        command=torch.zeros(b, dtype=torch.long, device=device),
        source=["navsim"] * b, keys=[f"k{i}" for i in range(b)], meta=[{"num_history_frames": 9}] * b)


def _profile_step(step_fn) -> None:
    """One more step under torch.profiler: where the GPU time goes (top kernels, and matmul/attention/other)."""
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        step_fn()
        torch.cuda.synchronize()
    ev = [(e.key, getattr(e, "device_time_total", 0) or 0) for e in prof.key_averages()]
    ev = [(k, t) for k, t in ev if t > 0 and not k.startswith(("aten::", "autograd::", "FSDP", "ProfilerStep"))]
    total = sum(t for _, t in ev)
    groups = {"attention (sdpa)": ("sdpa", "fmha", "flash", "cudnn"), "matmul (gemm)": ("gemm", "xmma", "cutlass", "nvjet")}
    share = {g: 0.0 for g in groups}
    for k, t in ev:
        for g, keys in groups.items():
            if any(x in k.lower() for x in keys):
                share[g] += t
                break
    print(f"    profile of one step: {total / 1e3:.0f} ms of kernels; " +
          ", ".join(f"{g} {v / total:.0%}" for g, v in share.items()) + f", other {1 - sum(share.values()) / total:.0%}")
    for k, t in sorted(ev, key=lambda x: -x[1])[:12]:
        print(f"      {t / 1e3:8.1f} ms  {k[:120]}")


def _sync(device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def run_one(hw, ac: int, batch: int, steps: int, peak: float, env, profile: bool = False, attention: str = "sdpa",
            compile: bool = False, adamw: str = "fused", preset: str = "cogvideox-2b") -> dict:
    """``ac``: 0 = off, 1 = every block, k = every k-th block."""
    torch.manual_seed(0)
    cuda = env.device.type == "cuda"
    # built on the GPU (random init there; a 1.7B-parameter fp32 init on the CPU only costs start-up time)
    model = build_world({"preset": preset, "overrides": {"attention_backend": attention},
                         "objective": {"noise_mode": "resim_cond_aug", "num_history_frames": 3}}, device=env.device)
    lm, layout = wrap_model(model, env, parallel="fsdp", activation_checkpointing=ac > 0, bf16_params=cuda,
                            compile=compile, checkpoint_every_blocks=max(ac, 1))
    opt = torch.optim.AdamW([p for p in lm.parameters() if p.requires_grad], lr=1e-5,
                            **adamw_kernel(adamw, env.device))
    data = synthetic_batch(batch, hw, env.device, seq=model.cfg.max_text_seq_length, dim=model.cfg.text_embed_dim)
    flops = model.flops_per_sample(data) * batch
    times = []

    def step_fn():
        with torch.autocast(env.device.type, dtype=torch.bfloat16, enabled=cuda):
            loss, _ = lm(data)
        loss.float().backward()
        torch.nn.utils.clip_grad_norm_(lm.parameters(), 1.0)
        opt.step()
        opt.zero_grad(set_to_none=True)

    if cuda:
        torch.cuda.reset_peak_memory_stats()
    warm_s = 0.0
    for i in range(steps + 2):  # 2 warm-up steps (flex and --compile: their kernels compile here)
        _sync(env.device)
        t = time.perf_counter()
        step_fn()
        _sync(env.device)
        if i >= 2:
            times.append(time.perf_counter() - t)
        else:
            warm_s += time.perf_counter() - t
    if profile:
        _profile_step(step_fn)
    step = sorted(times)[len(times) // 2]
    return {"latent_hw": hw, "activation_checkpointing": ac, "attention": attention, "compile": compile,
            "adamw": adamw, "warmup_s": warm_s, "batch": batch, "step_s": step,
            "samples_per_s": batch / step, "tokens_per_s": model.tokens_per_sample(data) * batch / step,
            "tflops_per_s": flops / step / 1e12, "mfu": flops / step / (peak * 1e12),
            "max_mem_gib": torch.cuda.max_memory_allocated() / 2**30 if cuda else float("nan"), "layout": layout,
            "times": times, "flops_per_step": flops}


def _ac_setting(a: str) -> int:
    if a in ("off", "on"):
        return int(a == "on")
    if not a.isdigit() or int(a) < 2:
        raise SystemExit(f"--ac: {a!r} is not off, on or an integer k >= 2 (every k-th block)")
    return int(a)


def _ac_words(ac: int) -> str:
    return "off" if ac == 0 else "on" if ac == 1 else f"1/{ac}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batch", type=int, default=1)
    ap.add_argument("--steps", type=int, default=6)
    ap.add_argument("--peak-tflops", type=float, default=989.0)
    ap.add_argument("--json", help="also write the results here")
    ap.add_argument("--sizes", default="32x56,64x112", help="latent h x w, comma-separated (pixels / 8)")
    ap.add_argument("--ac", default="off,on", help="activation checkpointing settings: off, on, k (every k-th block)")
    ap.add_argument("--compile", default="off", help="off, on or off,on: torch.compile of each block")
    ap.add_argument("--adamw", default="fused", choices=["fused", "foreach", "for-loop"], help="AdamW's kernel")
    ap.add_argument("--attention", default="sdpa", help="attention backend(s) to run: sdpa, flex or sdpa,flex")
    ap.add_argument("--profile", action="store_true", help="profile one extra step per config (not timed)")
    ap.add_argument("--preset", default="cogvideox-2b", help="world-model preset (tiny: a CPU smoke run)")
    ap.add_argument("--device", default="cuda", choices=["cuda", "cpu"], help="cpu: a smoke run only")
    args = ap.parse_args()
    if args.device == "cuda" and not torch.cuda.is_available():
        raise SystemExit("bench/train_mfu.py needs a CUDA GPU (--device cpu --preset tiny for a smoke run)")

    env = init_distributed(device=args.device, force_group=True)
    if args.device == "cpu":
        print(f"device: CPU (smoke run) ; torch {torch.__version__}")
    else:
        torch.backends.cuda.matmul.allow_tf32 = True
        print(f"device: {torch.cuda.get_device_name()} ; torch {torch.__version__}; peak {args.peak_tflops} TFLOP/s bf16")
    backends = args.attention.split(",")
    for b in backends:
        if b not in ("sdpa", "flex"):
            raise SystemExit(f"--attention: unknown backend {b!r} (sdpa, flex)")
    compiles = [{"off": False, "on": True}[c] for c in args.compile.split(",")]
    results = []
    for hw in [tuple(map(int, s.split("x"))) for s in args.sizes.split(",")]:
        base = None
        for ac in [_ac_setting(a) for a in args.ac.split(",")]:
            for comp in compiles:
                for attention in backends:
                    try:
                        r = run_one(hw, ac, args.batch, args.steps, args.peak_tflops, env, args.profile, attention,
                                    comp, args.adamw, args.preset)
                    except torch.OutOfMemoryError:
                        r = {"latent_hw": hw, "activation_checkpointing": ac, "attention": attention,
                             "compile": comp, "batch": args.batch, "oom": True,
                             "max_mem_gib": torch.cuda.max_memory_allocated() / 2**30}
                    gc.collect()              # FSDP2 hooks keep module cycles: free the model before the next config
                    if env.device.type == "cuda":
                        torch.cuda.empty_cache()
                    results.append(r)
                    px = f"{hw[0] * 8}x{hw[1] * 8}"
                    head = (f"{px:>8s} AC {_ac_words(ac):3s} compile {'on ' if comp else 'off'} attention "
                            f"{attention:4s} AdamW {args.adamw} batch {args.batch}")
                    if r.get("oom"):
                        print(f"{head}: out of memory (peak {r['max_mem_gib']:.1f} GiB allocated before the failure)",
                              flush=True)
                        continue
                    base = base or r
                    print(f"{head}: step {r['step_s']:.3f} s (x{base['step_s'] / r['step_s']:.2f} of the first), "
                          f"{r['tokens_per_s']:,.0f} tokens/s, {r['tflops_per_s']:.1f} TFLOP/s, MFU {r['mfu']:.1%}, "
                          f"max mem {r['max_mem_gib']:.1f} GiB; step times {[round(x, 3) for x in r['times']]}; "
                          f"2 warm-up steps {r['warmup_s']:.1f} s; {r['layout']}", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)

if __name__ == "__main__":
    main()
