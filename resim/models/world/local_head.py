"""A per-frame convolutional head beside the DiT's patch-to-image projection (``LocalHeadConfig``).

The DiT predicts v one ``p x p`` patch per token. At low and middle noise levels v is mostly the noise itself,
which differs from latent pixel to latent pixel; a transformer with large patches learns that pixel-wise part
slowly, and a one-step clean estimate ``x0 = sqrt(a) x_t - sqrt(1 - a) v`` then keeps a speckle that DDIM draws
into every frame. This head sees each latent pixel of the noisy input and of the DiT's prediction with its 3x3
neighbourhood, modulated by the frame's noise-level embedding, and adds a correction (U-ViT's 3x3 convolution
after the linear projection, Bao et al. 2023; DIAMOND's denoiser is a U-Net for the same reason). It works frame by
frame, so the block-causal structure and the KV cache are untouched.
"""
from __future__ import annotations

import torch
from torch import nn

from resim.models.world.config import LocalHeadConfig


class LocalHead(nn.Module):
    """``(x_t, v_dit, temb) → v_dit + correction``; zero correction at initialisation.

    ``x_t``, ``v_dit``: ``(B, T, C, h, w)``; ``temb``: ``(B, T, D_t)`` per-frame conditioning embedding.
    """

    def __init__(self, cfg: LocalHeadConfig, in_channels: int, out_channels: int, cond_dim: int):
        super().__init__()
        c = cfg.channels
        self.conv_in = nn.Conv2d(in_channels + out_channels, c, 3, padding=1)
        self.norms = nn.ModuleList([nn.GroupNorm(min(8, c), c, affine=False) for _ in range(cfg.num_layers - 1)])
        self.mods = nn.ModuleList([nn.Linear(cond_dim, 2 * c) for _ in range(cfg.num_layers - 1)])
        self.convs = nn.ModuleList([nn.Conv2d(c, c, 3, padding=1) for _ in range(cfg.num_layers - 2)])
        self.conv_out = nn.Conv2d(c, out_channels, 3, padding=1)
        self.act = nn.SiLU()
        nn.init.zeros_(self.conv_out.weight)
        nn.init.zeros_(self.conv_out.bias)

    def forward(self, x_t: torch.Tensor, v: torch.Tensor, temb: torch.Tensor) -> torch.Tensor:
        b, t, ch, h, w = v.shape
        y = self.conv_in(torch.cat([x_t.to(v.dtype), v], dim=2).reshape(b * t, -1, h, w))
        cond = self.act(temb.reshape(b * t, -1).to(v.dtype))
        for i, (norm, mod) in enumerate(zip(self.norms, self.mods)):
            shift, scale = mod(cond).chunk(2, dim=-1)
            y = self.act(norm(y) * (1 + scale[:, :, None, None]) + shift[:, :, None, None])
            y = self.convs[i](y) if i < len(self.convs) else self.conv_out(y)
        return v + y.reshape(b, t, ch, h, w)
