"""Config validation: bad values are ConfigErrors naming the key, never ZeroDivisionError or a silent nan."""
import pytest

from resim.config import ConfigError, load
from resim.train.tasks.reward.config import RewardTrainConfig


@pytest.mark.parametrize("override, match", [
    ("model.num_heads=0", "num_heads must be >= 1"),          # was ZeroDivisionError (head_dim % 0)
    ("model.head_dim=0", "head_dim must be >= 1"),
    ("model.mlp_hidden_dim=-3", "mlp_hidden_dim must be >= 1"),
    ("optim.lr=.nan", "optim.lr must be a finite number > 0"),   # nan passed `lr <= 0`
    ("optim.lr=1e999", "optim.lr must be a finite number > 0"),  # inf
    ("optim.lr=-.inf", "optim.lr must be a finite number > 0"),
    ("optim.weight_decay=-5", "weight_decay must be"),
    ("optim.weight_decay=.nan", "weight_decay must be"),
    ("optim.grad_clip_norm=.nan", "grad_clip_norm must be a finite number"),
    ("lr=1e-3", "unknown config key lr .*optim"),               # the optimiser is one nested section
    ("seed=-1", "seed must be >= 0"),
    ("model.dropout=.nan", "dropout must be in"),
    ("data.heldout_fraction=0.3", "unknown config key data.heldout_fraction"),   # the dataset's split now
])
def test_bad_values_are_config_errors(override, match):
    with pytest.raises(ConfigError, match=match):
        load(RewardTrainConfig, overrides=[override])


def test_valid_values_still_load():
    cfg = load(RewardTrainConfig, overrides=["optim.lr=3e-4", "optim.grad_clip_norm=0", "optim.weight_decay=0",
                                             "model.num_heads=2"])
    assert cfg.optim.lr == 3e-4 and cfg.model.num_heads == 2


def test_one_small_model_config_with_each_tasks_optimiser():
    """Reward, IDM and policy share SmallTrainConfig (epochs, batch, seed, optim); each keeps its own optimiser
    defaults, and a partial `optim` override keeps the rest of them (not OptimConfig's class defaults)."""
    from resim.train.config import OptimConfig, SmallTrainConfig
    from resim.train.tasks.idm import IDMTrainConfig
    from resim.train.tasks.policy import PolicyTrainConfig

    assert all(issubclass(c, SmallTrainConfig) for c in (RewardTrainConfig, IDMTrainConfig, PolicyTrainConfig))
    reward = load(RewardTrainConfig, overrides=["optim.lr=3e-4"]).optim
    assert (reward.lr, reward.weight_decay, reward.grad_clip_norm, reward.schedule) == (3e-4, 0.01, 0.0, "constant")
    idm = load(IDMTrainConfig, overrides=["optim.lr=1e-3"]).optim
    assert (idm.lr, idm.warmup_steps, idm.schedule, idm.min_lr_ratio) == (1e-3, 20, "cosine", 0.05)
    assert OptimConfig().schedule == "constant" and OptimConfig().lr == 1e-4   # the class's own, unlike the tasks'
    assert idm.for_steps(5).warmup_steps == 4 and idm.for_steps(100).warmup_steps == 20
