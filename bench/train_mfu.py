"""GPU step time and MFU of the CogVideoX-2B-size world model (random weights), FSDP2 on one GPU, bf16.

For each resolution (256x448 and 512x896 pixels -> 32x56 and 64x112 latents, 49 frames -> 13 latent
frames) and activation checkpointing off/on: builds the DiT (preset ``cogvideox-2b``), wraps it the
way the trainer does (``training.distributed.wrap_model``: AC, then ``fully_shard`` per block + root
with bf16 params / fp32 reduction, in a one-rank process group), and times full optimizer steps of
``model.loss(batch)`` (the real diffusion objective) on an in-memory batch. MFU = model training FLOPs
(``flops_per_sample``: 6 x block params x tokens + attention; recompute not counted) / step time /
peak bf16 FLOP/s. An out-of-memory configuration is reported as such, not skipped silently.

    PYTHONPATH=. python bench/train_mfu.py [--batch 1] [--steps 6] [--peak-tflops 989] [--sizes 32x56,64x112]
                                           [--ac off,on] [--attention sdpa,flex] [--profile] [--json FILE]

``--attention``: the model's attention backend(s) for the block-causal mask (``attention_backend`` override:
``sdpa`` = SDPA with the boolean mask, ``flex`` = flex_attention with a BlockMask, compiled; the compile happens
in the 2 warm-up steps). The FLOP count is the same for both (all S^2 scores, although flex skips ~45 % of the
tiles), so their MFU ratio is their step-time ratio.

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

from training.data import Batch
from training.distributed import init_distributed, wrap_model
from training.world import build_world


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


def run_one(hw, ac: bool, batch: int, steps: int, peak: float, env, profile: bool = False,
            attention: str = "sdpa") -> dict:
    torch.manual_seed(0)
    # built on the GPU (random init there; a 1.7B-parameter fp32 init on the CPU only costs start-up time)
    model = build_world({"preset": "cogvideox-2b", "overrides": {"attention_backend": attention},
                         "objective": {"noise_mode": "resim_cond_aug", "num_history_frames": 3}}, device=env.device)
    lm, layout = wrap_model(model, env, parallel="fsdp", activation_checkpointing=ac, bf16_params=True)
    opt = torch.optim.AdamW([p for p in lm.parameters() if p.requires_grad], lr=1e-5, foreach=True)
    data = synthetic_batch(batch, hw, env.device)
    flops = model.flops_per_sample(data) * batch
    times = []

    def step_fn():
        with torch.autocast("cuda", dtype=torch.bfloat16):
            loss, _ = lm(data)
        loss.float().backward()
        torch.nn.utils.clip_grad_norm_(lm.parameters(), 1.0)
        opt.step()
        opt.zero_grad(set_to_none=True)

    torch.cuda.reset_peak_memory_stats()
    warm_s = 0.0
    for i in range(steps + 2):  # 2 warm-up steps (flex: its kernels compile here)
        torch.cuda.synchronize()
        t = time.perf_counter()
        step_fn()
        torch.cuda.synchronize()
        if i >= 2:
            times.append(time.perf_counter() - t)
        else:
            warm_s += time.perf_counter() - t
    if profile:
        _profile_step(step_fn)
    step = sorted(times)[len(times) // 2]
    return {"latent_hw": hw, "activation_checkpointing": ac, "attention": attention, "warmup_s": warm_s,
            "batch": batch, "step_s": step,
            "samples_per_s": batch / step, "tokens_per_s": model.tokens_per_sample(data) * batch / step,
            "tflops_per_s": flops / step / 1e12, "mfu": flops / step / (peak * 1e12),
            "max_mem_gib": torch.cuda.max_memory_allocated() / 2**30, "layout": layout, "times": times,
            "flops_per_step": flops}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batch", type=int, default=1)
    ap.add_argument("--steps", type=int, default=6)
    ap.add_argument("--peak-tflops", type=float, default=989.0)
    ap.add_argument("--json", help="also write the results here")
    ap.add_argument("--sizes", default="32x56,64x112", help="latent h x w, comma-separated (pixels / 8)")
    ap.add_argument("--ac", default="off,on", help="activation checkpointing settings to run")
    ap.add_argument("--attention", default="sdpa", help="attention backend(s) to run: sdpa, flex or sdpa,flex")
    ap.add_argument("--profile", action="store_true", help="profile one extra step per config (not timed)")
    args = ap.parse_args()
    if not torch.cuda.is_available():
        raise SystemExit("bench/train_mfu.py needs a CUDA GPU")

    env = init_distributed(force_group=True)
    torch.backends.cuda.matmul.allow_tf32 = True
    print(f"device: {torch.cuda.get_device_name()} ; torch {torch.__version__}; peak {args.peak_tflops} TFLOP/s bf16")
    backends = args.attention.split(",")
    for b in backends:
        if b not in ("sdpa", "flex"):
            raise SystemExit(f"--attention: unknown backend {b!r} (sdpa, flex)")
    results = []
    for hw in [tuple(map(int, s.split("x"))) for s in args.sizes.split(",")]:
        for ac in [{"off": False, "on": True}[a] for a in args.ac.split(",")]:
            for attention in backends:
                try:
                    r = run_one(hw, ac, args.batch, args.steps, args.peak_tflops, env, args.profile, attention)
                except torch.OutOfMemoryError:
                    r = {"latent_hw": hw, "activation_checkpointing": ac, "attention": attention, "batch": args.batch,
                         "oom": True, "max_mem_gib": torch.cuda.max_memory_allocated() / 2**30}
                gc.collect()              # FSDP2 hooks keep module cycles: free the model before the next config
                torch.cuda.empty_cache()
                results.append(r)
                px = f"{hw[0] * 8}x{hw[1] * 8}"
                head = f"{px:>8s} AC {'on ' if ac else 'off'} attention {attention:4s} batch {args.batch}"
                if r.get("oom"):
                    print(f"{head}: out of memory (peak {r['max_mem_gib']:.1f} GiB allocated before the failure)",
                          flush=True)
                else:
                    print(f"{head}: step {r['step_s']:.3f} s, {r['tokens_per_s']:,.0f} tokens/s, "
                          f"{r['tflops_per_s']:.0f} TFLOP/s, MFU {r['mfu']:.1%}, max mem {r['max_mem_gib']:.1f} GiB; "
                          f"step times {[round(x, 3) for x in r['times']]}; 2 warm-up steps {r['warmup_s']:.1f} s; "
                          f"{r['layout']}", flush=True)
    ok = [r for r in results if not r.get("oom")]
    for hw in {tuple(r["latent_hw"]) for r in ok}:
        for attention in backends:
            by_ac = {r["activation_checkpointing"]: r for r in ok
                     if tuple(r["latent_hw"]) == hw and r["attention"] == attention}
            if True in by_ac and False in by_ac:
                print(f"{hw[0] * 8}x{hw[1] * 8} attention {attention}: step time AC on / AC off = "
                      f"{by_ac[True]['step_s'] / by_ac[False]['step_s']:.2f}x (same process)")
        for ac in (False, True):
            by_att = {r["attention"]: r for r in ok if tuple(r["latent_hw"]) == hw and r["activation_checkpointing"] == ac}
            if "sdpa" in by_att and "flex" in by_att:
                print(f"{hw[0] * 8}x{hw[1] * 8} AC {'on' if ac else 'off'}: step time sdpa / flex = "
                      f"{by_att['sdpa']['step_s'] / by_att['flex']['step_s']:.2f}x (same process)")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
