"""The world model as a trainable unit (registry name ``world``): build, freeze per stage, LoRA, hooks.

``build_world(model_cfg, device=...)`` validates ``WorldTrainConfig`` (the ``model:`` section of a
run config), builds ``resim.models.world.dit.WorldModel`` from a preset (random init, or CogVideoX
weights from a local folder with ``pretrained``), optionally loads the previous stage's weights
(``init_weights``: a run's ``final/model.safetensors``), applies LoRA and sets which parameters train
(ReSim Table S.1: stage 1 the DiT; stage 2 LoRA + trajectory/action encoders with the DiT frozen;
stage 3 everything). The objective is ``resim.diffusion.training_losses``, bound by
``TrainableWorldModel.loss`` (the network itself, ``WorldModel``, knows no objective).

``TrainableWorldModel`` adds the trainer/launcher hooks: ``fsdp_units`` (the transformer blocks),
``set_activation_checkpointing``, ``tokens_per_sample``, ``flops_per_sample`` (for MFU) and
``activation_bytes_per_sample`` (the dry run's memory estimate).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Optional

import torch

from resim.config import ConfigError, from_dict
from resim.diffusion.config import ObjectiveConfig
from resim.diffusion.losses import training_losses
from resim.models.exported import ExportError, read_weights
from resim.models.world.blocks import LayerNormZero
from resim.models.world.config import check_noise_levels, preset as model_preset
from resim.models.world.dit import NEW_MODULE_PREFIXES, WorldModel
from resim.models.world.lora import add_lora, is_lora_param, pre_peft_name, to_peft_layout


@dataclass
class WorldTrainConfig:
    preset: str = "tiny"                       # resim.models.world.config.PRESETS (tiny | small | cogvideox-2b)
    overrides: dict[str, Any] = field(default_factory=dict)   # WorldModelConfig fields
    pretrained: Optional[Path] = None          # local CogVideoX folder (diffusers save_pretrained layout)
    init_weights: Optional[Path] = None        # previous stage: RUN_DIR/final/model.safetensors (or ema.safetensors)
    objective: dict[str, Any] = field(default_factory=dict)   # resim.diffusion.config.ObjectiveConfig fields
    trainable: Literal["all", "dit", "lora+new", "new"] = "all"
    lora_rank: int = 0                         # 0: no LoRA
    lora_alpha: float = 0.0                    # 0: = rank (scale 1)
    lora_targets: tuple[str, ...] = ("to_q", "to_k", "to_v", "to_out.0")
    latent_hw: tuple[int, int] = (0, 0)        # (h, w) of the latents, for the dry run's estimates; 0 = sample size
    latent_frames: int = 13                    # T_lat, for the dry run's estimates

    def __post_init__(self):
        if self.lora_rank < 0:
            raise ConfigError("model.lora_rank must be >= 0")
        if self.trainable == "lora+new" and self.lora_rank == 0:
            raise ConfigError("model.trainable='lora+new' needs model.lora_rank > 0")


class TrainableWorldModel(WorldModel):
    """``WorldModel`` bound to its diffusion objective for the trainer (``loss(batch)``), plus the hooks the trainer
    and the launcher's dry run use. Same parameter names and state dict as ``WorldModel``: the objective is
    configuration (the run's ``model.objective``), not weights."""

    def __init__(self, cfg, objective: ObjectiveConfig | None = None):
        super().__init__(cfg)
        self.objective = objective if objective is not None else ObjectiveConfig()
        check_noise_levels(cfg, self.objective.schedule.num_train_timesteps)

    @classmethod
    def from_cogvideox(cls, src: Any, causal: bool = True, objective: ObjectiveConfig | None = None,
                       **overrides: Any) -> "TrainableWorldModel":
        objective = objective if objective is not None else ObjectiveConfig()
        return super().from_cogvideox(src, causal=causal, num_train_timesteps=objective.schedule.num_train_timesteps,
                                      init_kwargs={"objective": objective}, **overrides)

    # parameter names in checkpoints written before LoRA moved to peft, for resuming them (resim.train.checkpoint.load)
    legacy_param_name = staticmethod(pre_peft_name)

    def loss(self, batch: Any) -> tuple[torch.Tensor, dict[str, float]]:
        """The diffusion objective on one batch (``resim.diffusion.training_losses``)."""
        return training_losses(self, batch, self.objective, ego_motion_actions=self.cfg.actions.takes_ego_motion)

    def fsdp_units(self):
        return list(self.transformer_blocks)

    def set_activation_checkpointing(self, on: bool = True, every_blocks: int = 1) -> None:
        self.cfg.gradient_checkpointing = bool(on)  # the DiT checkpoints its blocks itself
        self.cfg.gradient_checkpointing_every = int(every_blocks)

    def tokens_per_sample(self, batch: Any = None, latent_thw: tuple[int, int, int] | None = None) -> int:
        c = self.cfg
        if latent_thw is None:
            _, t, _, h, w = batch.latents.shape
        else:
            t, h, w = latent_thw
        return t * (h // c.patch_size) * (w // c.patch_size) + c.max_text_seq_length

    def flops_per_sample(self, batch: Any = None, latent_thw: tuple[int, int, int] | None = None) -> float:
        """Training FLOPs of one sample (forward + backward = 3 x forward; recompute not counted, as MFU
        conventionally excludes it): 6 x per-token block params x tokens + 6 x AdaLN modulation params x (T + 1)
        + attention 12 x layers x S^2 x d (all S^2 scores: SDPA's cuDNN kernel computes every tile with our mask;
        the flex backend skips ~45 % of them, but the count is kept the same so that MFU compares step times).

        The modulation linears (``norm1.linear``/``norm2.linear`` of each block: 21 % of CogVideoX-2B's block
        parameters) run once per frame embedding (T rows) and once on the text embedding, not once per token;
        counting them per token overstated the FLOPs (and MFU) by ~17 % at 256x448 (first H100 run)."""
        c = self.cfg
        s = self.tokens_per_sample(batch, latent_thw)
        t = int(batch.latents.shape[1]) if latent_thw is None else int(latent_thw[0])
        block_params, mod_params = self._block_param_counts()
        d = c.hidden_dim
        return (6.0 * (block_params - mod_params) * s + 6.0 * mod_params * (t + 1)
                + 12.0 * c.num_layers * s * s * d)

    def _block_param_counts(self) -> tuple[int, int]:
        """(all block parameters, AdaLN modulation parameters), counted once: the trainer asks every step, and
        walking the (FSDP-sharded) modules each time is wasted work on the hot path."""
        counts = getattr(self, "_flop_param_counts", None)
        if counts is None:
            blocks = sum(p.numel() for p in self.transformer_blocks.parameters())
            mod = sum(p.numel() for m in self.transformer_blocks.modules() if isinstance(m, LayerNormZero)
                      for p in m.linear.parameters())
            counts = self._flop_param_counts = (blocks, mod)
        return counts

    def activation_bytes_per_sample(self, latent_thw: tuple[int, int, int], checkpointing: bool,
                                    bytes_per_value: int = 2, every_blocks: int = 1) -> float:
        """Rough activation memory of one sample: ~34 values per token per hidden unit per block without
        checkpointing (Korthikanti et al. 2022, flash attention so no S^2 term); a checkpointed block keeps its
        inputs (2 tensors), and one block's worth is live while it recomputes. ``every_blocks``: only blocks
        i % k == 0 are checkpointed (selective AC)."""
        c = self.cfg
        s = self.tokens_per_sample(latent_thw=latent_thw)
        per_block = 34 * s * c.hidden_dim * bytes_per_value
        if checkpointing:
            ckpt_blocks = len(range(0, c.num_layers, max(1, every_blocks)))
            return (ckpt_blocks * 2 * s * c.hidden_dim * bytes_per_value + per_block
                    + (c.num_layers - ckpt_blocks) * per_block)
        return c.num_layers * per_block


def build_world(model_cfg: dict, *, device: str | torch.device = "cpu") -> TrainableWorldModel:
    cfg = from_dict(WorldTrainConfig, model_cfg, prefix="model")
    objective = from_dict(ObjectiveConfig, cfg.objective, prefix="model.objective")
    if cfg.pretrained is not None:
        if str(device) == "meta":
            raise ConfigError("model.pretrained cannot be loaded on the meta device (dry run): leave it unset")
        model = TrainableWorldModel.from_cogvideox(Path(cfg.pretrained), objective=objective, **cfg.overrides)
    else:
        with torch.device(device):
            model = TrainableWorldModel(model_preset(cfg.preset, **cfg.overrides), objective=objective)
    if cfg.lora_rank:
        add_lora(model, cfg.lora_targets, cfg.lora_rank, cfg.lora_alpha or float(cfg.lora_rank))
    if cfg.init_weights is not None:
        _load_init(model, Path(cfg.init_weights))
    for n, p in model.named_parameters():
        is_new = n.startswith(NEW_MODULE_PREFIXES)
        is_lora = is_lora_param(n)
        p.requires_grad_({"all": True, "dit": not is_new and not is_lora, "lora+new": is_new or is_lora,
                          "new": is_new}[cfg.trainable])
    # frozen DiT + LoRA: some blocks' frozen params are unused by DDP's reducer only if nothing trains there
    model.ddp_find_unused_parameters = False
    return model


def _load_init(model: torch.nn.Module, path: Path) -> None:
    """Load the previous stage's weights; only LoRA tensors and new conditioning modules (which start at zero
    output, so the loaded model computes what the previous stage did) may be missing; nothing may be unexpected."""
    if not path.is_file():
        raise ConfigError(f"model.init_weights={path} does not exist (expected RUN_DIR/final/model.safetensors)")
    try:   # a pickle or torch file: never unpickled, one line
        sd = to_peft_layout(read_weights(path), model)   # a stage-1 file, or LoRA in the pre-peft layout
    except ExportError as e:
        raise ConfigError(f"model.init_weights={e}") from None
    own = model.state_dict()
    missing = [k for k in own if k not in sd and not is_lora_param(k)
               and not k.startswith(NEW_MODULE_PREFIXES)]
    unexpected = [k for k in sd if k not in own]
    bad = [k for k in sd if k in own and tuple(sd[k].shape) != tuple(own[k].shape)]
    if missing or unexpected or bad:
        raise ConfigError(f"model.init_weights={path} does not fit this model: missing={missing[:5]} "
                          f"unexpected={unexpected[:5]} shape mismatch={bad[:5]}")
    model.load_state_dict(sd, strict=False)
