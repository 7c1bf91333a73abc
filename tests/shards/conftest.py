"""Fixtures for shard tests: a small valid dataset written once per session, copied per test that corrupts it."""
import shutil

import pytest

from resim.shards.schema import COMMANDS
from tests.support.shards import add_dummy_prompts, make_dummy_sample
from resim.shards.writer import ShardWriter


def mixed_samples(n: int = 10):
    """Samples covering every member and option: fp16/bf16 latents, with/without traj and dino, hazards."""
    out = []
    for i in range(n):
        out.append(make_dummy_sample(
            source=("synthetic", "carla", "opendv", "navsim")[i % 4], item_id=f"ep/{i // 3}", start_frame=(i % 3) * 7,
            command=COMMANDS[i % 3], seed=i, latent_dtype="bfloat16" if i % 2 else "float16",
            with_trajectory=(i % 4 != 2), with_dino=(i % 3 == 0),
            hazard=(None if i % 4 != 1 else bool(i % 8 == 1))))
    return out


@pytest.fixture(scope="session")
def base_dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("base") / "ds"
    add_dummy_prompts(root)
    samples = mixed_samples(10)
    with ShardWriter(root, "unitA", max_samples_per_shard=4, config_hash="cafe") as w:
        for s in samples:
            w.write(s)
    return root, samples


@pytest.fixture
def dataset(base_dataset, tmp_path):
    """A private copy of the base dataset (tests may corrupt it)."""
    root = tmp_path / "ds"
    shutil.copytree(base_dataset[0], root)
    return root
