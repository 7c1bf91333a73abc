"""ShardWriter: validation, crash safety, reruns, naming rule."""
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from resim.shards import layout
from resim.shards.reader import iter_samples
from tests.support.shards import add_dummy_prompts, make_dummy_sample
from resim.shards.validate import SampleError
from resim.shards.verify import verify
from resim.shards.writer import ShardExistsError, ShardWriter

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
    from tests.support.shards import make_dummy_sample
    from resim.shards.writer import ShardWriter
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
    from resim.shards.schema import make_key

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


def _unit_files(root, prefix="unit"):
    """Names of the prefix's tars, indexes and manifests on disk (temporaries excluded)."""
    return {sub: sorted(p.name for p in (root / sub).iterdir() if p.name.startswith(prefix + "-"))
            for sub in ("shards", "index", "manifest")}


def _keys(root):
    return [s["__key__"] for s in iter_samples(root, attach_prompts=False)]


def test_overwrite_rerun_with_fewer_shards_removes_the_earlier_runs_higher_shards(tmp_path):
    from resim.shards.manifest import read_manifest

    _write_unit(tmp_path, n=10)                                         # shards 0..3
    with ShardWriter(tmp_path, "unit", max_samples_per_shard=3, overwrite=True) as w:
        new = [make_dummy_sample(item_id=f"u/{i}", seed=i + 100) for i in range(4)]
        for s in new:
            w.write(s)
    assert [i.name for i in w.close()] == ["unit-00000.tar", "unit-00001.tar"]
    assert _keys(tmp_path) == [s["__key__"] for s in new]              # no stale samples mixed in
    assert read_manifest(tmp_path)["key"].to_pylist() == [s["__key__"] for s in new]
    assert _unit_files(tmp_path) == {"shards": ["unit-00000.tar", "unit-00001.tar"],
                                     "index": ["unit-00000.json", "unit-00001.json"],
                                     "manifest": ["unit-00000.parquet", "unit-00001.parquet"]}
    assert w.removed_stale == ["unit-00002.tar", "unit-00003.tar"]
    assert verify(tmp_path) == []
    with ShardWriter(tmp_path, "unit", overwrite=True) as w:            # a rerun that yields nothing
        pass
    assert w.removed_stale == ["unit-00000.tar", "unit-00001.tar"] and _keys(tmp_path) == []


def test_rerun_with_fewer_shards_without_overwrite_is_refused_and_removes_nothing(tmp_path):
    _write_unit(tmp_path, n=6)                                          # shards 0..1
    before = _unit_files(tmp_path)
    with pytest.raises(ShardExistsError, match=r"unit-00001.tar from an earlier run.*overwrite=True"):
        _write_unit(tmp_path, n=3)                                      # shard 0 identical, shard 1 stale
    assert _unit_files(tmp_path) == before and len(_keys(tmp_path)) == 6 and verify(tmp_path) == []


def test_overwrite_rerun_interrupted_leaves_every_committed_shard_complete(tmp_path):
    _write_unit(tmp_path, n=9)                                          # shards 0..2
    old = {p.name: p.read_bytes() for p in layout.committed_shards(tmp_path)}
    with pytest.raises(RuntimeError):
        with ShardWriter(tmp_path, "unit", max_samples_per_shard=3, overwrite=True) as w:
            for i in range(4):                                          # shard 0 replaced, shard 1 open
                w.write(make_dummy_sample(item_id=f"u/{i}", seed=i + 100))
            raise RuntimeError("worker died mid-rerun")
    # the run did not finish: its new shard 0 is committed, the earlier run's 1..2 stay committed and intact
    assert [p.name for p in layout.committed_shards(tmp_path)] == sorted(old)
    assert all((layout.shards_dir(tmp_path) / n).read_bytes() == b for n, b in old.items() if n != "unit-00000.tar")
    assert verify(tmp_path) == []


def test_crash_while_removing_stale_shards_leaves_only_uncommitted_files(tmp_path, monkeypatch):
    from resim.shards import writer as writer_mod
    from resim.shards.manifest import read_manifest

    _write_unit(tmp_path, n=9)                                          # shards 0..2
    real_fsync_dir = writer_mod.fsync_dir

    def crash_after_uncommit(path):
        if Path(path) == layout.index_dir(tmp_path):                   # stale indexes are gone, nothing else yet
            raise KeyboardInterrupt("killed")
        real_fsync_dir(path)

    monkeypatch.setattr(writer_mod, "fsync_dir", crash_after_uncommit)
    new = [make_dummy_sample(item_id=f"u/{i}", seed=i + 100) for i in range(3)]
    with pytest.raises(KeyboardInterrupt):
        with ShardWriter(tmp_path, "unit", max_samples_per_shard=3, overwrite=True) as w:
            for s in new:
                w.write(s)
    monkeypatch.undo()
    files = _unit_files(tmp_path)
    assert files["index"] == ["unit-00000.json"] and len(files["shards"]) == 3   # 1..2: tars without an index
    assert _keys(tmp_path) == [s["__key__"] for s in new]              # readers see the new run only
    assert read_manifest(tmp_path)["key"].to_pylist() == [s["__key__"] for s in new]
    msgs = [str(p) for p in verify(tmp_path)]
    assert msgs == [f"shard unit-0000{i}.tar: shard has no index (uncommitted: its writer was interrupted; "
                    "rerun that work unit, or delete it)" for i in (1, 2)], msgs
    with ShardWriter(tmp_path, "unit", max_samples_per_shard=3, overwrite=True) as w:   # the rerun cleans up
        for s in new:
            w.write(s)
    assert [i.reused for i in w.close()] == [True]
    assert _unit_files(tmp_path)["shards"] == ["unit-00000.tar"] and verify(tmp_path) == []
