"""Exact resume: a run killed with SIGKILL (between checkpoints, and in the middle of a save) and resumed
logs bitwise the same losses as an uninterrupted run (CPU, float32, 2 DataLoader workers). The dataset mixes
two clip geometries (OpenDV-style 13 latent frames, NAVSIM-style 3), so the position holds partial shape
buckets and the model sees different T_latent from step to step."""
import json
import signal
import subprocess
import sys

import pytest
import torch

from resim.cli import main
from resim.train import checkpoint as ckpt
from tests.support.training import navsim_spec, write_world_dataset


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _args(ds, out):
    return ["train", "world", "--preset", "tiny", "--shards", str(ds), "--out", str(out), "--steps", "8",
            "--checkpoint-every", "3", "--set", "data.num_workers=2", "--set", "trainer.progress_bar=false",
            "--set", "trainer.tensorboard=false", "--set", "trainer.loss_curve_png=false",
            "--set", "trainer.save_final_weights=false", "--set", "trainer.ema_decay=0.9",
            "--set", "data.split=all"]   # every sample: the stream's buckets hold pending samples at step 3


def _losses(run):
    return [(r["step"], r["loss"], r["grad_norm"]) for r in map(json.loads, open(run / "metrics.jsonl"))]


def _killed_run(ds, out, env, var, step):
    env = {**env, var: str(step)}
    p = subprocess.run([sys.executable, "-m", "resim", *_args(ds, out)], env=env, capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == -signal.SIGKILL, p.stderr[-2000:]


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The dataset and the uninterrupted run's (step, loss, grad_norm) records."""
    root = tmp_path_factory.mktemp("resume")
    ds = write_world_dataset(root / "ds", sources=("opendv", "navsim"), specs={"navsim": navsim_spec()})
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        assert main(_args(ds, root / "ref")) == 0
    finally:
        torch.set_num_threads(n)
    expected = _losses(root / "ref")
    assert [s for s, _, _ in expected] == list(range(1, 9))
    return ds, expected


def test_sigkill_between_checkpoints_then_resume_is_bitwise_equal(reference, tmp_path, subprocess_env):
    world_dataset, expected = reference

    run = tmp_path / "killed"
    _killed_run(world_dataset, run, subprocess_env, "RESIM_FAULT_KILL_AT_STEP", 5)
    assert ckpt.latest_complete(run) == ckpt.checkpoint_path(run, 3)  # killed after step 5, last checkpoint 3
    assert len(_losses(run)) == 5
    pos = json.loads((ckpt.checkpoint_path(run, 3) / "rank_0.json").read_text())["data"]
    assert any(c["pending"] for c in pos["cursors"].values())  # resumes with buffered samples in a bucket
    assert main(_args(world_dataset, run) + ["--resume"]) == 0
    assert _losses(run) == expected  # bitwise: JSON floats round-trip exactly


def test_sigkill_during_save_leaves_previous_checkpoint_usable(reference, tmp_path, subprocess_env):
    world_dataset, expected = reference
    run = tmp_path / "killed_in_save"
    _killed_run(world_dataset, run, subprocess_env, "RESIM_FAULT_KILL_IN_SAVE", 6)
    half = ckpt.checkpoint_path(run, 6).with_name("step_00000006.tmp")
    assert half.is_dir() and not (half / "meta.json").exists()   # the interrupted save
    assert ckpt.latest_complete(run) == ckpt.checkpoint_path(run, 3)
    assert main(_args(world_dataset, run) + ["--resume"]) == 0
    assert _losses(run) == expected
    assert not half.exists() and ckpt.latest_complete(run) == ckpt.checkpoint_path(run, 8)
