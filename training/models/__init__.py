"""World model: causal, action-conditioned, diffusion-forcing DiT loading CogVideoX weights."""
from training.models.attention import KVCache, block_causal_mask
from training.models.causalize import causalize
from training.models.conditioning import actions_from_trajectory
from training.models.config import PRESETS, WorldModelConfig, config_from_cogvideox, preset
from training.models.dit import WorldModel

__all__ = ["KVCache", "PRESETS", "WorldModel", "WorldModelConfig", "actions_from_trajectory", "block_causal_mask",
           "causalize", "config_from_cogvideox", "preset"]
