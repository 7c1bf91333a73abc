"""Per-frame noise-level sampling for training.

``sample_noise_levels(cfg, B, T) -> (t (B, T) int64, loss_mask (B, T) bool)``:

``N = cfg.schedule.num_train_timesteps`` (the number of noise levels).

* ``diffusion_forcing``: ``t[b, f] ~ U{0..N-1}`` independently per frame (Chen et al. 2024; Vid2World 4.1),
  exposing the model to every mix of history/future levels it meets in causal rollouts; loss everywhere.
* ``resim_cond_aug``: history frames ``f < H`` share ``t_aug ~ U{0..cond_aug_max_t}`` (default N-1), the future shares
  ``t ~ U{0..N-1}`` (ReSim App. B.2, conditioning augmentation; t_aug = 0 at inference); loss on the future.
* ``uniform``: one ``t ~ U{0..N-1}`` for all frames (CogVideoX's full-sequence training); loss everywhere.

With ``cfg.low_level_fraction = p > 0`` every draw of a level that the loss counts (the future's, or every frame's) is
taken from ``U{0..cfg.low_level_max_t}`` with probability p instead (the same choice for the frames that share a
level); p = 0 draws exactly as above, with the same random numbers.
"""
from __future__ import annotations

import torch

from resim.diffusion.config import ObjectiveConfig


def sample_noise_levels(cfg: ObjectiveConfig, batch_size: int, num_frames: int,
                        generator: torch.Generator | None = None,
                        device: torch.device | str = "cpu",
                        num_history_frames: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """``num_history_frames`` (latent frames) overrides ``cfg.num_history_frames`` (a batch's own clip geometry)."""
    n = cfg.schedule.num_train_timesteps
    b, f = batch_size, num_frames

    def levels(shape: tuple[int, int]) -> torch.Tensor:
        t = torch.randint(0, n, shape, generator=generator)
        if cfg.low_level_fraction > 0:   # no extra draws at 0: old runs resume on the same random numbers
            low = torch.randint(0, cfg.low_level_max_t + 1, shape, generator=generator)
            t = torch.where(torch.rand(shape, generator=generator) < cfg.low_level_fraction, low, t)
        return t

    if cfg.noise_mode == "diffusion_forcing":
        t = levels((b, f))
        mask = torch.ones(b, f, dtype=torch.bool)
    elif cfg.noise_mode == "uniform":
        t = levels((b, 1)).expand(b, f).clone()
        mask = torch.ones(b, f, dtype=torch.bool)
    elif cfg.noise_mode == "resim_cond_aug":
        h = cfg.num_history_frames if num_history_frames is None else int(num_history_frames)
        if not 0 < h < f:
            raise ValueError(f"resim_cond_aug needs 0 < num_history_frames ({h}) < latent frames ({f})")
        t_aug = torch.randint(0, cfg.cond_aug_max_level + 1, (b, 1), generator=generator)
        t_fut = levels((b, 1))
        hist = torch.arange(f)[None] < h
        t = torch.where(hist, t_aug, t_fut)
        mask = ~hist.expand(b, f)
    else:  # validated by the config; reaching here is our bug
        raise AssertionError(cfg.noise_mode)
    return t.to(device), mask.to(device)
