"""The ``flex_attention`` backend: attention under a ``BlockMask`` (compiled on CUDA, eager elsewhere).

Why a second backend (``WorldModelConfig.attention_backend = "flex"``): with the block-causal mask as a boolean
tensor, SDPA runs cuDNN attention with the mask as a dense bias, computing every tile; on an H100 the masked
call took 2.18x the unmasked one at 512x896 although the mask removes 46 % of the scores, and it was ~75 % of
an uncached forward. ``flex_attention`` with the same pattern as a ``BlockMask`` skips the fully masked
128x128 tiles and evaluates the mask only on tiles that straddle a frame boundary. Measured in the model on
an H100 (torch 2.11; docs/benchmarks.md, the sections of bench/rollout_gpu_cogvideox2b.py and
bench/train_mfu.py): a 4-s 512x896 rollout 1.29x faster (49.2 s vs 63.6 s), a 512x896 training step with
activation checkpointing 1.55x faster; no gain at 256x448 training. The mask itself is built in ``attention.py``
(:func:`resim.models.world.attention.block_causal_block_mask`, cached per geometry).

Compilation. flex_attention is only fast compiled: ``torch.compile`` generates one Triton kernel from the
``mask_mod``. Called eagerly, PyTorch runs an unfused reference implementation that materialises the
``(B, H, S_q, S_k)`` scores: correct, but slow and O(S^2) in memory (at 512x896 far beyond any GPU). So:

* CUDA: ``torch.compile(flex_attention)``, created once per process on first use, with torch's default
  ``dynamic=None``: the first shape compiles static; after a shape change dynamo recompiles once with symbolic
  lengths. A rollout whose key length grows every round (frame by frame with a KV cache: one geometry per
  round) thus compiles about twice instead of once per geometry; past dynamo's recompile limit (8) it would
  silently fall back to the eager path above.
* inside an outer ``torch.compile`` region (e.g. compiled blocks): plain ``flex_attention``; the outer compile
  traces it.
* CPU and other devices: eager. Equal to SDPA within fp32 rounding (tests/models/test_flex_attention.py) but
  slower than SDPA's fused CPU kernel: keep ``"sdpa"`` for CPU runs.
* CPU with gradients: PyTorch's flex_attention has no CPU backward (torch 2.13 raises NotImplementedError),
  so there we run SDPA with the BlockMask expanded to the equivalent dense boolean mask (same pattern, same
  result): a CPU test or demo can train a model configured with ``"flex"``.

Dtypes. SDPA is an autocast op (it runs in the autocast dtype); flex_attention is not, and on CUDA the qk-norm
(LayerNorm, an fp32 op under autocast) returns fp32 q, k next to a bf16 v. Under autocast we therefore cast
q, k, v to the autocast dtype (the precision SDPA would use) and call flex with autocast off.
"""
from __future__ import annotations

import contextlib
import warnings

import torch
import torch.nn.functional as F
from torch.nn.attention.flex_attention import BlockMask, create_mask, flex_attention

_compiled_flex = None   # torch.compile(flex_attention), created on first CUDA use (compiling is lazy anyway)


def _compiled():
    global _compiled_flex
    if _compiled_flex is None:
        _compiled_flex = torch.compile(flex_attention)
    return _compiled_flex


def flex_block_attention(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor,
                         block_mask: BlockMask | None) -> torch.Tensor:
    """``softmax(q k^T / sqrt(D) + mask) v`` under ``block_mask`` (None = full attention).

    ``q`` (B, H, S_q, D); ``k``, ``v`` (B, H, S_k, D); ``block_mask`` of shape (1 or B, 1 or H, S_q, S_k).
    Returns (B, H, S_q, D) in the compute dtype (the autocast dtype under autocast, else ``q``'s), as
    ``F.scaled_dot_product_attention(q, k, v, attn_mask=dense_mask)`` would.
    """
    dev = q.device.type
    autocast = torch.is_autocast_enabled(dev)
    dtype = torch.get_autocast_dtype(dev) if autocast else q.dtype
    q, k, v = q.to(dtype), k.to(dtype), v.to(dtype)   # no-ops when already in dtype
    with torch.autocast(dev, enabled=False) if autocast else contextlib.nullcontext():
        if torch.compiler.is_compiling():
            return flex_attention(q, k, v, block_mask=block_mask)
        if dev == "cuda":
            return _compiled()(q, k, v, block_mask=block_mask)
        if torch.is_grad_enabled() and (q.requires_grad or k.requires_grad or v.requires_grad):
            # no flex backward off CUDA (see the module docstring): the same pattern as a dense mask, via SDPA
            dense = None
            if block_mask is not None:
                s_q, s_k = block_mask.seq_lengths
                dense = create_mask(block_mask.mask_mod, 1, 1, s_q, s_k, device=q.device)
            return F.scaled_dot_product_attention(q, k, v, attn_mask=dense)
        with warnings.catch_warnings():
            # the "called without torch.compile() ... unfused implementation" warning: intended off CUDA
            warnings.filterwarnings("ignore", message=".*flex_attention called without torch.compile.*")
            return flex_attention(q, k, v, block_mask=block_mask)

