"""Seconds to simulate one 4-s 512x896 clip with a CogVideoX-2B-size world model on a GPU (issue 9 benchmark).

Random weights (the timing does not depend on them), bf16, 50 DDIM steps, CFG on (both branches batched into
one forward of 2 samples), ReSim setting: 3 history latent frames (9 px frames) + 10 future latent frames
(40 px frames = 4 s at 10 Hz) denoised together; KV cache on and off. Optionally frame-by-frame (--chunk 1).
Anchors: ReSim reports 120 s per 4-s clip on one A100; CogVideoX-2B itself takes ~45 s for a 6-s clip on an
H100 (diffusers, 50 steps, CFG). Target from issue 9: <= 20 s on an H100/H200.

Model forward only (the VAE decode and T5 are not timed; the T5 embedding is random). Needs CUDA.

  PYTHONPATH=. python bench/rollout_gpu_cogvideox2b.py [--steps 50] [--chunk 10] [--repeats 2] [--compile]
  PYTHONPATH=. python bench/rollout_gpu_cogvideox2b.py --sdpa-probe     # which SDPA kernel runs, then exit

``--sdpa-probe``: for the model's own attention module (``training.models.attention.Attention``, 30 heads x 64,
bf16, batch 2 = CFG) at 256x448 and 512x896 (13 latent frames + 226 text tokens), with no mask and with the
block-causal mask, it (1) profiles one forward (and one forward+backward at 256x448) with the default SDPA
dispatch and prints the CUDA kernels that ran, and (2) times ``F.scaled_dot_product_attention`` restricted to
each backend (flash / efficient / cuDNN / math) with CUDA events, reporting "not eligible" where the backend
refuses the inputs, and (3) times the alternative, ``flex_attention`` with the same pattern as a BlockMask
(compiled; checked against SDPA with the mask). Ratios are against the default dispatch without the mask, in
the same process. Results (H100, 2026-11-24): docs/benchmarks.md, "GPU".
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
    ap.add_argument("--sdpa-probe", action="store_true", help="report which SDPA kernel runs (see above) and exit")
    args = ap.parse_args()
    if not torch.cuda.is_available():
        raise SystemExit("this benchmark needs a CUDA GPU (none found); the CPU benchmark is bench/rollout_kv_cache.py")
    if args.sdpa_probe:
        sdpa_probe()
        return

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
              f"{best / res.model_forwards * 1e3:.0f} ms per forward, "
              f"peak {torch.cuda.max_memory_allocated() / 2**30:.1f} GiB); vs ReSim's 120 s on an A100: "
              f"{120 / best:.1f}x; target 20 s: {'met' if best <= 20 else 'NOT met'}")
    if "on" in results and "off" in results:
        print(f"KV cache speed-up: {results['off'] / results['on']:.2f}x")


def _cuda_ms(fn, iters: int = 3) -> float:
    fn()                                                   # warm-up (and eligibility check)
    torch.cuda.synchronize()
    start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    start.record()
    for _ in range(iters):
        fn()
    end.record()
    torch.cuda.synchronize()
    return start.elapsed_time(end) / iters


def _attention_kernels(prof) -> list[str]:
    """Names (and CUDA ms) of the kernels that look like attention (flash / fmha / cudnn sdpa / softmax / bmm)."""
    keys = ("flash", "fmha", "attention", "sdpa", "cudnn", "softmax", "bmm", "cutlass")
    out = []
    for e in prof.key_averages():
        name = e.key
        dev_us = getattr(e, "device_time_total", None) or getattr(e, "cuda_time_total", 0)
        if dev_us and any(k in name.lower() for k in keys) and not name.startswith("aten::"):
            out.append(f"{name[:110]} ({dev_us / 1e3:.1f} ms)")
    return out


def sdpa_probe() -> None:
    import torch.nn.functional as F
    from torch.nn.attention import SDPBackend, sdpa_kernel
    from torch.profiler import ProfilerActivity, profile

    from training.models.attention import Attention, block_causal_mask
    from training.models.config import preset

    cfg = preset("cogvideox-2b")
    dev = torch.device("cuda")
    print(f"device: {torch.cuda.get_device_name(0)}, torch {torch.__version__}; sdp flags: "
          f"flash={torch.backends.cuda.flash_sdp_enabled()} mem_efficient={torch.backends.cuda.mem_efficient_sdp_enabled()} "
          f"cudnn={torch.backends.cuda.cudnn_sdp_enabled()} math={torch.backends.cuda.math_sdp_enabled()}", flush=True)
    torch.manual_seed(0)
    attn = Attention(cfg.hidden_dim, cfg.num_attention_heads, cfg.attention_head_dim).to(dev, torch.bfloat16)
    p, L, nf, b = cfg.patch_size, cfg.max_text_seq_length, 13, 2
    backends = [("flash", SDPBackend.FLASH_ATTENTION), ("efficient", SDPBackend.EFFICIENT_ATTENTION),
                ("cudnn", SDPBackend.CUDNN_ATTENTION), ("math", SDPBackend.MATH)]
    for hp, wp in ((256, 448), (512, 896)):
        n = (hp // 8 // p) * (wp // 8 // p)
        s = L + nf * n
        x = torch.randn(b, s, cfg.hidden_dim, device=dev, dtype=torch.bfloat16)
        mask = block_causal_mask(L, n, nf, device=dev)
        print(f"--- {hp}x{wp}: S = {s} tokens ({n} per frame), batch {b}, {cfg.num_attention_heads} heads x "
              f"{cfg.attention_head_dim}; mask {tuple(mask.shape)} bool, {mask.float().mean().item():.3f} True",
              flush=True)
        for mname, m in (("no mask", None), ("block-causal mask", mask)):
            with torch.no_grad(), profile(activities=[ProfilerActivity.CUDA]) as prof:
                attn(x, mask=m)
                torch.cuda.synchronize()
            print(f"  forward, default dispatch, {mname}: " + "; ".join(_attention_kernels(prof)), flush=True)
            if hp == 256:
                xg = x.detach().requires_grad_(True)
                with profile(activities=[ProfilerActivity.CUDA]) as prof:
                    attn(xg, mask=m)[0].float().sum().backward()
                    torch.cuda.synchronize()
                print(f"  forward+backward, default dispatch, {mname}: " + "; ".join(_attention_kernels(prof)),
                      flush=True)
        h, d = cfg.num_attention_heads, cfg.attention_head_dim
        q, k, v = (torch.randn(b, h, s, d, device=dev, dtype=torch.bfloat16) for _ in range(3))
        base = None
        for mname, m in (("no mask", None), ("block-causal mask", mask)):
            for bname, be in [("default", None)] + backends:
                if bname == "math" and hp == 512:
                    print(f"  sdpa {mname:17s} {bname:9s}: skipped (would materialise {b}x{h}x{s}x{s} scores)")
                    continue
                def call(be=be, m=m):
                    if be is None:
                        return F.scaled_dot_product_attention(q, k, v, attn_mask=m)
                    with sdpa_kernel([be]):
                        return F.scaled_dot_product_attention(q, k, v, attn_mask=m)
                try:
                    with torch.no_grad():
                        ms = _cuda_ms(call)
                except (RuntimeError, torch.OutOfMemoryError) as e:
                    msg = str(e).strip().splitlines()[0][:120] if str(e).strip() else type(e).__name__
                    print(f"  sdpa {mname:17s} {bname:9s}: not eligible / failed ({type(e).__name__}: {msg})")
                    continue
                base = base or ms
                print(f"  sdpa {mname:17s} {bname:9s}: {ms:8.2f} ms  (x{ms / base:.2f} vs default, no mask)", flush=True)
        _flex_probe(q, k, v, mask, L, n, nf, base)
        del q, k, v, x, mask
        torch.cuda.empty_cache()


def _flex_probe(q, k, v, mask, text_len: int, n: int, nf: int, base: float) -> None:
    """The alternative the docs name: ``flex_attention`` with the same block-causal pattern as a BlockMask
    (fully masked 128x128 tiles skipped), compiled; checked against SDPA with the boolean mask."""
    import torch.nn.functional as F
    try:
        from torch.nn.attention.flex_attention import create_block_mask, flex_attention

        dev = q.device
        frame_id = torch.cat([torch.full((text_len,), -1, device=dev),
                              torch.arange(nf, device=dev).repeat_interleave(n)])

        def mask_mod(b, h, q_idx, kv_idx):
            return frame_id[kv_idx] <= frame_id[q_idx]

        s = q.shape[2]
        bm = create_block_mask(mask_mod, None, None, s, s, device=dev)
        flex = torch.compile(flex_attention, dynamic=False)
        t0 = time.perf_counter()
        with torch.no_grad():
            out = flex(q, k, v, block_mask=bm)
            torch.cuda.synchronize()
            compile_s = time.perf_counter() - t0
            ref = F.scaled_dot_product_attention(q, k, v, attn_mask=mask)
            err = (out.float() - ref.float()).abs().max().item()
            ms = _cuda_ms(lambda: flex(q, k, v, block_mask=bm))
        print(f"  flex_attention block mask (sparsity {bm.sparsity():.1f} %, compile {compile_s:.0f} s): {ms:8.2f} ms  "
              f"(x{ms / base:.2f} vs default, no mask); max |flex - sdpa(mask)| = {err:.2e}", flush=True)
    except Exception as e:                                  # report, do not hide: the probe is diagnostic
        print(f"  flex_attention: failed ({type(e).__name__}: {str(e).strip().splitlines()[0][:160] if str(e).strip() else ''})",
              flush=True)


if __name__ == "__main__":
    main()
