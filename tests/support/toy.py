"""A small denoising MLP with ``loss(batch) -> (loss, logs)``: exercises the generic trainer in tests
without the world model (registered as ``toy`` by tests/conftest.py, not by the product).

It reads either a dict ``{"x": (B, D) float}`` or a ``resim.train.data.Batch`` (uses ``latents``
``(B, T, C, h, w)`` as B*T*h*w vectors of C channels) and learns to remove Gaussian noise drawn
from torch's global RNG, so an exact resume must also restore the RNG.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from resim.config import from_dict


@dataclass
class ToyConfig:
    dim: int = 16          # channels of the input vectors (latent channels for a Batch)
    hidden: int = 32
    num_blocks: int = 2
    noise_std: float = 0.5


class _Block(nn.Module):
    def __init__(self, hidden: int):
        super().__init__()
        self.norm = nn.LayerNorm(hidden)
        self.fc = nn.Linear(hidden, hidden)

    def forward(self, h):
        return h + self.fc(torch.nn.functional.gelu(self.norm(h)))


class ToyDenoiser(nn.Module):
    def __init__(self, cfg: ToyConfig):
        super().__init__()
        self.cfg = cfg
        self.inp = nn.Linear(cfg.dim, cfg.hidden)
        self.blocks = nn.ModuleList(_Block(cfg.hidden) for _ in range(cfg.num_blocks))
        self.out = nn.Linear(cfg.hidden, cfg.dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.inp(x)
        for b in self.blocks:
            h = b(h)
        return self.out(h)

    def fsdp_units(self):
        return list(self.blocks)

    def loss(self, batch):
        if isinstance(batch, dict):
            x = batch["x"].float()
        else:  # a Batch: (B, T, C, h, w) latents -> vectors of C channels
            lat = batch.latents.float()
            x = lat.permute(0, 1, 3, 4, 2).reshape(-1, lat.shape[2])
        noisy = x + self.cfg.noise_std * torch.randn_like(x)
        loss = torch.nn.functional.mse_loss(self(noisy), x)
        return loss, {"x_std": x.detach().std()}


def build_toy(model_cfg: dict, *, device="cpu") -> ToyDenoiser:
    cfg = from_dict(ToyConfig, model_cfg)
    with torch.device(device):
        return ToyDenoiser(cfg)
