"""Real torchrun (gloo, CPU): 2 processes train the tiny world model from shards through `resim train launch`."""
import json
import shutil
import subprocess
import sys
import warnings

import pytest

from resim.cli import main

from resim.train import checkpoint as ckpt
from tests.support.training import write_world_dataset


def _launch(ds, out, env, *extra, nproc=2, steps=10):
    cmd = [sys.executable, "-m", "resim", "train", "launch", "--nproc-per-node", str(nproc), "--",
           "world", "--preset", "tiny", "--shards", str(ds), "--out", str(out), "--steps", str(steps),
           "--set", "optim.lr=3e-3", "--set", "data.open_shards_per_worker=1",
           "--set", "trainer.progress_bar=false", "--set", "trainer.tensorboard=false", *extra]
    p = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=240)
    if p.returncode != 0 and "terminate called without an active exception" in p.stderr:
        # A rank sometimes aborts in C++ at its first step when the 2-core machine is loaded (SIGABRT,
        # "terminate called without an active exception"): measured ~10 % of runs under a busy second core,
        # on the code before this test's session too (3 of 20), never with a Python error. One retry in a
        # clean output folder for exactly that signature; any other failure, or a second abort, fails.
        warnings.warn(f"torchrun rank aborted (known gloo/CPU-load crash), retrying once: {p.stderr[-300:]}")
        shutil.rmtree(out, ignore_errors=True)
        p = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=240)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    return p.stdout + p.stderr


def _losses(out):
    return [r["loss"] for r in map(json.loads, open(out / "metrics.jsonl"))]


def test_ddp_two_ranks_loss_decreases_on_repeated_batch(tmp_path, subprocess_env):
    # one shard of 2 samples, batch 2, sequential reading: every step sees the same batch; and
    # 1 shard < 2 ranks x 2 workers: with resampled draws and a fixed epoch length nobody runs dry (no hang)
    ds = write_world_dataset(tmp_path / "ds", num_samples=2, per_shard=2)
    out = tmp_path / "run"
    log = _launch(ds, out, subprocess_env, "--set", "data.num_workers=2")
    assert "DDP over 2 ranks" in log and "2 batches of 2 per rank per epoch (2 ranks x 2 workers)" in log
    loss = _losses(out)
    assert len(loss) == 10  # rank 0 logs one line per optimizer step, nobody else writes
    assert sum(loss[-3:]) / 3 < 0.85 * loss[0], loss
    last = ckpt.latest_complete(out)
    assert last == ckpt.checkpoint_path(out, 10)
    assert (last / "rank_0.json").is_file() and (last / "rank_1.json").is_file()
    assert (out / "loss_curve.png").is_file() and (out / "final" / "model.safetensors").is_file()


@pytest.mark.slow
def test_fsdp2_two_ranks_then_resharded_resume_on_one(tmp_path, subprocess_env, capsys):
    ds = write_world_dataset(tmp_path / "ds", num_samples=2, per_shard=2)
    out = tmp_path / "run"
    log = _launch(ds, out, subprocess_env, "--set", "trainer.parallel=fsdp", "--set", "trainer.ema_decay=0.9",
                  steps=4)
    assert "FSDP2 fully_shard on 2 blocks + root over 2 ranks" in log
    assert "returned a view tensor" not in log  # FSDP2's warning about views returned by a unit (a DiT block)
    # resume on 1 process (in this one: a 1-rank gloo group for FSDP2): DCP reshards the 2-rank checkpoint
    rc = main(["train", "world", "--preset", "tiny", "--shards", str(ds), "--out", str(out), "--steps", "6",
               "--resume", "--set", "optim.lr=3e-3", "--set", "data.open_shards_per_worker=1",
               "--set", "trainer.parallel=fsdp", "--set", "trainer.ema_decay=0.9",
               "--set", "trainer.progress_bar=false", "--set", "trainer.tensorboard=false"])
    assert rc == 0
    assert "resharded resume: checkpoint written by 2 ranks, this run has 1" in capsys.readouterr().out
    loss = _losses(out)
    assert len(loss) == 6 and loss[-1] < loss[0]
