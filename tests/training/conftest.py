"""Fixtures for the training tests: small real shard datasets written with the real ShardWriter."""
import os
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def write_world_dataset(root, num_samples=12, per_shard=4, sources=("synthetic",), seed=0):
    """Shards the tiny world model can train on: 16-channel 8x12 latents, (16, 64) prompt embeddings.
    Commands cycle; sources cycle per shard (one source per shard, as the pipeline writes them)."""
    from shards.schema import COMMANDS
    from shards.testing import add_dummy_prompts, make_dummy_sample
    from shards.writer import ShardWriter

    add_dummy_prompts(root, seq_len=16, dim=64, seed=seed)
    n_shards = -(-num_samples // per_shard)
    i = 0
    for s in range(n_shards):
        src = sources[s % len(sources)]
        with ShardWriter(root, f"{src}-{s}", max_samples_per_shard=per_shard, config_hash="test") as w:
            for _ in range(min(per_shard, num_samples - i)):
                w.write(make_dummy_sample(source=src, item_id=f"ep-{s}-{i // 3}", start_frame=(i % 3) * 10,
                                          command=COMMANDS[i % 3], seed=seed * 1000 + i, latent_channels=16,
                                          latent_hw=(8, 12), frames_hw=(16, 24)))
                i += 1
    return Path(root)


@pytest.fixture
def world_dataset(tmp_path):
    return write_world_dataset(tmp_path / "ds")


def subprocess_env():
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env.setdefault("OMP_NUM_THREADS", "1")
    env["PYTHONUNBUFFERED"] = "1"
    env.pop("RESIM_FAULT_KILL_AT_STEP", None)
    env.pop("RESIM_FAULT_KILL_IN_SAVE", None)
    return env


PY = sys.executable
