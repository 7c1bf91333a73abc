"""Seconds to simulate one 4-s 512x896 clip with a CogVideoX-2B-size world model on a GPU (benchmark).

Random weights (the timing does not depend on them), bf16, 50 DDIM steps, CFG on (both branches batched into
one forward of 2 samples), ReSim setting: 3 history latent frames (9 px frames) + 10 future latent frames
(40 px frames = 4 s at 10 Hz) denoised together; KV cache on and off. Optionally frame-by-frame (--chunk 1).
Anchors: ReSim reports 120 s per 4-s clip on one A100; CogVideoX-2B itself takes ~45 s for a 6-s clip on an
H100 (diffusers, 50 steps, CFG). Target: <= 20 s on an H100/H200.

Model forward only (the VAE decode and T5 are not timed; the T5 embedding is random). Needs CUDA.

  PYTHONPATH=. python bench/rollout_gpu_cogvideox2b.py [--steps 50] [--chunk 10] [--repeats 2] [--compile]
                                                       [--compile-mode default|reduce-overhead]
                                                       [--attention sdpa,flex]
  PYTHONPATH=. python bench/rollout_gpu_cogvideox2b.py --sdpa-probe     # which SDPA kernel runs, then exit
  PYTHONPATH=. python bench/rollout_gpu_cogvideox2b.py --flex-probe     # model's attention: sdpa vs flex, exit

``--attention``: the model's attention backend(s) for the block-causal mask (``WorldModelConfig.attention_backend``;
comma-separated: each is timed on the same model in the same process, switched with
``WorldModel.set_attention_backend``). The flex backend compiles its kernel during the warm-up rollout (the
warm-up's seconds are printed; they are not in the timed rollout).

``--smoke-cpu``: the same code paths with the tiny preset on the CPU at a small size (checks this script, times
nothing meaningful), e.g. ``--smoke-cpu --height-px 64 --width-px 96 --steps 2 --repeats 1 --attention sdpa,flex``.

``--sdpa-probe``: for the model's own attention module (``resim.models.world.attention.Attention``, 30 heads x 64,
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
import torch.nn.functional as F
from torch.nn.attention import SDPBackend, sdpa_kernel
from torch.profiler import ProfilerActivity, profile

from resim.diffusion.guidance import guidance_preset
from resim.models.world.attention import Attention, block_causal_block_mask, block_causal_mask
from resim.models.world.config import preset
from resim.models.world.dit import WorldModel
from resim.models.world.flex import flex_block_attention
from resim.sample.compile import COMPILE_MODES, compile_blocks
from resim.sample.rollout import Condition, RolloutConfig, rollout


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--chunk", type=int, default=10, help="latent frames denoised together (10 ReSim, 1 Vid2World)")
    ap.add_argument("--height-px", type=int, default=512)
    ap.add_argument("--width-px", type=int, default=896)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--modes", default="on,off", help="KV-cache modes to time, comma-separated")
    ap.add_argument("--compile", action="store_true",
                    help="torch.compile the transformer blocks as resim sample does (its default on CUDA)")
    ap.add_argument("--compile-mode", default="default", choices=COMPILE_MODES,
                    help="torch.compile mode (reduce-overhead: CUDA graphs)")
    ap.add_argument("--eager-baseline", action="store_true",
                    help="with --compile: time the eager model first, in the same process, and print the ratio")
    ap.add_argument("--no-guidance", action="store_true",
                    help="conditional branch only (one sample per forward): a distilled student's sampler, with "
                         "e.g. --steps 4 (docs/distill.md); target 4 s per 4-s clip")
    ap.add_argument("--attention", default="sdpa", help="attention backend(s) to time: sdpa, flex or sdpa,flex")
    ap.add_argument("--sdpa-probe", action="store_true", help="report which SDPA kernel runs (see above) and exit")
    ap.add_argument("--flex-probe", action="store_true",
                    help="time the model's Attention module with the sdpa vs the flex backend's mask, then exit")
    ap.add_argument("--smoke-cpu", action="store_true", help="tiny preset on the CPU: check the script (see above)")
    args = ap.parse_args()
    dev = torch.device("cpu" if args.smoke_cpu else "cuda")
    preset_name = "tiny" if args.smoke_cpu else "cogvideox-2b"
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("this benchmark needs a CUDA GPU (none found); the CPU benchmark is bench/rollout_kv_cache.py")
    if args.sdpa_probe:
        sdpa_probe()
        return
    if args.flex_probe:
        flex_probe(dev, preset_name)
        return
    backends = args.attention.split(",")
    for b in backends:
        if b not in ("sdpa", "flex"):
            raise SystemExit(f"--attention: unknown backend {b!r} (sdpa, flex)")

    cfg = preset(preset_name)
    torch.manual_seed(0)
    with dev:
        model = WorldModel(cfg)
    model = model.to(torch.bfloat16).eval().requires_grad_(False)
    n_params = sum(p.numel() for p in model.parameters())
    h, w = args.height_px // 8, args.width_px // 8
    g = torch.Generator().manual_seed(0)
    hist = torch.randn(1, 3, cfg.in_channels, h, w, generator=g).to(dev)
    text = torch.randn(1, cfg.max_text_seq_length, cfg.text_embed_dim, generator=g).to(dev, torch.bfloat16)
    cond = Condition(text=text, null_text=torch.zeros_like(text), trajectory=torch.randn(1, 8, 3).to(dev))
    tokens = (h // cfg.patch_size) * (w // cfg.patch_size)
    print(f"device: {_device_name(dev)}, torch {torch.__version__}; WorldModel {preset_name} size "
          f"({n_params / 1e9:.2f} B params, random, bf16); {args.height_px}x{args.width_px} px -> latents {h}x{w}, "
          f"{tokens} tokens/frame, 3 + 10 latent frames ({13 * tokens + cfg.max_text_seq_length} tokens), "
          f"{args.steps} steps, {'no CFG (1 sample/forward)' if args.no_guidance else 'CFG batched (2 samples/forward)'}, "
          f"chunk {args.chunk}")
    guidance = "none" if args.no_guidance else "resim"
    target_s = 4.0 if args.no_guidance else 20.0     # issue targets: the student real time, the teacher 20 s
    def time_all(tag: str) -> dict:
        results = {}
        for backend in backends:
            model.set_attention_backend(backend)
            for mode in args.modes.split(","):
                rc = RolloutConfig(num_steps=args.steps, history_frames=3, frames_per_round=10,
                                   chunk_frames=args.chunk, kv_cache=mode, guidance=guidance_preset(guidance))
                warm = RolloutConfig(num_steps=2, history_frames=3, frames_per_round=10, chunk_frames=args.chunk,
                                     kv_cache=mode, guidance=guidance_preset(guidance))
                t0 = time.perf_counter()
                rollout(model, hist, cond, 10, warm)               # warm-up (kernels, allocator, compile)
                _sync(dev)
                warm_s = time.perf_counter() - t0
                if dev.type == "cuda":
                    torch.cuda.reset_peak_memory_stats()
                best = float("inf")
                for _ in range(args.repeats):
                    t0 = time.perf_counter()
                    res = rollout(model, hist, cond, 10, rc, seed=0)
                    _sync(dev)
                    best = min(best, time.perf_counter() - t0)
                results[(backend, mode)] = (best, res.latents.float())
                print(f"[{tag}] attention {backend:4s}, KV cache {mode:3s}: {best:7.2f} s per 4-s clip = "
                      f"{40 / best:.1f} generated frames/s ({res.model_forwards} forwards, "
                      f"{best / res.model_forwards * 1e3:.0f} ms per forward, "
                      f"peak {_peak_gib(dev):.1f} GiB; 2-step warm-up {warm_s:.1f} s); "
                      f"vs ReSim's 120 s on an A100: {120 / best:.1f}x; target {target_s:g} s: "
                      f"{'met' if best <= target_s else 'NOT met'}",
                      flush=True)
        return results

    results = {} if args.compile and not args.eager_baseline else time_all("eager")
    if args.compile:   # what `resim sample` does on CUDA by default (resim/sample/compile.py)
        eager = results
        compile_blocks(model, mode=args.compile_mode)
        results = time_all(f"compiled, {args.compile_mode}")
        for key in eager:
            print(f"attention {key[0]}, KV cache {key[1]}: compiled blocks ({args.compile_mode}) speed-up over eager "
                  f"{eager[key][0] / results[key][0]:.2f}x (same process)")
    for backend in backends:
        if (backend, "on") in results and (backend, "off") in results:
            print(f"attention {backend}: KV cache speed-up {results[(backend, 'off')][0] / results[(backend, 'on')][0]:.2f}x")
    for mode in args.modes.split(","):
        if ("sdpa", mode) in results and ("flex", mode) in results:
            (ts, ls), (tf, lf) = results[("sdpa", mode)], results[("flex", mode)]
            print(f"KV cache {mode}: flex speed-up over sdpa {ts / tf:.2f}x (same process); final latents "
                  f"max |flex - sdpa| = {(lf - ls).abs().max().item():.3g} (max |sdpa| {ls.abs().max().item():.3g}; "
                  f"bf16, {args.steps} steps of random weights: rounding differences grow, not a correctness test)")


def _sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize()


def _peak_gib(dev: torch.device) -> float:
    return torch.cuda.max_memory_allocated() / 2**30 if dev.type == "cuda" else float("nan")


def _device_name(dev: torch.device) -> str:
    return torch.cuda.get_device_name(dev) if dev.type == "cuda" else "CPU (smoke run)"


def _cuda_ms(fn, iters: int = 3, dev: torch.device | None = None) -> float:
    if dev is not None and dev.type != "cuda":             # smoke runs: wall clock
        fn()
        t0 = time.perf_counter()
        for _ in range(iters):
            fn()
        return (time.perf_counter() - t0) / iters * 1e3
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


def flex_probe(dev: torch.device, preset_name: str = "cogvideox-2b") -> None:
    """The model's ``Attention`` module (30 heads x 64, bf16, batch 2) with the mask each backend builds:
    the dense bool mask (sdpa) vs the cached ``BlockMask`` (flex, ``resim.models.world.flex``'s compiled call), for
    the uncached ReSim geometry and the cached one (10 new frames against text + 13 frames), at 256x448 and
    512x896. The flex path compiles static for its first shape, then once with dynamic lengths (torch's
    default), so every row after the first times the dynamic-shape kernel (compare: the static compile in
    ``--sdpa-probe``)."""
    cfg = preset(preset_name)
    torch.manual_seed(0)
    attn = Attention(cfg.hidden_dim, cfg.num_attention_heads, cfg.attention_head_dim).to(dev, torch.bfloat16)
    p, L, b, h, d = cfg.patch_size, cfg.max_text_seq_length, 2, cfg.num_attention_heads, cfg.attention_head_dim
    print(f"device: {_device_name(dev)}, torch {torch.__version__}", flush=True)
    for hp, wp in ((256, 448), (512, 896)) if dev.type == "cuda" else ((32, 48),):
        n = (hp // 8 // p) * (wp // 8 // p)
        for name, nf, prefix, text_q in (("uncached 13 frames", 13, 0, True), ("cached: 10 new vs 3 + text", 10, 3, False)):
            s_q = (L if text_q else 0) + nf * n
            s_k = L + (prefix + nf) * n
            x = torch.randn(b, s_q, cfg.hidden_dim, device=dev, dtype=torch.bfloat16)
            past = None if text_q else tuple(torch.randn(b, h, s_k - s_q, d, device=dev, dtype=torch.bfloat16)
                                             for _ in range(2))
            dense = block_causal_mask(L, n, nf, prefix, text_q, device=dev)
            t0 = time.perf_counter()
            bm = block_causal_block_mask(L, n, nf, prefix, text_q, device=dev)
            _sync(dev)
            build_ms = (time.perf_counter() - t0) * 1e3
            with torch.no_grad():
                ref = attn(x, mask=dense, past_kv=past)[0]
                t0 = time.perf_counter()
                out = attn(x, mask=bm, past_kv=past)[0]
                _sync(dev)
                first_s = time.perf_counter() - t0
                err = (out.float() - ref.float()).abs().max().item()
                ms_sdpa = _cuda_ms(lambda: attn(x, mask=dense, past_kv=past), dev=dev)
                ms_flex = _cuda_ms(lambda: attn(x, mask=bm, past_kv=past), dev=dev)
                q, k, v = (torch.randn(b, h, s, d, device=dev, dtype=torch.bfloat16) for s in (s_q, s_k, s_k))
                ms_k_sdpa = _cuda_ms(lambda: F.scaled_dot_product_attention(q, k, v, attn_mask=dense), dev=dev)
                ms_k_flex = _cuda_ms(lambda: flex_block_attention(q, k, v, bm), dev=dev)
            print(f"  {hp}x{wp} {name:27s} S_q {s_q:6d} S_k {s_k:6d}: module sdpa(bool mask) {ms_sdpa:7.2f} ms, "
                  f"module flex {ms_flex:7.2f} ms (x{ms_sdpa / ms_flex:.2f}; first call {first_s:.1f} s, BlockMask "
                  f"build {build_ms:.0f} ms, sparsity {bm.sparsity():.1f} %); attention call alone: sdpa {ms_k_sdpa:7.2f} "
                  f"ms, flex {ms_k_flex:7.2f} ms (x{ms_k_sdpa / ms_k_flex:.2f}); max |flex - sdpa| {err:.2e}",
                  flush=True)
            del x, past, dense, q, k, v
            if dev.type == "cuda":
                torch.cuda.empty_cache()


if __name__ == "__main__":
    main()
