"""The run lock on OUT (``resim/pipeline/out_lock.py``).

The attack: two ``resim pipeline run`` with different configs at once into one OUT wrote a dataset of two
data hashes (51 + 12 samples) that ``resim shards verify`` passed. Here a real run of one config is paused in
another process after it took OUT (its config stamped, before any unit), and a second run with another config
must fail at once with one line naming OUT, the owner and the fix, writing nothing. A run killed while it
held the lock must not block the rerun that resumes it.
"""
import logging
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from resim.cli import main
from resim.config import ConfigError
from resim.pipeline import out_lock, runner

from .conftest import REPO, make_config

CONFIG = str(REPO / "configs/pipeline/synthetic.yaml")

# A real `runner.run` into OUT that stops once it holds OUT (prepare_out done, before the synthetic world is
# generated): the first of two concurrent runs, frozen at the moment the second one starts.
HOLDER = """
import sys, time
from resim.pipeline import runner
from resim.pipeline.load import load_config
cfg = load_config(sys.argv[1], [f"sources.synthetic.root={sys.argv[3]}", "shards.max_samples_per_shard=7"],
                  out=sys.argv[2])
def pause(cfg):
    print("holding", flush=True)
    time.sleep(600)
runner.ensure_synthetic = pause
runner.run(cfg)
"""


def _start_holder(out: Path, world: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    p = subprocess.Popen([sys.executable, "-c", HOLDER, CONFIG, str(out), str(world)], cwd=REPO, env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    line = p.stdout.readline()
    if line.strip() != "holding":
        p.kill()
        pytest.fail(f"the holder run did not start: {line!r} {p.stderr.read()[-2000:]}")
    return p


def _snapshot(out: Path) -> dict:
    return {str(p.relative_to(out)): (p.read_bytes() if p.is_file() else None, p.stat().st_mtime_ns)
            for p in sorted(out.rglob("*"))}


def test_a_second_run_into_an_out_a_live_run_holds_fails_at_once_and_writes_nothing(tmp_path, capsys):
    out, world = tmp_path / "out", tmp_path / "world"
    holder = _start_holder(out, world)
    try:
        before = _snapshot(out)
        assert "config_hash.txt" in before           # the first run took OUT: its config is stamped
        t0 = time.monotonic()
        rc = main(["pipeline", "run", CONFIG, "--out", str(out), "--no-progress",
                   "--set", f"sources.synthetic.root={world}", "--set", "shards.max_samples_per_shard=8"])
        elapsed = time.monotonic() - t0
        err = capsys.readouterr().err.strip()
        assert rc == 1
        assert "Traceback" not in err and len(err.splitlines()) == 1, err
        assert err.startswith(f"resim pipeline run: error: out: {out} is in use by another pipeline run "), err
        assert f"pid {holder.pid} on {socket.gethostname()} since " in err, err
        assert "wait for it to end, or use another --out" in err, err
        assert elapsed < 30, f"took {elapsed:.1f} s: the second run waited instead of failing"   # no waiting
        assert _snapshot(out) == before              # not a byte written: the config stamp is still the first's
        assert not world.exists()                    # nor a synthetic world generated
    finally:
        holder.kill()
        holder.wait()


def test_a_lock_left_by_a_killed_run_does_not_block_the_rerun(tmp_path, monkeypatch, caplog):
    out, world = tmp_path / "out", tmp_path / "world"
    holder = _start_holder(out, world)
    holder.send_signal(signal.SIGKILL)               # as the OOM killer or a lost node would
    holder.wait()
    assert str(holder.pid) in (out / ".lock").read_text()   # the owner is still recorded: the lock is stale

    def reached(cfg):   # past the lock and prepare_out: stop here, a whole run is not needed to show it
        raise ConfigError("reached ensure_synthetic")
    monkeypatch.setattr(runner, "ensure_synthetic", reached)
    with caplog.at_level(logging.WARNING, logger="resim.pipeline"), \
            pytest.raises(ConfigError, match="reached ensure_synthetic"):
        runner.run(make_config(out, [f"sources.synthetic.root={world}"]))
    taken = [r.getMessage() for r in caplog.records if "taking over the lock" in r.getMessage()]
    assert len(taken) == 1 and f"pid {holder.pid} " in taken[0], caplog.text
    assert (out / ".lock").read_text() == ""         # released cleanly despite the error: the next run is quiet
    with out_lock.hold(out):
        pass
