"""World model: causal, action-conditioned, diffusion-forcing DiT loading CogVideoX weights."""
from resim.models.world.attention import KVCache, block_causal_mask
from resim.models.world.causalize import causalize
from resim.models.world.conditioning import actions_from_trajectory
from resim.models.world.config import PRESETS, WorldModelConfig, config_from_cogvideox, preset
from resim.models.world.dit import WorldModel

__all__ = ["KVCache", "PRESETS", "WorldModel", "WorldModelConfig", "actions_from_trajectory", "block_causal_mask",
           "causalize", "config_from_cogvideox", "preset"]
