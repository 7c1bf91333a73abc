"""Typed config of the world model, with named presets from ``tiny`` to ``cogvideox-2b``.

The DiT fields mirror diffusers' ``CogVideoXTransformer3DModel`` config (same names where they exist) so a
CogVideoX checkpoint's ``config.json`` maps onto them one to one (:func:`config_from_cogvideox`). The new
fields configure what ReSim (arXiv 2506.09981, App. B.2) and Vid2World (arXiv 2505.14357, Sec. 4) add:
causality, the text noise-level rule, the trajectory encoder and per-frame actions.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Literal, Mapping

from resim.config import ConfigError, from_dict

# diffusers config keys we accept and copy; keys we must refuse when set to anything but the default
_COGVIDEOX_KEYS = (
    "num_attention_heads", "attention_head_dim", "in_channels", "out_channels", "flip_sin_to_cos",
    "freq_shift", "time_embed_dim", "text_embed_dim", "num_layers", "attention_bias", "sample_width",
    "sample_height", "sample_frames", "patch_size", "temporal_compression_ratio", "max_text_seq_length",
    "activation_fn", "timestep_activation_fn", "norm_elementwise_affine", "norm_eps",
    "spatial_interpolation_scale", "temporal_interpolation_scale", "patch_bias",
)
_UNSUPPORTED = {  # key: the only value we support (CogVideoX-2B's); others would load wrongly
    "ofs_embed_dim": None,
    "patch_size_t": None,
    "use_rotary_positional_embeddings": False,
    "use_learned_positional_embeddings": False,
}

ATTENTION_BACKENDS = ("sdpa", "flex")


def check_attention_backend(backend: str) -> None:
    if backend not in ATTENTION_BACKENDS:
        raise ConfigError(f"attention_backend={backend!r} is not one of {ATTENTION_BACKENDS}")


@dataclass
class TrajectoryEncoderConfig:
    """ReSim's trajectory encoder: waypoints → 2 attention blocks → linear head (App. B.2)."""
    enabled: bool = True
    num_waypoints: int = 8
    waypoint_dim: int = 3              # x m, y m, yaw rad (ego frame: x fwd, y left, yaw left +)
    hidden_dim: int = 64
    num_heads: int = 4
    num_layers: int = 2
    # divide waypoints by this before the encoder so typical values are O(1): (x m, y m, yaw rad)
    input_scale: tuple[float, float, float] = (20.0, 5.0, 0.5)

    def __post_init__(self) -> None:
        if self.hidden_dim % self.num_heads:
            raise ConfigError(f"trajectory.hidden_dim={self.hidden_dim} must be divisible by num_heads={self.num_heads}")
        if len(self.input_scale) != self.waypoint_dim or any(s <= 0 for s in self.input_scale):
            raise ConfigError(f"trajectory.input_scale must be {self.waypoint_dim} positive numbers")


@dataclass
class ActionConfig:
    """Vid2World's per-frame actions, added to each frame's noise-level embedding (Sec. 4.2)."""
    kind: Literal["none", "continuous", "discrete"] = "continuous"
    action_dim: int = 3                # continuous: (dx m, dy m, dyaw rad) ego motion over the latent frame
    num_actions: int = 0               # discrete: size of the embedding table
    hidden_dim: int = 64
    input_scale: tuple[float, ...] = (2.0, 0.5, 0.1)  # continuous: divide actions by this (per component)

    def __post_init__(self) -> None:
        if self.kind == "discrete" and self.num_actions < 1:
            raise ConfigError("actions.num_actions must be >= 1 for discrete actions")
        if self.kind == "continuous" and len(self.input_scale) != self.action_dim:
            raise ConfigError(f"actions.input_scale must have action_dim={self.action_dim} entries")
        # actions are divided by it (conditioning.ActionEncoder): a zero gives inf/NaN inputs, a negative flips
        # the action's sign; checked for every kind so a config that switches kind later cannot carry it silently
        if any(not s > 0 for s in self.input_scale):
            raise ConfigError(f"actions.input_scale must be positive numbers, got {tuple(self.input_scale)}")

    @property
    def takes_ego_motion(self) -> bool:
        """Continuous (dx, dy, dyaw) actions: the form a trajectory gives (``actions_from_trajectory``)."""
        return self.kind == "continuous" and self.action_dim == 3


@dataclass
class TextPoolConfig:
    """A pooled prompt vector added to every frame's noise-level embedding (AdaLN), beside joint attention.

    CogVideoX-2B reads the prompt only through joint attention over the T5 tokens. A small model trained briefly
    learns to ignore that path when the history already predicts the future
    (docs/lab/2026-11-26-synth-world-stage-chain.md, "Experiments beside the chain"); a
    pooled text vector in the modulation, as SD3's pooled projection or DiT's class embedding, is a direct path.
    Disabled by default: CogVideoX checkpoints have no such module (it starts at zero output when enabled).
    """
    enabled: bool = False
    hidden_dim: int = 128
    num_heads: int = 4                 # heads of the learned-query attention pooling over the text tokens

    def __post_init__(self) -> None:
        if self.hidden_dim % self.num_heads:
            raise ConfigError(f"text_pool.hidden_dim={self.hidden_dim} must be divisible by num_heads={self.num_heads}")


@dataclass
class LocalHeadConfig:
    """A small per-frame convolutional head added to the DiT's output (``local_head.py``).

    A patch of ``p x p`` latent pixels is one token: with large patches (the small synthetic model's p = 8) the
    transformer must carry every latent pixel's noise through its blocks to predict v, and its one-step clean
    estimate at mid noise levels keeps a speckle the sampler then draws. A convolution sees each pixel and its
    neighbours, as U-ViT's extra 3x3 convolution after the patch-to-image projection (Bao et al. 2023, Sec. 3)
    and DIAMOND's U-Net denoiser. Disabled by default: CogVideoX checkpoints have no such module (it starts at
    zero output when enabled).
    """
    enabled: bool = False
    channels: int = 64
    num_layers: int = 3                # 3x3 convolutions; the last one starts at zero

    def __post_init__(self) -> None:
        if self.channels < 1 or self.num_layers < 2:
            raise ConfigError(f"local_head: channels >= 1 and num_layers >= 2, got {self.channels}, {self.num_layers}")


@dataclass
class WorldModelConfig:
    """The causal, action-conditioned DiT. Shapes: latents (B, T_lat, in_channels, h, w)."""
    # --- CogVideoX layout (names as in diffusers) ---
    num_attention_heads: int = 30
    attention_head_dim: int = 64
    in_channels: int = 16
    out_channels: int = 16
    flip_sin_to_cos: bool = True
    freq_shift: int = 0
    time_embed_dim: int = 512
    text_embed_dim: int = 4096
    num_layers: int = 30
    attention_bias: bool = True
    sample_width: int = 90             # latent width the checkpoint was trained at (positions are recomputed)
    sample_height: int = 60
    sample_frames: int = 49            # in *pixel* frames, as diffusers counts them
    patch_size: int = 2
    temporal_compression_ratio: int = 4
    max_text_seq_length: int = 226     # text length L the sin-cos layout reserves (text gets no position)
    activation_fn: str = "gelu-approximate"
    timestep_activation_fn: str = "silu"
    norm_elementwise_affine: bool = True
    norm_eps: float = 1e-5
    spatial_interpolation_scale: float = 1.875
    temporal_interpolation_scale: float = 1.0
    patch_bias: bool = True
    # --- world model ---
    causal: bool = True                # block-causal mask over latent frames (Vid2World Sec. 4.1)
    # noise level whose embedding modulates the text tokens: "fixed" uses text_timestep_value for every
    # sample (required with causal=True, see dit.py), "max" the largest frame level (== the shared level when
    # all frames share one, i.e. the pretrained model's behaviour); "auto": fixed if causal else max.
    text_timestep: Literal["auto", "fixed", "max"] = "auto"
    text_timestep_value: int = 0
    trajectory: TrajectoryEncoderConfig = field(default_factory=TrajectoryEncoderConfig)
    actions: ActionConfig = field(default_factory=ActionConfig)
    text_pool: TextPoolConfig = field(default_factory=TextPoolConfig)
    local_head: LocalHeadConfig = field(default_factory=LocalHeadConfig)
    gradient_checkpointing: bool = False
    gradient_checkpointing_every: int = 1   # with it on, blocks i % k == 0 recompute (selective AC); 1 = all
    # kernel for the block-causal mask (attention.py, flex.py): "sdpa" = F.scaled_dot_product_attention with a
    # boolean (S, S) mask (cuDNN attention on an H100, every tile computed); "flex" = flex_attention with a
    # BlockMask that skips fully masked tiles (compiled on CUDA; eager and slower than sdpa on CPU). Outputs
    # agree up to rounding, weights are the same: a model can be trained with one and sampled with the other
    # (WorldModel.set_attention_backend). Unmasked attention (causal=False) always runs SDPA.
    attention_backend: Literal["sdpa", "flex"] = "sdpa"

    def __post_init__(self) -> None:
        if self.activation_fn != "gelu-approximate" or self.timestep_activation_fn != "silu":
            raise ConfigError("only activation_fn='gelu-approximate' and timestep_activation_fn='silu' "
                              "(CogVideoX's) are implemented")
        if (self.num_attention_heads * self.attention_head_dim) % 16:
            raise ConfigError("hidden size (heads * head_dim) must be divisible by 16 for 3D sin-cos positions")
        if self.text_timestep_value < 0:   # the upper bound is the schedule's: check_noise_levels
            raise ConfigError(f"text_timestep_value={self.text_timestep_value} must be >= 0")
        check_attention_backend(self.attention_backend)
        if self.causal and self.text_timestep == "max":
            raise ConfigError("text_timestep='max' with causal=True would make every frame depend on the "
                              "noise level of later frames; use 'fixed' (or 'auto')")

    @property
    def hidden_dim(self) -> int:
        return self.num_attention_heads * self.attention_head_dim

    @property
    def resolved_text_timestep(self) -> str:
        if self.text_timestep == "auto":
            return "fixed" if self.causal else "max"
        return self.text_timestep


PRESETS: dict[str, dict[str, Any]] = {
    # trains in seconds on CPU; the same layout as the tiny diffusers config in shared/ENVIRONMENT.md
    "tiny": dict(
        num_attention_heads=2, attention_head_dim=16, in_channels=16, out_channels=16, time_embed_dim=32,
        text_embed_dim=64, num_layers=2, sample_width=12, sample_height=8, sample_frames=49,
        max_text_seq_length=16,
        trajectory=dict(hidden_dim=32, num_heads=2), actions=dict(hidden_dim=32),
    ),
    "small": dict(
        num_attention_heads=8, attention_head_dim=32, time_embed_dim=128, text_embed_dim=512, num_layers=8,
        sample_width=56, sample_height=32, trajectory=dict(hidden_dim=128), actions=dict(hidden_dim=128),
    ),
    # the synthetic world's world model (configs/models/synth-world, docs/models/synth-world.md): 5.0 M
    # parameters. Latents of configs/models/synth-vae at 64x96 px are 8x12 (24 tokens of 2x2 patches per
    # latent frame, 312 for a 13-frame clip) + 64 text tokens (the placeholder T5 at encode.max_text_tokens
    # = 64). Width 192 and 6 blocks: 0.47 s per batch of 8 on a 2-core CPU, 4,000 steps in ~32 min; the tiny
    # preset (width 32, 2 blocks) cannot learn a world.
    "synth": dict(
        num_attention_heads=6, attention_head_dim=32, in_channels=16, out_channels=16, time_embed_dim=128,
        text_embed_dim=64, num_layers=6, sample_width=12, sample_height=8, sample_frames=49,
        max_text_seq_length=64,
        trajectory=dict(hidden_dim=128, num_heads=4), actions=dict(hidden_dim=128),
    ),
    # THUDM/CogVideoX-2b transformer/config.json
    "cogvideox-2b": dict(
        num_attention_heads=30, attention_head_dim=64, time_embed_dim=512, text_embed_dim=4096, num_layers=30,
        sample_width=90, sample_height=60, sample_frames=49, max_text_seq_length=226,
        trajectory=dict(hidden_dim=512, num_heads=8), actions=dict(hidden_dim=512),
    ),
}


def check_noise_levels(cfg: WorldModelConfig, num_train_timesteps: int) -> None:
    """The noise levels of a model trained with ``num_train_timesteps`` levels (``objective.schedule``) are
    ``[0, N)``: ``text_timestep_value`` must be one of them."""
    n = int(num_train_timesteps)
    if not 0 <= cfg.text_timestep_value < n:
        raise ConfigError(f"text_timestep_value={cfg.text_timestep_value} not in [0, {n}) "
                          f"(objective.schedule.num_train_timesteps = {n})")


def check_pretrained_noise_levels(num_train_timesteps: int, pretrained_num_train_timesteps: int | None) -> None:
    """Pretrained weights whose scheduler had another number of levels (CogVideoX: 1000) cannot be trained or
    sampled with ``num_train_timesteps``: their timestep embedding learnt what each level ``t`` means."""
    if pretrained_num_train_timesteps is not None and int(pretrained_num_train_timesteps) != int(num_train_timesteps):
        raise ConfigError(f"objective.schedule.num_train_timesteps={num_train_timesteps}, but the pretrained weights "
                          f"were trained with {pretrained_num_train_timesteps} noise levels (their "
                          "scheduler/scheduler_config.json): their timestep embedding cannot take another count")


def preset(name: str, **overrides: Any) -> WorldModelConfig:
    """A named preset with (nested-dict) overrides, validated."""
    if name not in PRESETS:
        raise ConfigError(f"unknown world-model preset {name!r}; known: {sorted(PRESETS)}")
    data = _merge(PRESETS[name], overrides)
    return from_dict(WorldModelConfig, data)


def _merge(base: Mapping[str, Any], upd: Mapping[str, Any]) -> dict[str, Any]:
    out = {k: (dict(v) if isinstance(v, Mapping) else v) for k, v in base.items()}
    for k, v in upd.items():
        if dataclasses.is_dataclass(v):
            v = dataclasses.asdict(v)
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = _merge(out[k], v)
        else:
            out[k] = v
    return out


def config_from_cogvideox(diffusers_config: Mapping[str, Any], **overrides: Any) -> WorldModelConfig:
    """Map a diffusers ``CogVideoXTransformer3DModel`` config (dict) onto :class:`WorldModelConfig`.

    Raises ``ConfigError`` for variants whose weights would not load faithfully (rotary positions as in
    CogVideoX-5B, temporal patching as in 1.5, the ``ofs`` embedding of 5B-I2V).
    """
    for key, ok in _UNSUPPORTED.items():
        if diffusers_config.get(key, ok) != ok:
            raise ConfigError(f"CogVideoX config {key}={diffusers_config[key]!r} is not supported "
                              f"(only {ok!r}, as in CogVideoX-2B)")
    data: dict[str, Any] = {k: diffusers_config[k] for k in _COGVIDEOX_KEYS if k in diffusers_config}
    if data.get("out_channels") is None:
        data["out_channels"] = data.get("in_channels", 16)
    hidden = data.get("num_attention_heads", 30) * data.get("attention_head_dim", 64)
    # new modules sized to the DiT unless overridden
    data["trajectory"] = {"hidden_dim": min(512, hidden), "num_heads": 8 if min(512, hidden) % 8 == 0 else 2}
    data["actions"] = {"hidden_dim": min(512, hidden)}
    return from_dict(WorldModelConfig, _merge(data, overrides))
