"""CogVideoX's transformer block with *per-frame* AdaLN modulation ("expert" AdaLN: separate shift/scale/gate
for text and video from one linear layer).

diffusers' ``CogVideoXLayerNormZero`` takes one embedding per sample; here video tokens of frame ``f`` are
modulated by the embedding of frame ``f``'s noise level (+ its action), ``temb_frames (B, T, D_t)``, and the
text tokens by ``temb_text (B, D_t)``. When every frame carries the sample's embedding this is the same
arithmetic as diffusers' block (same weights, same key names).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn
from torch.nn.attention.flex_attention import BlockMask

from training.models.attention import Attention


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

        Returns normed video, normed text (or None), video gate (B, T*n, D)-broadcastable, text gate.
        """
        b, tn, d = video.shape
        t = temb_frames.shape[1]
        shift, scale, gate = self.linear(self.silu(temb_frames)).chunk(6, dim=-1)[:3]   # (B, T, D) each
        v = self.norm(video).view(b, t, tn // t, d) * (1 + scale[:, :, None]) + shift[:, :, None]
        v_gate = gate[:, :, None].expand(b, t, tn // t, d).reshape(b, tn, d)
        if text is None:
            return v.reshape(b, tn, d), None, v_gate, None
        e_shift, e_scale, e_gate = self.linear(self.silu(temb_text)).chunk(6, dim=-1)[3:]  # (B, D) each
        e = self.norm(text) * (1 + e_scale[:, None]) + e_shift[:, None]
        return v.reshape(b, tn, d), e, v_gate, e_gate[:, None]


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
        L = 0 if ne is None else ne.shape[1]
        video = video + gv * a[:, L:]
        if text is not None:
            text = text + ge * a[:, :L]
        nv, ne, gv, ge = self.norm2(video, text, temb_frames, temb_text)
        x = nv if ne is None else torch.cat([ne, nv], dim=1)
        f = self.ff(x)
        video = video + gv * f[:, L:]
        if text is not None:
            text = text + ge * f[:, :L]
        return video, text, kv
