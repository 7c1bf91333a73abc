"""Embeddings of CogVideoX's layout, re-implemented so they accept *per-frame* noise levels.

* :func:`timestep_embedding` – DDPM sinusoidal embedding of integer levels of any shape (diffusers'
  ``get_timestep_embedding`` asserts 1-D input; ours maps ``(B, T)`` → ``(B, T, D)`` with the same numbers).
* :class:`TimestepMLP` – ``time_embedding`` (linear → SiLU → linear); state-dict keys as diffusers'.
* :func:`sincos_pos_embed_3d` – diffusers' ``get_3d_sincos_pos_embed``: ``D/4`` temporal + ``3D/4`` spatial
  channels. Frame ``f``'s code depends only on ``f`` (not on the clip length), so a suffix of frames
  ``[f0, f0 + n)`` gets exactly the positions it has inside the whole clip (used by the KV cache).
* :class:`PatchEmbed` – per-frame 2×2 patches (``Conv2d``) and the text projection, keys as diffusers'.
"""
from __future__ import annotations

import math

import torch
from torch import nn


def timestep_embedding(t: torch.Tensor, dim: int, flip_sin_to_cos: bool = True, freq_shift: float = 0.0,
                       max_period: float = 10000.0) -> torch.Tensor:
    """Sinusoidal embedding of noise levels ``t`` (any shape, int or float) → ``t.shape + (dim,)`` float32."""
    half = dim // 2
    exponent = -math.log(max_period) * torch.arange(half, dtype=torch.float32, device=t.device)
    freqs = torch.exp(exponent / (half - freq_shift))
    args = t.float()[..., None] * freqs
    emb = torch.cat([torch.sin(args), torch.cos(args)], dim=-1)
    if flip_sin_to_cos:
        emb = torch.cat([emb[..., half:], emb[..., :half]], dim=-1)
    if dim % 2:
        emb = nn.functional.pad(emb, (0, 1))
    return emb


class TimestepMLP(nn.Module):
    """``linear_1 → SiLU → linear_2`` (diffusers ``TimestepEmbedding``): (..., in_dim) → (..., out_dim)."""

    def __init__(self, in_dim: int, out_dim: int):
        super().__init__()
        self.linear_1 = nn.Linear(in_dim, out_dim)
        self.act = nn.SiLU()
        self.linear_2 = nn.Linear(out_dim, out_dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.linear_2(self.act(self.linear_1(x)))


def _sincos_1d(dim: int, pos: torch.Tensor) -> torch.Tensor:
    """(M,) positions → (M, dim): [sin | cos] with frequencies 1/10000^(2i/dim), computed in float64."""
    omega = torch.arange(dim // 2, dtype=torch.float64, device=pos.device) / (dim / 2.0)
    omega = 1.0 / 10000 ** omega
    out = torch.outer(pos.reshape(-1).to(torch.float64), omega)
    return torch.cat([torch.sin(out), torch.cos(out)], dim=1)


def sincos_pos_embed_3d(dim: int, grid_hw: tuple[int, int], frames: int, spatial_scale: float = 1.0,
                        temporal_scale: float = 1.0, frame_offset: int = 0,
                        device: torch.device | None = None) -> torch.Tensor:
    """3D sin-cos positions ``(frames, h*w, dim)`` float32 for frames ``frame_offset … frame_offset+frames-1``.

    Identical to ``diffusers.models.embeddings.get_3d_sincos_pos_embed(dim, (w, h), T, ...)[offset:]``:
    channels = [temporal D/4 | spatial 3D/4], spatial = [emb(h-index…) | emb(w-index…)] as diffusers' meshgrid
    with ``indexing='xy'`` produces them; tokens are row-major over (h, w).
    """
    h, w = grid_hw
    d_sp, d_t = 3 * dim // 4, dim // 4
    gw = torch.arange(w, dtype=torch.float32, device=device) / spatial_scale
    gh = torch.arange(h, dtype=torch.float32, device=device) / spatial_scale
    grid = torch.stack(torch.meshgrid(gw, gh, indexing="xy"), dim=0).reshape(2, 1, h, w)
    sp = torch.cat([_sincos_1d(d_sp // 2, grid[0]), _sincos_1d(d_sp // 2, grid[1])], dim=1)  # (h*w, d_sp)
    gt = torch.arange(frame_offset, frame_offset + frames, dtype=torch.float32, device=device) / temporal_scale
    tp = _sincos_1d(d_t, gt)  # (frames, d_t)
    out = torch.cat([tp[:, None, :].expand(frames, h * w, d_t), sp[None].expand(frames, h * w, d_sp)], dim=-1)
    return out.float()


class PatchEmbed(nn.Module):
    """Per-frame ``p×p`` patches of the latent video and the text projection (diffusers ``CogVideoXPatchEmbed``).

    ``video(x)``: ``(B, T, C, h, w)`` → ``(B, T, (h/p)*(w/p), D)`` (no positions). ``text(e)``: ``(B, L, D_text)`` →
    ``(B, L, D)``. Positions are added by the DiT, which knows each frame's absolute index.
    """

    def __init__(self, patch_size: int, in_channels: int, dim: int, text_dim: int, bias: bool = True):
        super().__init__()
        self.patch_size = patch_size
        self.proj = nn.Conv2d(in_channels, dim, kernel_size=patch_size, stride=patch_size, bias=bias)
        self.text_proj = nn.Linear(text_dim, dim)

    def video(self, x: torch.Tensor) -> torch.Tensor:
        b, t, c, h, w = x.shape
        y = self.proj(x.reshape(b * t, c, h, w))  # (B*T, D, h/p, w/p)
        return y.flatten(2).transpose(1, 2).reshape(b, t, -1, y.shape[1])

    def text(self, e: torch.Tensor) -> torch.Tensor:
        return self.text_proj(e)
