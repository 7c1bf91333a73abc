"""How Video2Reward is trained (ReSim appendix B.2): :class:`RewardTrainConfig`, a small model's training
(``resim.train.config.SmallTrainConfig``: epochs, batch, seed, ``optim``) with the model and its data.

Presets: ``tiny`` (placeholder backbone, 56 px, CPU tests and demo), ``synthetic`` (tiny + whole-episode window for
`resim synth` worlds) and ``resim`` (DINOv2 at 224x224 as in the paper).
"""
from __future__ import annotations

from dataclasses import dataclass, field

from resim.models.reward.config import RewardDataConfig, RewardModelConfig
from resim.train.config import OptimConfig, SmallTrainConfig


@dataclass
class RewardTrainConfig(SmallTrainConfig):
    model: RewardModelConfig = field(default_factory=RewardModelConfig)
    data: RewardDataConfig = field(default_factory=RewardDataConfig)
    # ReSim B.2: AdamW, learning rate 1e-3, 20 epochs; a constant rate and no clipping (ReSim states none)
    optim: OptimConfig = field(default_factory=lambda: OptimConfig(lr=1e-3, weight_decay=0.01, grad_clip_norm=0.0))
    epochs: int = 20
    use_stored_features: bool = True  # use dino.npy when every sample has it and the id matches


PRESETS: dict[str, dict] = {
    "tiny": {},
    "resim": {"model": {"image_size_px": 224, "backbone_dir": "models/dinov2-small", "head_dim": 256,
                        "num_heads": 8, "mlp_hidden_dim": 512, "num_frames": 8, "frame_step": 5},
              "batch_size_per_gpu": 32},
    # The synthetic world's CARLA-layout episodes (8 s at 10 Hz, `resim synth --preset tiny`): one window
    # spans 78 of the 80 frames, so the episode-level infraction (a late crash, a stop of >= 3 s) is in
    # view (docs/reward.md, "what the frames show"); frozen random placeholder backbone, head only.
    # temporal_diff: the head also sees each frame's feature change (stops show as little change late in
    # the episode); it was the change that lifted the ranking on every held-out split
    # (docs/lab/2026-11-22-reward-synthetic-world.md, "What changed, and what each change did").
    "synthetic": {"model": {"num_frames": 8, "frame_step": 11, "head_dim": 32, "num_heads": 2,
                            "mlp_hidden_dim": 64, "dropout": 0.1, "temporal_diff": True},
                  "epochs": 100},
}
