"""Inputs that hung instead of failing, or failed naming the wrong cause: each now ends, within a limit, with one
line naming the input.

Each command runs in a subprocess with a timeout, so a regression fails here instead of hanging the suite.
"""
import os
import subprocess
import sys
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from resim.media.files import NotARegularFile, check_regular, open_regular
from resim.shards.reader import iter_samples
from tests.planting import plant_nan_latents
from tests.support.training import write_world_dataset

REPO = Path(__file__).resolve().parents[2]
TRAIN = ["train", "world", "--preset", "tiny", "--set", "trainer.progress_bar=false",
         "--set", "trainer.tensorboard=false", "--set", "trainer.loss_curve_png=false"]


def _resim(args: list[str], timeout_s: float, cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(REPO), OMP_NUM_THREADS="1")
    return subprocess.run([sys.executable, "-m", "resim", *args], env=env, cwd=cwd, capture_output=True,
                          text=True, timeout=timeout_s)


def _one_line(r: subprocess.CompletedProcess) -> str:
    lines = [ln for ln in r.stderr.strip().splitlines() if not ln.startswith("[resim")]
    assert r.returncode != 0 and len(lines) == 1, (r.returncode, r.stderr[-3000:])
    return lines[0]


def test_the_file_helper_refuses_a_fifo_a_folder_a_device_and_a_dangling_link(tmp_path):
    os.mkfifo(tmp_path / "f.mp4")
    (tmp_path / "dir.mp4").mkdir()
    (tmp_path / "dangling.mp4").symlink_to(tmp_path / "gone.mp4")
    (tmp_path / "ok.mp4").write_bytes(b"x")
    (tmp_path / "link.mp4").symlink_to(tmp_path / "ok.mp4")
    for name, what in (("f.mp4", "named pipe"), ("dir.mp4", "directory"), ("dangling.mp4", "dangling"),
                       ("none.mp4", "no such file")):
        for check in (check_regular, open_regular):
            with pytest.raises(NotARegularFile, match=what):
                check(tmp_path / name)
    with pytest.raises(NotARegularFile, match="character device"):
        open_regular("/dev/zero")
    assert check_regular(tmp_path / "link.mp4") == tmp_path / "link.mp4"
    with open_regular(tmp_path / "link.mp4") as f:
        assert f.read() == b"x"


def test_label_on_a_fifo_is_one_line_not_a_hang(tmp_path):
    os.mkfifo(tmp_path / "f.mp4")
    line = _one_line(_resim(["label", str(tmp_path / "f.mp4")], 60, tmp_path))
    assert "f.mp4" in line and "named pipe" in line


def test_training_on_a_dataset_whose_every_clip_is_a_duplicate_stops_in_one_line(tmp_path):
    ds = write_world_dataset(tmp_path / "ds", num_samples=12)
    keys = [s["__key__"] for s in iter_samples(ds)]
    (ds / "dedup").mkdir(exist_ok=True)
    pq.write_table(pa.table({"key": keys}), ds / "dedup" / "duplicates.parquet")
    r = _resim([*TRAIN, "--steps", "2", "--shards", str(ds), "--out", str(tmp_path / "run")], 180, tmp_path)
    line = _one_line(r)
    assert "no usable sample" in line and "near-duplicate" in line and str(ds) in line, line


def test_training_on_a_dataset_whose_every_latent_is_nan_stops_in_one_line(tmp_path):
    bad = write_world_dataset(tmp_path / "ds", num_samples=12)
    for tar in bad.glob("shards/*.tar"):   # every latent NaN (the writer refuses it: planted, same size)
        plant_nan_latents(tar)
    r = _resim([*TRAIN, "--steps", "2", "--shards", str(bad), "--out", str(tmp_path / "run")], 180, tmp_path)
    line = _one_line(r)
    assert "no usable sample" in line and "corrupt" in line and "NaN" in line, line
    assert r.stderr.count("skipping corrupt") <= 40     # the first 20 per worker, then one per 100


def test_resume_from_a_checkpoint_whose_metadata_is_a_fifo_is_one_line(tmp_path):
    ds = write_world_dataset(tmp_path / "ds", num_samples=12)
    common = [*TRAIN, "--shards", str(ds), "--out", str(tmp_path / "run")]
    r = _resim([*common, "--steps", "1", "--checkpoint-every", "1"], 300, tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    meta = sorted((tmp_path / "run").glob("checkpoints/step_*/.metadata"))[-1]
    meta.unlink()
    os.mkfifo(meta)
    line = _one_line(_resim([*common, "--steps", "2", "--resume"], 60, tmp_path))
    assert ".metadata" in line and "named pipe" in line, line


def test_training_on_a_nan_prompt_embedding_names_the_prompt_not_the_learning_rate(tmp_path):
    ds = write_world_dataset(tmp_path / "ds", num_samples=12)
    for f in (ds / "prompts").glob("*.npy"):
        raw = bytearray(f.read_bytes())
        raw[-64:] = b"\xff" * 64      # bfloat16 NaN bit patterns in the payload
        f.write_bytes(bytes(raw))
    r = _resim([*TRAIN, "--steps", "2", "--shards", str(ds), "--out", str(tmp_path / "run")], 180, tmp_path)
    line = _one_line(r)
    assert "prompt" in line and "NaN" in line and "optim.lr" not in line, line


def _train_in_process(ds, out, *extra):
    from resim.cli import main

    return main([*TRAIN, "--steps", "2", "--checkpoint-every", "1", "--shards", str(ds), "--out", str(out), *extra])


def _err_lines(capsys) -> list[str]:
    return [ln for ln in capsys.readouterr().err.strip().splitlines() if not ln.startswith("[resim")]


def test_a_full_disk_while_checkpointing_is_one_line_exit_6_and_leaves_no_partial_step(tmp_path, capsys,
                                                                                     monkeypatch):
    import errno

    import resim.train.checkpoint as ck

    ds = write_world_dataset(tmp_path / "ds", num_samples=12)
    real = ck.dcp.save

    def full_after_first(state, storage_writer):
        if list((tmp_path / "run" / "checkpoints").glob("step_*[0-9]")):   # the first checkpoint fits
            (Path(storage_writer.path) / "__0_0.distcp").write_bytes(b"half")
            raise OSError(errno.ENOSPC, "No space left on device", str(storage_writer.path))
        return real(state, storage_writer=storage_writer)
    monkeypatch.setattr(ck.dcp, "save", full_after_first)
    assert _train_in_process(ds, tmp_path / "run") == 6
    lines = _err_lines(capsys)
    assert len(lines) == 1 and "No space left on device" in lines[0] and "--resume" in lines[0], lines
    left = sorted(p.name for p in (tmp_path / "run" / "checkpoints").iterdir())
    assert left == ["step_00000001"], left        # the good one kept, the half-written one gone


def test_ctrl_c_in_training_is_one_line_exit_130(tmp_path, capsys, monkeypatch):
    import resim.train.checkpoint as ck

    ds = write_world_dataset(tmp_path / "ds", num_samples=12)

    def interrupted(*a, **k):
        raise KeyboardInterrupt
    monkeypatch.setattr(ck, "save", interrupted)
    assert _train_in_process(ds, tmp_path / "run") == 130
    lines = _err_lines(capsys)
    assert len(lines) == 1 and "interrupted (Ctrl-C)" in lines[0], lines


def test_init_weights_that_are_a_pickle_are_one_line_and_never_unpickled(tmp_path, capsys):
    import pickle

    ds = write_world_dataset(tmp_path / "ds", num_samples=12)
    marker = tmp_path / "pwned"

    class Boom:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))
    bad = tmp_path / "weights.safetensors"
    bad.write_bytes(pickle.dumps(Boom()))
    assert _train_in_process(ds, tmp_path / "run", "--set", f"model.init_weights={bad}") == 2
    lines = _err_lines(capsys)
    assert len(lines) == 1 and "not a readable safetensors file" in lines[0], lines
    assert not marker.exists()


def test_resume_from_a_checkpoint_whose_meta_step_is_not_its_name_is_one_line(tmp_path, capsys):
    import json

    ds = write_world_dataset(tmp_path / "ds", num_samples=12)
    assert _train_in_process(ds, tmp_path / "run") == 0
    meta = sorted((tmp_path / "run").glob("checkpoints/step_*/meta.json"))[-1]
    meta.write_text(json.dumps({**json.loads(meta.read_text()), "step": 10 ** 18}))
    capsys.readouterr()
    assert _train_in_process(ds, tmp_path / "run", "--resume", "--steps", "3") == 5
    lines = _err_lines(capsys)
    assert len(lines) == 1 and "is not the step in the folder's name" in lines[0], lines


@pytest.mark.parametrize("damage", ["truncate_distcp", "meta_json", "rank_json", "metadata_dev_zero"])
def test_resume_from_a_damaged_checkpoint_is_one_line(tmp_path, capsys, damage):
    ds = write_world_dataset(tmp_path / "ds", num_samples=12)
    assert _train_in_process(ds, tmp_path / "run") == 0
    step = sorted((tmp_path / "run").glob("checkpoints/step_*"))[-1]
    if damage == "truncate_distcp":
        shard = next(step.glob("*.distcp"))
        shard.write_bytes(shard.read_bytes()[: shard.stat().st_size // 2])
    elif damage == "meta_json":
        (step / "meta.json").write_text('{"step": ')
    elif damage == "rank_json":
        (step / "rank_0.json").write_text("not json")
    else:
        (step / ".metadata").unlink()
        (step / ".metadata").symlink_to("/dev/zero")
    capsys.readouterr()
    assert _train_in_process(ds, tmp_path / "run", "--resume", "--steps", "3") == 5
    lines = _err_lines(capsys)
    assert len(lines) == 1 and lines[0].startswith("resim train world: checkpoint error:"), lines


def test_a_read_only_run_folder_is_one_line_exit_6(tmp_path, capsys, monkeypatch):
    import errno

    ds = write_world_dataset(tmp_path / "ds", num_samples=12)
    out = tmp_path / "run"
    real = Path.mkdir

    def read_only(self, *a, **k):   # as a read-only mount answers (root ignores permission bits, so not chmod)
        if self == out or out in self.parents:
            raise OSError(errno.EROFS, "Read-only file system", str(self))
        return real(self, *a, **k)
    monkeypatch.setattr(Path, "mkdir", read_only)
    assert _train_in_process(ds, out) == 6
    lines = _err_lines(capsys)
    assert len(lines) == 1 and "Read-only file system" in lines[0], lines
