"""CogVideoX's transformer block with *per-frame* AdaLN modulation ("expert" AdaLN: separate shift/scale/gate
for text and video from one linear layer).

diffusers' ``CogVideoXLayerNormZero`` takes one embedding per sample; here video tokens of frame ``f`` are
modulated by the embedding of frame ``f``'s noise level (+ its action), ``temb_frames (B, T, D_t)``, and the
text tokens by ``temb_text (B, D_t)``. When every frame carries the sample's embedding this is the same
arithmetic as diffusers' block (same weights, same key names).

Copies that cost memory traffic and no arithmetic are avoided (measured by bench/block_elementwise.py
against the block as it was and diffusers' ``CogVideoXBlock``, same weights, same output):

* the video gate is applied per frame on a ``(B, T, n, D)`` view, not expanded to a ``(B, T*n, D)`` tensor (a
  copy the size of the activations, written in the forward and kept for the backward, twice per block);
* under autocast the modulated norm output is cast to the compute dtype once, so the attention's three
  projections and the feed-forward read one bf16 tensor instead of each casting (and keeping) its own copy;
* the per-frame and text modulations are one linear (one weight gradient, not two summed), and the attention
  and feed-forward outputs are split into text and video with one ``split`` (see ``DiTBlock._gated_residual``).

(An ``addcmul`` for ``norm(x) * (1 + scale) + shift`` was measured too: no fewer bytes over forward and
backward, and not kept.) Under ``torch.compile`` inductor fuses elementwise ops by itself; this matters for
the eager path (CPU runs, and any run with compile off) and for what is kept for the backward.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn
from torch.nn.attention.flex_attention import BlockMask

from resim.models.world.attention import Attention


class LayerNormZero(nn.Module):
    """``linear(silu(temb))`` → 6 chunks (shift, scale, gate for video | for text); keys as diffusers'."""

    def __init__(self, cond_dim: int, dim: int, elementwise_affine: bool = True, eps: float = 1e-5):
        super().__init__()
        self.silu = nn.SiLU()
        self.linear = nn.Linear(cond_dim, 6 * dim)
        self.norm = nn.LayerNorm(dim, eps=eps, elementwise_affine=elementwise_affine)

    def forward(self, video: torch.Tensor, text: torch.Tensor | None, temb_frames: torch.Tensor,
                temb_text: torch.Tensor | None):
        """video (B, T*n, D), text (B, L, D) or None, temb_frames (B, T, D_t), temb_text (B, D_t) or None.

        Returns the normed and modulated video (B, T*n, D) and text (B, L, D) (or None), in the compute dtype
        (the autocast dtype under autocast, else the input's), the video gate per frame (B, T, 1, D) and the
        text gate (B, 1, D) (or None), for ``gated_add``.
        """
        b, tn, d = video.shape
        t = temb_frames.shape[1]
        dtype = compute_dtype(video)
        # one linear over [frames | text] embeddings: its weight gradient (6D x D_t) is then computed once, not
        # once per call and summed
        temb = temb_frames if text is None else torch.cat([temb_frames, temb_text[:, None]], dim=1)
        mod = self.linear(self.silu(temb))                                     # (B, T [+ 1], 6D)
        shift, scale, gate = mod[:, :t].chunk(6, dim=-1)[:3]                   # (B, T, D) each
        v = self.norm(video).view(b, t, tn // t, d) * (1 + scale[:, :, None]) + shift[:, :, None]
        v = v.view(b, tn, d).to(dtype)
        if text is None:
            return v, None, gate[:, :, None], None
        e_shift, e_scale, e_gate = mod[:, t:].chunk(6, dim=-1)[3:]             # (B, 1, D) each
        e = (self.norm(text) * (1 + e_scale) + e_shift).to(dtype)
        return v, e, gate[:, :, None], e_gate


def compute_dtype(x: torch.Tensor) -> torch.dtype:
    """The dtype the next matmul runs in: the autocast dtype under autocast, else ``x``'s."""
    dev = x.device.type
    return torch.get_autocast_dtype(dev) if torch.is_autocast_enabled(dev) else x.dtype


def gated_add(x: torch.Tensor, gate: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """``x + gate * y`` with ``x``, ``y`` (B, T*n, D) and a per-frame ``gate`` (B, T, 1, D): the gate broadcasts
    over each frame's n tokens on a (B, T, n, D) view instead of being expanded to (B, T*n, D). Text: ``gate``
    (B, 1, D) broadcasts as it is."""
    if gate.dim() == 3:
        return x + gate * y
    b, t = gate.shape[:2]
    return x + (gate * y.unflatten(1, (t, -1))).flatten(1, 2)   # a fresh tensor, not a view (see DiTBlock)


class GELUProj(nn.Module):
    def __init__(self, dim_in: int, dim_out: int):
        super().__init__()
        self.proj = nn.Linear(dim_in, dim_out)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.gelu(self.proj(x), approximate="tanh")


class FeedForward(nn.Module):
    """``net = [GELU(tanh) proj, Dropout, Linear, Dropout]`` (diffusers ``FeedForward``, keys ``net.0.proj``, ``net.2``)."""

    def __init__(self, dim: int, mult: int = 4):
        super().__init__()
        self.net = nn.ModuleList([GELUProj(dim, dim * mult), nn.Dropout(0.0), nn.Linear(dim * mult, dim),
                                  nn.Dropout(0.0)])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for layer in self.net:
            x = layer(x)
        return x


class DiTBlock(nn.Module):
    """norm1 → joint attention → gated residual → norm2 → FF (on text and video) → gated residual."""

    def __init__(self, dim: int, heads: int, head_dim: int, time_embed_dim: int, attention_bias: bool = True,
                 norm_elementwise_affine: bool = True, norm_eps: float = 1e-5):
        super().__init__()
        self.norm1 = LayerNormZero(time_embed_dim, dim, norm_elementwise_affine, norm_eps)
        self.attn1 = Attention(dim, heads, head_dim, bias=attention_bias)
        self.norm2 = LayerNormZero(time_embed_dim, dim, norm_elementwise_affine, norm_eps)
        self.ff = FeedForward(dim)

    def forward(self, video: torch.Tensor, text: torch.Tensor | None, temb_frames: torch.Tensor,
                temb_text: torch.Tensor | None, mask: torch.Tensor | BlockMask | None,
                past_kv: tuple[torch.Tensor, torch.Tensor] | None = None, return_kv: bool = False):
        """video (B, T*n, D); text (B, L, D), or None when the text lives in ``past_kv`` (cached sampling);
        ``mask``: the block-causal mask as a bool tensor (SDPA) or a ``BlockMask`` (flex), see attention.py.

        Returns (video, text or None, (k, v) over [past | text | video] if ``return_kv`` else None). Every
        returned tensor has its own storage (no views): blocks are FSDP2 units, and FSDP2 warns that an
        in-place op on a view returned by a unit can corrupt gradients.
        """
        nv, ne, gv, ge = self.norm1(video, text, temb_frames, temb_text)
        x = nv if ne is None else torch.cat([ne, nv], dim=1)
        a, kv = self.attn1(x, mask=mask, past_kv=past_kv, return_kv=return_kv)
        video, text = self._gated_residual(video, text, gv, ge, a)
        nv, ne, gv, ge = self.norm2(video, text, temb_frames, temb_text)
        x = nv if ne is None else torch.cat([ne, nv], dim=1)
        video, text = self._gated_residual(video, text, gv, ge, self.ff(x))
        return video, text, kv

    @staticmethod
    def _gated_residual(video, text, gv, ge, y):
        """``video + gv * y_video``, ``text + ge * y_text`` where ``y`` is (B, [L +] T*n, D) over [text | video].
        One ``split``, not two slices: its backward writes one gradient, where each slice's backward writes a
        zero-padded full-size one and then adds them (diffusers' attention processor splits too)."""
        if text is None:
            return gated_add(video, gv, y), None
        y_text, y_video = y.split([text.shape[1], video.shape[1]], dim=1)
        return gated_add(video, gv, y_video), gated_add(text, ge, y_text)
