"""The world model: a causal, action-conditioned, diffusion-forcing DiT with CogVideoX's layout.

``WorldModel(cfg)(x, t, text, trajectory=None, actions=None) -> v``

* ``x``: noisy latents ``(B, T, C, h, w)`` (CogVideoX VAE latents, scaled by the VAE's scaling factor);
* ``t``: integer noise levels ``(B, T)`` in ``[0, N)``, ``N = objective.schedule.num_train_timesteps`` (CogVideoX:
  1000), one per latent frame (Diffusion Forcing); ``(B,)`` or a Python int broadcast over frames;
* ``text``: T5 embeddings ``(B, L, D_text)`` (any L: text tokens carry no position in CogVideoX-2B);
* ``trajectory``: ``(B, 8, 3)`` ego-frame waypoints or None (→ the null trajectory);
* ``actions``: ``(B, T, A)`` float or ``(B, T)`` int ids, or None (→ the null action at every frame).

Returns the v-prediction with ``x``'s shape and dtype. The model is the network only: the diffusion objective
(``resim.diffusion.training_losses(model, batch, objective)``) and the sampler (``resim.sample``) take it
as an argument, with the noise schedule from the run's config (``resim.train.tasks.world_model.TrainableWorldModel`` binds the
two for the trainer).

Noise-level rule for the text tokens. Video tokens of frame f are modulated (AdaLN) by the embedding of
t[:, f] (+ frame f's action). The text tokens need one embedding too. With ``causal=True`` we use the
embedding of a *fixed* level (``text_timestep_value``, default 0 = "clean", a state the pretrained model saw
at its last denoising steps). Any rule reading the frames' levels (the max, the mean, the last frame's) would
make the text stream – which every frame attends to – depend on the level of the frame currently being
denoised: the history frames' features would then change at every denoising step of a new frame (no KV
cache possible) and frame f's output would depend on frame f+1's noise level, breaking causality. With
``causal=False`` (full-sequence, as pretrained) the default is the largest frame level, which equals the
shared level when all frames share one, i.e. exactly the pretrained model.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

import torch
from torch import nn
from torch.utils.checkpoint import checkpoint

from resim.config import save
from resim.models.world.attention import KVCache, block_causal_block_mask, block_causal_mask
from resim.models.world.blocks import DiTBlock
from resim.models.world.cogvideox import cogvideox_num_train_timesteps, load_cogvideox_state
from resim.models.world.conditioning import ActionEncoder, TextPooler, TrajectoryEncoder
from resim.models.world.config import (WorldModelConfig, check_attention_backend, check_pretrained_noise_levels,
                                    config_from_cogvideox)
from resim.models.world.embeddings import PatchEmbed, TimestepMLP, sincos_pos_embed_3d, timestep_embedding
from resim.models.world.local_head import LocalHead

NEW_MODULE_PREFIXES = ("trajectory_encoder.", "action_encoder.", "text_pooler.", "local_head.")


class AdaNormOut(nn.Module):
    """Final AdaLN (diffusers ``AdaLayerNorm`` with chunk_dim=1: shift first), applied per frame."""

    def __init__(self, cond_dim: int, dim: int, elementwise_affine: bool, eps: float):
        super().__init__()
        self.silu = nn.SiLU()
        self.linear = nn.Linear(cond_dim, 2 * dim)
        self.norm = nn.LayerNorm(dim, eps=eps, elementwise_affine=elementwise_affine)

    def forward(self, video: torch.Tensor, temb_frames: torch.Tensor) -> torch.Tensor:
        b, tn, d = video.shape
        t = temb_frames.shape[1]
        shift, scale = self.linear(self.silu(temb_frames)).chunk(2, dim=-1)
        out = self.norm(video).view(b, t, tn // t, d) * (1 + scale[:, :, None]) + shift[:, :, None]
        return out.reshape(b, tn, d)


class WorldModel(nn.Module):
    """See the module docstring. Parameter names of the DiT part equal diffusers' CogVideoX ones."""

    def __init__(self, cfg: WorldModelConfig):
        super().__init__()
        self.cfg = cfg
        d, dt = cfg.hidden_dim, cfg.time_embed_dim
        self.patch_embed = PatchEmbed(cfg.patch_size, cfg.in_channels, d, cfg.text_embed_dim, bias=cfg.patch_bias)
        self.time_embedding = TimestepMLP(d, dt)
        self.transformer_blocks = nn.ModuleList([
            DiTBlock(d, cfg.num_attention_heads, cfg.attention_head_dim, dt, cfg.attention_bias,
                     cfg.norm_elementwise_affine, cfg.norm_eps) for _ in range(cfg.num_layers)])
        self.norm_final = nn.LayerNorm(d, cfg.norm_eps, cfg.norm_elementwise_affine)
        self.norm_out = AdaNormOut(dt, d, cfg.norm_elementwise_affine, cfg.norm_eps)
        self.proj_out = nn.Linear(d, cfg.patch_size * cfg.patch_size * cfg.out_channels)
        self.trajectory_encoder = TrajectoryEncoder(cfg.trajectory, d) if cfg.trajectory.enabled else None
        self.action_encoder = ActionEncoder(cfg.actions, dt) if cfg.actions.kind != "none" else None
        self.text_pooler = TextPooler(cfg.text_pool, cfg.text_embed_dim, dt) if cfg.text_pool.enabled else None
        self.local_head = (LocalHead(cfg.local_head, cfg.in_channels, cfg.out_channels, dt)
                           if cfg.local_head.enabled else None)

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_cogvideox(cls, src: Any, causal: bool = True, num_train_timesteps: int | None = None,
                       init_kwargs: dict | None = None, **overrides: Any) -> "WorldModel":
        """Build from a diffusers ``CogVideoXTransformer3DModel`` (instance) or a local folder it was saved to
        (``save_pretrained``; a pipeline folder with a ``transformer/`` subfolder also works).

        All DiT weights are copied; the trajectory/action encoders start at zero output, so with
        ``causal=False``, one shared noise level and no trajectory/actions the output equals the source model's.
        ``overrides`` are :class:`WorldModelConfig` fields (nested dicts for ``trajectory``/``actions``).
        ``num_train_timesteps``: the noise levels the model will be trained or sampled with (the objective's
        ``schedule``); a pipeline folder's ``scheduler/`` must have as many (CogVideoX: 1000): the timestep
        embedding is tied to them (ConfigError otherwise, before any weight is read). ``init_kwargs``: further
        arguments of the (sub)class's constructor.
        """
        if num_train_timesteps is not None:
            check_pretrained_noise_levels(num_train_timesteps, cogvideox_num_train_timesteps(src))
        config, state = load_cogvideox_state(src)
        cfg = config_from_cogvideox(config, causal=causal, **overrides)
        model = cls(cfg, **(init_kwargs or {}))
        model.load_pretrained_dit(state)
        return model

    def load_pretrained_dit(self, state: Mapping[str, torch.Tensor]) -> None:
        """Copy a CogVideoX transformer state dict; every DiT tensor must be present, nothing else unknown."""
        state = {k: v for k, v in state.items() if k != "patch_embed.pos_embedding"}  # sin-cos: recomputed
        own = self.state_dict()
        missing = [k for k in own if k not in state and not k.startswith(NEW_MODULE_PREFIXES)]
        unexpected = [k for k in state if k not in own]
        bad_shape = [f"{k}: {tuple(v.shape)} vs {tuple(own[k].shape)}" for k, v in state.items()
                     if k in own and tuple(v.shape) != tuple(own[k].shape)]
        if missing or unexpected or bad_shape:
            raise ValueError(f"CogVideoX weights do not fit this config: missing={missing[:8]} "
                             f"unexpected={unexpected[:8]} shape mismatches={bad_shape[:8]}")
        self.load_state_dict(state, strict=False)

    def set_attention_backend(self, backend: str) -> None:
        """Switch the kernel used for the block-causal mask: ``"sdpa"`` or ``"flex"`` (see ``config.py``).

        Weights are unaffected and outputs agree up to rounding, so e.g. a checkpoint trained with ``"sdpa"``
        can be sampled with ``"flex"``. Takes effect at the next forward.
        """
        check_attention_backend(backend)
        self.cfg.attention_backend = backend

    def new_parameters(self) -> list[nn.Parameter]:
        """Parameters of the modules that CogVideoX does not have (trajectory and action encoders)."""
        return [p for n, p in self.named_parameters() if n.startswith(NEW_MODULE_PREFIXES)]

    # ------------------------------------------------------------------ forward
    def _frame_levels(self, t: torch.Tensor | int, b: int, n_frames: int, device: torch.device) -> torch.Tensor:
        t = torch.as_tensor(t, device=device)
        if t.dim() == 0:
            t = t.expand(b, n_frames)
        elif t.dim() == 1:
            t = t[:, None].expand(b, n_frames)
        if tuple(t.shape) != (b, n_frames):
            raise ValueError(f"t must be (B, T_lat) = {(b, n_frames)}, got {tuple(t.shape)}")
        return t

    def _embed_levels(self, t: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
        emb = timestep_embedding(t, self.cfg.hidden_dim, self.cfg.flip_sin_to_cos, self.cfg.freq_shift)
        return self.time_embedding(emb.to(dtype))

    def forward(self, x: torch.Tensor, t: torch.Tensor | int, text: torch.Tensor | None,
                trajectory: torch.Tensor | None = None, actions: torch.Tensor | None = None, *,
                trajectory_keep: torch.Tensor | None = None, action_keep: torch.Tensor | None = None,
                kv_cache: KVCache | None = None, return_kv_cache: bool = False):
        """v-prediction ``(B, T, C, h, w)``; with ``return_kv_cache`` also the :class:`KVCache` of all frames.

        ``trajectory_keep`` (B,) / ``action_keep`` (B, T) bool: False → null embedding (condition dropout).
        ``kv_cache``: keys/values of text + ``kv_cache.num_frames`` earlier frames (from a previous call with
        ``return_kv_cache=True``); then ``x``/``t``/``actions`` hold only the new frames (absolute indices
        ``kv_cache.num_frames …``), ``text`` is ignored (its keys/values are cached) and ``trajectory`` must be the
        one the cache was built with. Requires ``causal=True``. The result equals the uncached call on the
        concatenated frames, restricted to the new ones.
        """
        cfg = self.cfg
        if x.dim() != 5 or x.shape[2] != cfg.in_channels:
            raise ValueError(f"x must be (B, T, {cfg.in_channels}, h, w), got {tuple(x.shape)}")
        b, nf, _, h, w = x.shape
        p = cfg.patch_size
        if h % p or w % p:
            raise ValueError(f"latent size {(h, w)} not divisible by patch size {p}")
        if kv_cache is not None and not cfg.causal:
            raise ValueError("kv_cache needs causal=True: without the block-causal mask a prefix's keys/values "
                             "depend on the frames after it")
        dtype = x.dtype
        t = self._frame_levels(t, b, nf, x.device)
        temb = self._embed_levels(t, dtype)                                      # (B, T, D_t)
        if self.action_encoder is not None:
            if actions is None:
                temb = temb + self.action_encoder.null.to(dtype)
            else:
                if actions.shape[:2] != (b, nf):
                    raise ValueError(f"actions must start with (B, T) = {(b, nf)}, got {tuple(actions.shape)}")
                temb = temb + self.action_encoder(actions, action_keep).to(dtype)
        elif actions is not None:
            raise ValueError("actions given but this model has actions.kind='none'")
        text_cond = None
        if self.text_pooler is not None:
            if kv_cache is None:
                if text is None or text.dim() != 3 or text.shape[0] != b:
                    raise ValueError(f"text must be (B={b}, L, {cfg.text_embed_dim})")
                text_cond = self.text_pooler(text.to(dtype)).to(dtype)
            elif kv_cache.text_cond is None:
                raise ValueError("this model pools the text but the kv_cache holds no pooled text (built by "
                                 "another model?)")
            else:
                text_cond = kv_cache.text_cond
            temb = temb + text_cond[:, None]

        # --- tokens
        prefix = kv_cache.num_frames if kv_cache is not None else 0
        video = self.patch_embed.video(x)                                       # (B, T, n, D)
        n = video.shape[2]
        pos = sincos_pos_embed_3d(cfg.hidden_dim, (h // p, w // p), nf, cfg.spatial_interpolation_scale,
                                  cfg.temporal_interpolation_scale, frame_offset=prefix, device=x.device)
        video = video + pos.to(dtype)
        if self.trajectory_encoder is not None:
            video = video + self.trajectory_encoder(trajectory, trajectory_keep, batch_size=b, dtype=dtype)[:, None, None]
        elif trajectory is not None:
            raise ValueError("trajectory given but this model has trajectory.enabled=false")
        video = video.reshape(b, nf * n, -1)

        if kv_cache is None:
            if text is None or text.dim() != 3 or text.shape[0] != b:
                raise ValueError(f"text must be (B={b}, L, {cfg.text_embed_dim})")
            txt = self.patch_embed.text(text.to(dtype))
            rule = cfg.resolved_text_timestep
            t_text = t.max(dim=1).values if rule == "max" else torch.full((b,), cfg.text_timestep_value, device=x.device)
            temb_text = self._embed_levels(t_text, dtype)
            if text_cond is not None:
                temb_text = temb_text + text_cond
            text_len = txt.shape[1]
        else:
            if kv_cache.tokens_per_frame != n:
                raise ValueError(f"cache has {kv_cache.tokens_per_frame} tokens per frame, x has {n}")
            txt, temb_text, text_len = None, None, kv_cache.text_len
        mask = None
        if cfg.causal:
            # one mask per forward, shared by every layer; the flex BlockMask is also cached across forwards
            build = block_causal_block_mask if cfg.attention_backend == "flex" else block_causal_mask
            mask = build(text_len, n, nf, prefix, with_text_queries=kv_cache is None, device=x.device)

        # --- blocks
        keys, values = [], []
        for i, blk in enumerate(self.transformer_blocks):
            past = (kv_cache.keys[i], kv_cache.values[i]) if kv_cache is not None else None
            if (cfg.gradient_checkpointing and torch.is_grad_enabled()
                    and i % max(1, cfg.gradient_checkpointing_every) == 0):
                video, txt, kv = checkpoint(blk, video, txt, temb, temb_text, mask, past, return_kv_cache,
                                             use_reentrant=False)
            else:
                video, txt, kv = blk(video, txt, temb, temb_text, mask, past, return_kv_cache)
            if return_kv_cache:
                keys.append(kv[0])
                values.append(kv[1])

        # --- output
        video = self.norm_out(self.norm_final(video), temb)
        out = self.proj_out(video)                                              # (B, T*n, p*p*C)
        out = out.reshape(b, nf, h // p, w // p, -1, p, p).permute(0, 1, 4, 2, 5, 3, 6).flatten(5, 6).flatten(3, 4)
        if self.local_head is not None:
            out = self.local_head(x, out, temb)
        if return_kv_cache:
            return out, KVCache(keys, values, text_len, n, prefix + nf, text_cond)
        return out


def save_config(model: WorldModel, path: str | Path) -> Path:
    """Write the resolved model config (YAML) next to an output."""
    return save(model.cfg, path)
