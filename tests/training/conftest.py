"""Fixtures for the training tests: small real shard datasets written with the real ShardWriter."""
import os
from pathlib import Path

import pytest

from tests.support.training import write_world_dataset

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def world_dataset(tmp_path):
    return write_world_dataset(tmp_path / "ds")


@pytest.fixture
def subprocess_env():
    return make_subprocess_env()


def make_subprocess_env():
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env.setdefault("OMP_NUM_THREADS", "1")
    env["PYTHONUNBUFFERED"] = "1"
    env.pop("RESIM_FAULT_KILL_AT_STEP", None)
    env.pop("RESIM_FAULT_KILL_IN_SAVE", None)
    return env

