"""Config validation: bad values are ConfigErrors naming the key, never ZeroDivisionError or a silent nan."""
import pytest

from resim.config import ConfigError, load
from resim.models.reward.config import RewardTrainConfig


@pytest.mark.parametrize("override, match", [
    ("model.num_heads=0", "num_heads must be >= 1"),          # was ZeroDivisionError (head_dim % 0)
    ("model.head_dim=0", "head_dim must be >= 1"),
    ("model.mlp_hidden_dim=-3", "mlp_hidden_dim must be >= 1"),
    ("lr=.nan", "lr must be a finite number > 0"),             # nan passed `lr <= 0`
    ("lr=1e999", "lr must be a finite number > 0"),            # inf
    ("lr=-.inf", "lr must be a finite number > 0"),
    ("weight_decay=-5", "weight_decay must be"),
    ("weight_decay=.nan", "weight_decay must be"),
    ("grad_clip_norm=-1", "grad_clip_norm must be"),
    ("seed=-1", "seed must be >= 0"),
    ("model.dropout=.nan", "dropout must be in"),
    ("data.heldout_fraction=.nan", "heldout_fraction must be in"),
])
def test_bad_values_are_config_errors(override, match):
    with pytest.raises(ConfigError, match=match):
        load(RewardTrainConfig, overrides=[override])


def test_valid_values_still_load():
    cfg = load(RewardTrainConfig, overrides=["lr=3e-4", "grad_clip_norm=0", "weight_decay=0", "model.num_heads=2"])
    assert cfg.lr == 3e-4 and cfg.model.num_heads == 2
