"""Typed configs for Video2Reward (ReSim appendix B.2).

``RewardModelConfig`` fixes everything that changes what the model computes
(backbone, input size, which frames of a clip it sees, head size); ``RewardDataConfig`` which clips carry labels
and how a window is cut from them. How the model is trained (optimiser, epochs, presets) is
``resim.train.tasks.reward.config.RewardTrainConfig``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from resim.config import ConfigError

PLACEHOLDER_BACKBONE_DIR = "configs/models/placeholder-dinov2-tiny"


@dataclass
class RewardModelConfig:
    # Local folder readable by transformers.Dinov2Model.from_pretrained (config.json [+ weights]).
    # A folder without weights is a placeholder: weights are built from `backbone_init_seed`.
    backbone_dir: str = PLACEHOLDER_BACKBONE_DIR
    backbone_init_seed: int = 0
    freeze_backbone: bool = True
    # Frames are resized to image_size_px x image_size_px (ReSim: 224) and ImageNet-normalised.
    image_size_px: int = 56
    # The model's window: num_frames frames taken every frame_step frames of the input video
    # (so one window spans (num_frames - 1) * frame_step + 1 input frames).
    num_frames: int = 8
    frame_step: int = 1
    # Backbone features are rounded to this dtype in the live path too, so that training on
    # stored dino.npy (float16, resim/shards/schema.py) and through the backbone sees identical inputs.
    feature_dtype: Literal["float16", "float32"] = "float16"
    # Head: project D -> head_dim, 2 factorised spatio-temporal blocks, mean-pool, MLP -> scalar.
    head_dim: int = 64
    num_heads: int = 4
    num_blocks: int = 2
    mlp_hidden_dim: int = 128
    dropout: float = 0.0
    head_init_seed: int = 0
    # Motion input: each frame's tokens are concatenated with their difference to the previous sampled
    # frame's (zeros for the first) before the head's projection (D -> 2D inputs). Still DINOv2 features
    # -> spatio-temporal attention -> scalar; it hands the head "how much changed" directly, which a
    # frozen random backbone's features otherwise bury (docs/reward.md: stops look like slow scenes).
    temporal_diff: bool = False
    # "sigmoid": the output is sigmoid(logit), in (0, 1) like the infraction score it predicts;
    # "none": the raw linear output (unbounded; the first reward runs used it).
    output_activation: Literal["sigmoid", "none"] = "sigmoid"

    def __post_init__(self):
        if self.image_size_px < 8:
            raise ConfigError(f"image_size_px must be >= 8, got {self.image_size_px}")
        if self.num_frames < 1 or self.frame_step < 1:
            raise ConfigError("num_frames and frame_step must be >= 1")
        # checked before the divisibility test below, which would otherwise divide by zero
        for name in ("head_dim", "num_heads", "mlp_hidden_dim"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.head_dim % self.num_heads:
            raise ConfigError(f"head_dim {self.head_dim} must be divisible by num_heads {self.num_heads}")
        if self.num_blocks < 1:
            raise ConfigError("num_blocks must be >= 1")
        if self.output_activation not in ("sigmoid", "none"):
            raise ConfigError(f"output_activation must be 'sigmoid' or 'none', got {self.output_activation!r}")
        if not 0.0 <= self.dropout < 1.0:  # false for nan too
            raise ConfigError(f"dropout must be in [0, 1), got {self.dropout}")

    @property
    def window_frames(self) -> int:
        """Input frames spanned by one model window."""
        return (self.num_frames - 1) * self.frame_step + 1


@dataclass
class RewardDataConfig:
    # Which clips carry labels: only those with an infraction score (CARLA-like / synthetic outcomes); which are
    # held out: the dataset's split (resim.shards.split), not a setting of the run.
    # Where a window is cut from a longer clip: "end" = the last window (the imagined future).
    clip_window: Literal["end", "start"] = "end"
