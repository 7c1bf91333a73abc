"""Fixtures for Video2Reward tests: a tiny model config and procedural toy clips."""
import pytest
import torch

from resim.config import from_dict
from resim.models.reward.config import RewardModelConfig
from resim.train.tasks.reward.config import RewardTrainConfig

torch.set_num_threads(1)

TINY_MODEL = {"num_frames": 4, "frame_step": 2, "head_dim": 32, "num_heads": 2, "mlp_hidden_dim": 32}


@pytest.fixture
def tiny_cfg() -> RewardModelConfig:
    return from_dict(RewardModelConfig, TINY_MODEL)


@pytest.fixture
def tiny_train_cfg() -> RewardTrainConfig:
    return from_dict(RewardTrainConfig, {"epochs": 3, "batch_size_per_gpu": 8, "model": TINY_MODEL})


@pytest.fixture(scope="module")
def toy():
    from tests.support.reward_toy import toy_clips

    return toy_clips(12, 2, 8, seed=0)
