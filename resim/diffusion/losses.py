"""``training_losses(model, batch, cfg) -> (loss, logs)``: the world model's diffusion objective.

The model is an argument (DiT style): anything with ``model(x_t, t, text, trajectory, actions,
trajectory_keep=..., action_keep=...) -> v`` works, so FSDP/compile wrappers apply from outside.

Batch (a mapping or an object with these attributes; tensors already on the model's device):

* ``latents`` (B, T, C, h, w) float – clean VAE latents (scaled);
* ``text`` (B, L, D_text) – T5 embedding of prefix + command; ``null_text`` (B, L, D_text) – the prefix alone
  (ReSim drops only the *command*, the prefix is kept; needed when ``text_drop_prob > 0``);
* ``trajectory`` (B, 8, 3) optional; ``has_trajectory`` (B,) bool optional (False rows use the null);
* ``source`` sequence of B strings optional ("opendv", "navsim", "carla", …): sources listed in
  ``cfg.trajectory_keep_sources`` (CARLA) never drop the trajectory – their hazardous behaviour cannot be
  inferred from the history (ReSim App. B.2);
* ``actions`` (B, T, A) / (B, T) optional, ``action_valid`` (B, T) bool optional. Without actions but with a
  trajectory (with ``cfg.actions_from_trajectory`` and ``ego_motion_actions``) per-frame ego motion is derived
  from the trajectory.
* ``num_history_latent_frames`` (int) and ``latent_frame_dt_s`` (float) optional: the batch's clip geometry
  (``resim.train.data.Batch`` derives them from the shard metadata). With ``cfg.geometry_from_batch`` they
  replace ``cfg.num_history_frames`` / ``cfg.latent_frame_dt_s``, so batches of different clip lengths (NAVSIM
  2 Hz: 3 latent frames, 1 of history; OpenDV: 13, 3 of history) train under one config. T may differ from
  step to step (the DiT's sin-cos positions are computed for each T).

Per-sample condition dropout (classifier-free guidance): text p=0.5, trajectory p=0.5 (not for CARLA), each
frame's action p=0.2 (Vid2World's causal action guidance). Actions derived from a trajectory are dropped
with it (they carry the same information, so keeping them would leave no unconditional branch).

Loss: mean squared error on v over the frames the noise mode selects (future only for ``resim_cond_aug``).
This equals CogVideoX's own fine-tuning loss, ``(1−ᾱ)^-1 · |x̂0 − x0|²`` with ``x̂0`` from v, because
``x̂0 − x0 = −√(1−ᾱ)(v̂ − v)``.
"""
from __future__ import annotations

from typing import Any

import torch

from resim.diffusion.config import ObjectiveConfig
from resim.diffusion.noise_levels import sample_noise_levels
from resim.diffusion.schedule import add_noise, alphas_cumprod, v_target
from resim.models.world.conditioning import actions_from_trajectory

_AC_CACHE: dict[tuple, torch.Tensor] = {}


def _get(batch: Any, name: str, default: Any = None) -> Any:
    if isinstance(batch, dict):
        return batch.get(name, default)
    return getattr(batch, name, default)


def _alphas(cfg: ObjectiveConfig, device: torch.device) -> torch.Tensor:
    s = cfg.schedule
    key = (s.num_train_timesteps, s.beta_start, s.beta_end, s.snr_shift_scale, s.rescale_zero_terminal_snr, str(device))
    if key not in _AC_CACHE:
        _AC_CACHE[key] = alphas_cumprod(s).to(device)
    return _AC_CACHE[key]


def loss_level_bins(num_train_timesteps: int) -> tuple[tuple[str, int, int], ...]:
    """``(name, lo, hi)`` of the logged per-level losses: the thirds ``[0, N/3)``, ``[N/3, 2N/3)``, ``[2N/3, N)`` of
    the ``N`` noise levels (integer division: 0/333/666/1000 for CogVideoX's N = 1000)."""
    n = int(num_train_timesteps)
    return (("loss_t_low", 0, n // 3), ("loss_t_mid", n // 3, 2 * n // 3), ("loss_t_high", 2 * n // 3, n))


def _bernoulli_keep(p_drop: float, shape: tuple[int, ...], generator, device) -> torch.Tensor:
    return (torch.rand(shape, generator=generator) >= p_drop).to(device)


def training_losses(model: Any, batch: Any, cfg: ObjectiveConfig, generator: torch.Generator | None = None, *,
                    ego_motion_actions: bool = False) -> tuple[torch.Tensor, dict[str, float]]:
    """One stochastic estimate of the objective; ``generator`` (CPU) makes the draws reproducible.

    ``ego_motion_actions``: the model takes per-frame (dx, dy, dyaw) actions, so a batch with a trajectory and no
    actions gets them derived from the trajectory. The caller says so (``model_cfg.actions.takes_ego_motion``): the
    objective does not look inside the network."""
    x0 = _get(batch, "latents")
    if x0 is None or x0.dim() != 5:
        raise ValueError("batch.latents must be (B, T, C, h, w)")
    b, nf = x0.shape[:2]
    dev = x0.device
    text = _get(batch, "text")
    if text is None:
        raise ValueError("batch.text (B, L, D_text) is required")

    hist, frame_dt = cfg.num_history_frames, cfg.latent_frame_dt_s
    if cfg.geometry_from_batch:
        hist = _get(batch, "num_history_latent_frames") or hist
        frame_dt = _get(batch, "latent_frame_dt_s") or frame_dt

    # --- noise levels, noisy input, target
    t, loss_mask = sample_noise_levels(cfg, b, nf, generator, dev, num_history_frames=hist)
    noise = torch.randn(x0.shape, generator=generator).to(device=dev, dtype=x0.dtype)
    ac = _alphas(cfg, dev)
    x_t = add_noise(x0, noise, t, ac)
    target = v_target(x0, noise, t, ac)

    if cfg.shuffle_commands:   # the control: prompts permuted across the batch (see ObjectiveConfig)
        text = text[torch.randperm(b, generator=generator).to(text.device)]

    # --- condition dropout
    keep_text = _bernoulli_keep(cfg.text_drop_prob, (b,), generator, dev)
    if cfg.text_drop_prob > 0:
        null_text = _get(batch, "null_text")
        if null_text is None:
            raise ValueError("text_drop_prob > 0 needs batch.null_text (the prompt prefix without the command)")
        text = torch.where(keep_text[:, None, None], text, null_text.to(text.dtype))

    traj = _get(batch, "trajectory")
    keep_traj = None
    if traj is not None:
        keep_traj = _bernoulli_keep(cfg.trajectory_drop_prob, (b,), generator, dev)
        sources = _get(batch, "source")
        if sources is not None:
            if len(sources) != b:
                raise ValueError(f"batch.source has {len(sources)} entries for a batch of {b}")
            always = torch.tensor([s in cfg.trajectory_keep_sources for s in sources], device=dev)
            keep_traj = keep_traj | always
        has = _get(batch, "has_trajectory")
        if has is not None:
            keep_traj = keep_traj & torch.as_tensor(has, device=dev).bool()

    actions = _get(batch, "actions")
    keep_act = None
    derived = False
    if actions is not None:
        valid = _get(batch, "action_valid")
        keep_act = torch.ones(b, nf, dtype=torch.bool, device=dev) if valid is None else valid.to(dev).bool()
    elif traj is not None and cfg.actions_from_trajectory and ego_motion_actions:
        actions, keep_act = actions_from_trajectory(traj, nf, hist, frame_dt, cfg.waypoint_dt_s)
        keep_act = keep_act.to(dev) & keep_traj[:, None]
        derived = True
    if actions is not None:
        keep_act = keep_act & _bernoulli_keep(cfg.action_drop_prob, (b, nf), generator, dev)

    # --- prediction and loss
    pred = model(x_t, t, text, traj, actions, trajectory_keep=keep_traj, action_keep=keep_act)
    per_frame = ((pred.float() - target.float()) ** 2).mean(dim=(2, 3, 4))             # (B, T)
    w = loss_mask.float()
    loss = (per_frame * w).sum() / w.sum().clamp_min(1.0)

    with torch.no_grad():
        logs = {"loss": float(loss.detach()), "t_mean": float(t.float()[loss_mask].mean()) if loss_mask.any() else 0.0,
                "text_kept": float(keep_text.float().mean())}
        if keep_traj is not None:
            logs["trajectory_kept"] = float(keep_traj.float().mean())
        if keep_act is not None:
            logs["actions_kept"] = float(keep_act.float().mean())
            logs["actions_derived"] = float(derived)
        for name, lo, hi in loss_level_bins(cfg.schedule.num_train_timesteps):
            sel = loss_mask & (t >= lo) & (t < hi)
            if sel.any():
                logs[name] = float(per_frame.detach()[sel].mean())
    return loss, logs
