"""Joint text+video self-attention with qk-norm, a block-causal mask and a prefix KV cache.

Sequence layout (as CogVideoX): ``[text (L) | frame 0 (n) | frame 1 (n) | …]`` with ``n = (h/p)(w/p)``.

Block-causal mask (Vid2World Sec. 4.1: a causal temporal mask needs no new weights, attention adapts to
the shorter context): a video token of frame ``f`` sees the text and every token of frames ``≤ f``; a text
token sees only the text. The latter keeps the text stream a function of the prompt alone, so it never
depends on (a) frames, (b) their noise levels – which is what lets the sampler compute text and history
keys/values once and reuse them (KV cache) and what makes "perturb frame > f, nothing at ≤ f changes" hold
for the text-mediated paths too (text attending to all frames would leak future frames into every frame
through the next layer's text keys).

Two representations of the same pattern, one per attention backend (``WorldModelConfig.attention_backend``):

* ``"sdpa"`` (default): :func:`block_causal_mask`, a boolean ``(S_q, S_k)`` tensor shared across batch and heads
  (broadcast, not materialised per head) for ``F.scaled_dot_product_attention``. Measured on an H100 with torch
  2.11 (docs/benchmarks.md, "GPU (NVIDIA H100)"): the default dispatch runs **cuDNN attention** with the mask
  taken as a dense bias (FlashAttention-2 refuses any mask; the memory-efficient kernel accepts it but is
  2.3-2.8x slower). The masked call is 1.67-2.18x the *unmasked* one although the mask removes 46 % of the
  scores: every tile is computed and the (S, S) bias read. CPU runs the fused flash-attention-for-CPU kernel.
* ``"flex"``: :func:`block_causal_block_mask`, the same pattern as a ``flex_attention`` ``BlockMask`` (cached
  per geometry; fully masked 128x128 tiles are skipped, no O(S^2) tensor), run by
  :func:`resim.models.world.flex.flex_block_attention` (compiled on CUDA, eager on CPU).

Unmasked attention (``causal=False``) always uses SDPA: nothing to skip, and unmasked cuDNN is the fastest
kernel measured.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import nn
from torch.nn.attention.flex_attention import BlockMask, create_block_mask

from resim.models.world.flex import flex_block_attention


def block_frame_ids(text_len: int, tokens_per_frame: int, num_frames: int, prefix_frames: int = 0,
                    with_text_queries: bool = True, device: torch.device | str | None = None,
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """Frame id of every query ``(S_q,)`` and key ``(S_k,)`` (text: -1); the one definition of the pattern.

    Keys: ``text_len`` text tokens, then ``prefix_frames + num_frames`` frames of ``tokens_per_frame`` tokens.
    Queries: the text tokens (if ``with_text_queries``) and the ``num_frames`` new frames (absolute indices
    ``prefix_frames …``). Query ``i`` may attend key ``j`` iff ``k_frame[j] <= q_frame[i]``: a video query of
    frame f sees keys of frames <= f and the text (id -1); a text query (id -1) sees the text keys only.
    """
    n = tokens_per_frame
    k_frame = torch.cat([torch.full((text_len,), -1, device=device),
                         torch.arange(prefix_frames + num_frames, device=device).repeat_interleave(n)])
    q_frame = torch.arange(prefix_frames, prefix_frames + num_frames, device=device).repeat_interleave(n)
    if with_text_queries:
        q_frame = torch.cat([torch.full((text_len,), -1, device=device), q_frame])
    return q_frame, k_frame


def block_causal_mask(text_len: int, tokens_per_frame: int, num_frames: int, prefix_frames: int = 0,
                      with_text_queries: bool = True, device: torch.device | str | None = None) -> torch.Tensor:
    """Boolean mask ``(S_q, S_k)``, True = may attend (SDPA backend); layout as :func:`block_frame_ids`.

    Built directly on ``device`` from the two frame-id vectors (one comparison kernel) rather than cached: for
    CogVideoX-2B at 13 frames the mask is 17,776² ≈ 316 MB (553 MB at 512x896), too big to keep copies of or
    to copy host→device every step.
    """
    q_frame, k_frame = block_frame_ids(text_len, tokens_per_frame, num_frames, prefix_frames, with_text_queries,
                                       device)
    return k_frame[None, :] <= q_frame[:, None]


def block_causal_block_mask(text_len: int, tokens_per_frame: int, num_frames: int, prefix_frames: int = 0,
                            with_text_queries: bool = True, device: torch.device | str | None = None) -> BlockMask:
    """The same pattern as a ``flex_attention`` ``BlockMask`` (flex backend), shape ``(1, 1, S_q, S_k)``
    broadcast over batch and heads. Cached per geometry (the arguments): built once, then every layer of
    every forward of that geometry (a rollout's 50 denoising steps, a training run's fixed clip size) reuses
    it. Its block tables are small (``(S/128)^2`` ints), so keeping a few geometries costs little."""
    dev = torch.device(device if device is not None else "cpu")
    if dev.type == "cuda" and dev.index is None:          # "cuda" and "cuda:0" must hit the same entry
        dev = torch.device("cuda", torch.cuda.current_device())
    return _cached_block_mask(text_len, tokens_per_frame, num_frames, prefix_frames, with_text_queries, dev)


@functools.lru_cache(maxsize=16)
def _cached_block_mask(text_len: int, tokens_per_frame: int, num_frames: int, prefix_frames: int,
                       with_text_queries: bool, device: torch.device) -> BlockMask:
    q_frame, k_frame = block_frame_ids(text_len, tokens_per_frame, num_frames, prefix_frames, with_text_queries,
                                       device)

    def mask_mod(b, h, q_idx, kv_idx):
        # indexing the two id vectors keeps this the one pattern definition (block_frame_ids); it is also the
        # form whose speed and agreement with SDPA were measured on the H100 (bench --sdpa-probe)
        return k_frame[kv_idx] <= q_frame[q_idx]

    # create_block_mask evaluates mask_mod on the whole (S_q, S_k) grid once (a transient bool tensor of the
    # dense mask's size), then keeps per-128x128-tile tables: full / partial / empty
    return create_block_mask(mask_mod, None, None, q_frame.numel(), k_frame.numel(), device=device)


@dataclass
class KVCache:
    """Per-layer keys/values of a prefix: the text tokens and ``num_frames`` clean history frames.

    ``keys[i]``/``values[i]``: ``(B, heads, L + num_frames * tokens_per_frame, head_dim)``. Built by
    ``WorldModel.forward(..., return_kv_cache=True)`` and consumed by ``forward(..., kv_cache=cache)`` (causal
    models only: with the block-causal mask a prefix's keys/values do not depend on anything after it).
    """
    keys: list[torch.Tensor] = field(default_factory=list)
    values: list[torch.Tensor] = field(default_factory=list)
    text_len: int = 0
    tokens_per_frame: int = 0
    num_frames: int = 0
    # the pooled text vector (B, D_t) of the prompt the cache was built with (models with text_pool enabled)
    text_cond: torch.Tensor | None = None

    def crop(self, num_frames: int) -> "KVCache":
        """The cache of the first ``num_frames`` frames (e.g. a sliding window start or a rollback)."""
        if not 0 <= num_frames <= self.num_frames:
            raise ValueError(f"cannot crop a {self.num_frames}-frame cache to {num_frames} frames")
        s = self.text_len + num_frames * self.tokens_per_frame
        return KVCache([k[:, :, :s] for k in self.keys], [v[:, :, :s] for v in self.values],
                       self.text_len, self.tokens_per_frame, num_frames, self.text_cond)


class Attention(nn.Module):
    """Multi-head self-attention over ``[text | video]`` with LayerNorm qk-norm (CogVideoX's ``attn1``).

    Submodule names (``to_q``, ``to_k``, ``to_v``, ``to_out.0``, ``norm_q``, ``norm_k``) equal diffusers' so
    checkpoints and LoRA target names carry over.
    """

    def __init__(self, dim: int, heads: int, head_dim: int, bias: bool = True, out_bias: bool = True,
                 qk_norm_eps: float = 1e-6):
        super().__init__()
        self.heads, self.head_dim = heads, head_dim
        inner = heads * head_dim
        self.norm_q = nn.LayerNorm(head_dim, eps=qk_norm_eps)
        self.norm_k = nn.LayerNorm(head_dim, eps=qk_norm_eps)
        self.to_q = nn.Linear(dim, inner, bias=bias)
        self.to_k = nn.Linear(dim, inner, bias=bias)
        self.to_v = nn.Linear(dim, inner, bias=bias)
        self.to_out = nn.ModuleList([nn.Linear(inner, dim, bias=out_bias), nn.Dropout(0.0)])

    def forward(self, x: torch.Tensor, mask: torch.Tensor | BlockMask | None = None,
                past_kv: tuple[torch.Tensor, torch.Tensor] | None = None, return_kv: bool = False,
                ) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor] | None]:
        """``x`` (B, S, dim) → (out (B, S, dim), (k, v) of the full key sequence, or None).

        ``return_kv``: return the keys/values (B, heads, S_past + S, head_dim), contiguous, for a KV cache.
        Training leaves it off: ``v`` is a transposed *view* of ``to_v``'s output, and a view returned
        from an FSDP2 unit (a block) triggers FSDP2's in-place-on-view warning.

        ``past_kv``: keys/values (B, heads, S_past, head_dim) prepended to this call's keys/values (a
        prefix's cache); ``mask`` (S, S_past + S) bool, True = attend (SDPA), or the same pattern as a
        ``BlockMask`` (flex_attention backend; see the module docstring), or None (full attention, SDPA).
        """
        b, s, _ = x.shape
        q = self.to_q(x).view(b, s, self.heads, self.head_dim).transpose(1, 2)
        k = self.to_k(x).view(b, s, self.heads, self.head_dim).transpose(1, 2)
        v = self.to_v(x).view(b, s, self.heads, self.head_dim).transpose(1, 2)
        q, k = self.norm_q(q), self.norm_k(k)
        if past_kv is not None:
            k = torch.cat([past_kv[0], k], dim=2)
            v = torch.cat([past_kv[1], v], dim=2)
        if isinstance(mask, BlockMask):
            o = flex_block_attention(q, k, v, mask)
        else:
            o = F.scaled_dot_product_attention(q, k, v, attn_mask=mask)
        o = o.transpose(1, 2).reshape(b, s, self.heads * self.head_dim)
        out = self.to_out[1](self.to_out[0](o))
        if not return_kv:
            return out, None
        return out, (k.contiguous(), v.contiguous())  # own storage, not views (no-ops after a cat)
