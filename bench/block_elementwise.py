"""The memory traffic of one transformer block outside matmul and attention: the block as it is, the block as
it was, and diffusers' ``CogVideoXBlock``, with the same weights, in the same process.

The GPU profile of a training step (docs/benchmarks.md, "GPU") found half the kernel time outside matmul and
attention: LayerNorm, casts, copies, the elementwise AdaLN and gating. Kernels like these are bound by the
bytes they write and read, so this bench counts, for one forward and backward of one block:

* ``non-matmul MB written``: the bytes every aten op other than matmul/attention writes (its outputs), counted
  with a ``TorchDispatchMode``: a device-independent measure of the elementwise traffic;
* ``ops``: how many aten ops run (each is at least one kernel launch in eager mode);
* ``saved MB``: the activations kept for the backward (distinct storages, parameters excluded);
* seconds per forward + backward (median, the variants alternating) and the ratio to the block as it was.

The three variants take the same input and give the same output (the largest difference is printed): the
changes remove copies, not arithmetic. "before" is the block's forward as it was before the gate and cast
changes (kept here, verbatim, as the baseline); diffusers' block takes one AdaLN embedding per sample (no
per-frame gate), so it shows what the field's eager code costs.

    PYTHONPATH=. python bench/block_elementwise.py                          # CPU, fp32 and bf16 autocast
    PYTHONPATH=. python bench/block_elementwise.py --dim 1920 --heads 30 --frames 13 --hw 16x28 --device cuda
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from resim.models.world.blocks import DiTBlock
from resim.train.traffic import SavedActivations, Traffic


class _BeforeBlock(DiTBlock):
    """The block's forward before this change (commit a4b23ad): the video gate expanded to (B, T*n, D) and the
    modulated norm output left in the residual's dtype."""

    @staticmethod
    def _norm(m, video, text, temb_frames, temb_text):
        b, tn, d = video.shape
        t = temb_frames.shape[1]
        shift, scale, gate = m.linear(m.silu(temb_frames)).chunk(6, dim=-1)[:3]
        v = m.norm(video).view(b, t, tn // t, d) * (1 + scale[:, :, None]) + shift[:, :, None]
        v_gate = gate[:, :, None].expand(b, t, tn // t, d).reshape(b, tn, d)
        e_shift, e_scale, e_gate = m.linear(m.silu(temb_text)).chunk(6, dim=-1)[3:]
        e = m.norm(text) * (1 + e_scale[:, None]) + e_shift[:, None]
        return v.reshape(b, tn, d), e, v_gate, e_gate[:, None]

    def forward(self, video, text, temb_frames, temb_text, mask=None, past_kv=None, return_kv=False):
        nv, ne, gv, ge = self._norm(self.norm1, video, text, temb_frames, temb_text)
        x = torch.cat([ne, nv], dim=1)
        a, kv = self.attn1(x, mask=mask)
        L = ne.shape[1]
        video = video + gv * a[:, L:]
        text = text + ge * a[:, :L]
        nv, ne, gv, ge = self._norm(self.norm2, video, text, temb_frames, temb_text)
        x = torch.cat([ne, nv], dim=1)
        f = self.ff(x)
        video = video + gv * f[:, L:]
        text = text + ge * f[:, :L]
        return video, text, kv


def _run(block, inputs, diffusers_api: bool):
    video, text, temb_frames, temb_text = inputs
    if diffusers_api:
        v, e = block(video, text, temb_text)
    else:
        v, e, _ = block(video, text, temb_frames, temb_text, None)
    return v, e


def _measure(block, inputs, diffusers_api, autocast_dtype, device):
    saved = SavedActivations(block.parameters())
    ctx = torch.autocast(device.type, dtype=autocast_dtype) if autocast_dtype else torch.autocast(device.type, enabled=False)
    with Traffic() as mode, ctx, torch.autograd.graph.saved_tensors_hooks(*saved.hooks()):
        v, e = _run(block, inputs, diffusers_api)
        (v.float().square().mean() + e.float().square().mean()).backward()
    block.zero_grad(set_to_none=True)
    return mode, saved.bytes, v.detach().float()


def _timed(block, inputs, diffusers_api, autocast_dtype, device):
    ctx = torch.autocast(device.type, dtype=autocast_dtype) if autocast_dtype else torch.autocast(device.type, enabled=False)
    if device.type == "cuda":
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    with ctx:
        v, e = _run(block, inputs, diffusers_api)
        (v.float().square().mean() + e.float().square().mean()).backward()
    if device.type == "cuda":
        torch.cuda.synchronize()
    block.zero_grad(set_to_none=True)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dim", type=int, default=384, help="hidden width (CogVideoX-2B: 1920)")
    ap.add_argument("--heads", type=int, default=6, help="attention heads of 64 (CogVideoX-2B: 30)")
    ap.add_argument("--frames", type=int, default=4, help="latent frames T (per-frame AdaLN)")
    ap.add_argument("--hw", default="8x12", help="tokens per frame as HxW after patching (default 8x12)")
    ap.add_argument("--text", type=int, default=32, help="text tokens (CogVideoX: 226)")
    ap.add_argument("--batch", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--precision", default="fp32,bf16", help="comma list of fp32 (no autocast) and bf16 (autocast)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    dev = torch.device(args.device)
    h, w = (int(x) for x in args.hw.split("x"))
    d, tdim = args.dim, 512
    torch.manual_seed(0)
    now = DiTBlock(d, args.heads, d // args.heads, tdim).to(dev)
    before = _BeforeBlock(d, args.heads, d // args.heads, tdim).to(dev)
    before.load_state_dict(now.state_dict())
    variants = {"before (baseline)": (before, False), "now": (now, False)}
    try:   # optional: the GPU machines of scripts/gpu_realtime.sh have no diffusers; the two blocks above suffice
        from diffusers.models.transformers.cogvideox_transformer_3d import CogVideoXBlock
        ref = CogVideoXBlock(d, args.heads, d // args.heads, tdim, attention_bias=True).to(dev)
        ref.load_state_dict(now.state_dict(), strict=True)
        variants["diffusers CogVideoXBlock"] = (ref, True)
    except ImportError:
        print("(diffusers is not installed: its block is left out)")

    g = torch.Generator().manual_seed(1)
    video = torch.randn(args.batch, args.frames * h * w, d, generator=g).to(dev)
    text = torch.randn(args.batch, args.text, d, generator=g).to(dev)
    temb = torch.randn(args.batch, tdim, generator=g).to(dev)
    inputs = (video, text, temb[:, None].expand(-1, args.frames, -1), temb)   # every frame the sample's level

    print(f"one block, dim {d}, {args.heads} heads, batch {args.batch}, {args.frames} frames x {h}x{w} tokens + "
          f"{args.text} text ({args.batch * (args.frames * h * w + args.text)} tokens), {dev}, "
          f"torch {torch.__version__}, {args.threads} threads")
    for prec in args.precision.split(","):
        ac = {"fp32": None, "bf16": torch.bfloat16}[prec]
        rows, outs = {}, {}
        for name, (blk, dapi) in variants.items():
            mode, saved, out = _measure(blk, inputs, dapi, ac, dev)
            rows[name] = [mode.bytes["other"] / 2**20, sum(mode.ops.values()) - mode.ops["view"], saved / 2**20]
            outs[name] = out
        times = {n: [] for n in variants}
        for _ in range(args.repeats + 1):                 # the first round warms up, then alternate
            for name, (blk, dapi) in variants.items():
                times[name].append(_timed(blk, inputs, dapi, ac, dev))
        base = "before (baseline)"
        med = {n: statistics.median(t[1:]) for n, t in times.items()}
        print(f"\n{prec}{' autocast' if ac else ''}:")
        print(f"  {'variant':26s} {'non-matmul MB written':>21s} {'ops':>5s} {'saved MB':>9s} {'s/step':>8s} "
              f"{'vs before':>9s} {'max |out - before|':>19s}")
        for name, (mb, ops, sv) in rows.items():
            diff = (outs[name] - outs[base]).abs().max().item()
            print(f"  {name:26s} {mb:21.1f} {ops:5d} {sv:9.1f} {med[name]:8.4f} {med[base] / med[name]:8.2f}x "
                  f"{diff:19.2e}")


if __name__ == "__main__":
    main()
