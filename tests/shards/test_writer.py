"""ShardWriter: validation, crash safety, reruns, naming rule."""
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from shards import layout
from shards.reader import iter_samples
from shards.testing import add_dummy_prompts, make_dummy_sample
from shards.validate import SampleError
from shards.verify import verify
from shards.writer import ShardExistsError, ShardWriter

REPO = Path(__file__).resolve().parents[2]


def _bad(mutate, **kw):
    s = make_dummy_sample(**kw)
    mutate(s)
    return s


@pytest.mark.parametrize("mutate,match", [
    (lambda s: s.update({"latent.npy": s["latent.npy"][:, :2]}), "latent.npy shape"),
    (lambda s: s.update({"latent.npy": s["latent.npy"].astype(np.float32)}), "latent.npy dtype"),
    (lambda s: s.update({"traj.npy": s["traj.npy"].astype(np.float64)}), "traj.npy must be float32"),
    (lambda s: s.pop("frames.mp4"), r"required members \['frames.mp4'\]"),
    (lambda s: s.update({"frames.mp4": np.zeros((2, 4, 4, 3), np.uint8)}), "encoded mp4 bytes"),
    (lambda s: s.update({"__key__": s["__key__"] + ".x"}), "first dot"),
    (lambda s: s["meta.json"].update({"command": "Reversing"}), "meta.command"),
    (lambda s: s["meta.json"].update({"surprise": 1}), "not in schema"),
    (lambda s: s["meta.json"].pop("fps_hz"), "lacks fields"),
    (lambda s: s["meta.json"].update({"start_frame": 1.5}), "start_frame"),
    (lambda s: s["meta.json"].update({"is_turning": True}), "contradicts"),
    (lambda s: s["meta.json"].update({"has_trajectory": False}), "has_trajectory"),
    (lambda s: s["meta.json"].update({"item_id": "other"}), "make_key"),
    (lambda s: s.update({"extra.pyd": b"x"}), "code-executing"),
])
def test_writer_refuses_invalid_samples(tmp_path, mutate, match):
    with ShardWriter(tmp_path, "v") as w:
        with pytest.raises(SampleError, match=match):
            w.write(_bad(mutate))
        w.write(make_dummy_sample())  # the writer is still usable
    assert len(list(iter_samples(tmp_path, attach_prompts=False))) == 1


def test_duplicate_key_and_prefix_rules(tmp_path):
    with pytest.raises(ValueError, match="prefix"):
        ShardWriter(tmp_path, "a.b")
    with pytest.raises(ValueError, match="prefix"):
        ShardWriter(tmp_path, "../x")
    with ShardWriter(tmp_path, "d") as w:
        w.write(make_dummy_sample())
        with pytest.raises(SampleError, match="already written"):
            w.write(make_dummy_sample())


def test_exception_in_block_leaves_no_partial_shard(tmp_path):
    with pytest.raises(RuntimeError):
        with ShardWriter(tmp_path, "x", max_samples_per_shard=2) as w:
            for i in range(3):
                w.write(make_dummy_sample(item_id=f"e/{i}", seed=i))
            raise RuntimeError("worker failed")
    names = sorted(p.name for p in layout.shards_dir(tmp_path).iterdir())
    assert names == ["x-00000.tar"]  # the complete first shard is committed, the open one is gone


def _write_unit(root, n=6, prefix="unit", overwrite=False, seed_offset=0):
    add_dummy_prompts(root)
    with ShardWriter(root, prefix, max_samples_per_shard=3, overwrite=overwrite) as w:
        for i in range(n):
            w.write(make_dummy_sample(item_id=f"u/{i}", seed=i + seed_offset))
    return w.close()


def test_rerun_is_idempotent_and_conflicts_are_refused(tmp_path):
    first = _write_unit(tmp_path)
    again = _write_unit(tmp_path)
    assert [i.sha256 for i in again] == [i.sha256 for i in first] and all(i.reused for i in again)
    with pytest.raises(ShardExistsError, match="different content"):
        _write_unit(tmp_path, seed_offset=100)  # same names, other bytes: another writer on this prefix?
    assert [p.name for p in layout.committed_shards(tmp_path)] == ["unit-00000.tar", "unit-00001.tar"]
    replaced = _write_unit(tmp_path, seed_offset=100, overwrite=True)
    assert not any(i.reused for i in replaced) and replaced[0].sha256 != first[0].sha256
    assert verify(tmp_path) == []


def test_uncommitted_shard_is_replaced_on_rerun(tmp_path):
    _write_unit(tmp_path)
    layout.index_path(tmp_path, "unit-00001.tar").unlink()  # crash between rename and index
    with open(layout.shards_dir(tmp_path) / "unit-00001.tar", "r+b") as fh:
        fh.truncate(1000)
    assert any("no index" in str(p) for p in verify(tmp_path))
    _write_unit(tmp_path)
    assert verify(tmp_path) == []


CHILD = textwrap.dedent("""
    import sys, time
    from shards.testing import make_dummy_sample
    from shards.writer import ShardWriter
    w = ShardWriter(sys.argv[1], "killme", max_samples_per_shard=3)
    for i in range(int(sys.argv[2])):
        w.write(make_dummy_sample(item_id=f"k/{i}", seed=i))
    print("READY", flush=True)   # shard 0 committed, shard 1 half written
    time.sleep(60)
""")


def test_writer_killed_mid_shard_leaves_no_final_shard_and_rerun_completes(tmp_path):
    root = tmp_path / "ds"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen([sys.executable, "-c", CHILD, str(root), "5"], stdout=subprocess.PIPE, text=True, env=env)
    try:
        assert proc.stdout.readline().strip() == "READY"
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == -signal.SIGKILL
    finals = sorted(p.name for p in layout.all_shard_files(root))
    assert finals == ["killme-00000.tar"]  # the half-written shard exists only under a temporary name
    temps = [p.name for p in layout.shards_dir(root).iterdir() if p.name.startswith(".")]
    assert len(temps) == 1 and temps[0].startswith(".killme-00001.tar.tmp-")
    assert [s["__key__"] for s in iter_samples(root, attach_prompts=False)].__len__() == 3
    assert any("leftover temporary file" in str(p) for p in verify(root))

    add_dummy_prompts(root)
    # the pipeline redoes the unit deterministically: shard 0 is recognised, the rest written, temp cleaned
    with ShardWriter(root, "killme", max_samples_per_shard=3) as w:
        for i in range(8):
            w.write(make_dummy_sample(item_id=f"k/{i}", seed=i))
    infos = w.close()
    assert [i.reused for i in infos] == [True, False, False]
    assert not any(p.name.startswith(".") for p in layout.shards_dir(root).iterdir())
    assert len(list(iter_samples(root, attach_prompts=False))) == 8
    assert verify(root) == []


def _unit_worker(args):
    root, unit = args
    from shards.schema import make_key

    with ShardWriter(root, f"u{unit:03d}", max_samples_per_shard=2) as w:
        for i in range(3):
            w.write(make_dummy_sample(item_id=f"unit{unit}/{i}", seed=unit * 10 + i))
    return [(i.name, i.num_samples) for i in w.close()], make_key("synthetic", f"unit{unit}/0", 0)


def test_many_concurrent_writers(tmp_path):
    import multiprocessing as mp

    add_dummy_prompts(tmp_path)
    with mp.get_context("fork").Pool(4) as pool:
        results = pool.map(_unit_worker, [(str(tmp_path), u) for u in range(6)])
    names = [n for r, _ in results for n, _ in r]
    assert len(names) == len(set(names)) == 12
    assert len(list(iter_samples(tmp_path, attach_prompts=False))) == 18
    assert verify(tmp_path) == []
