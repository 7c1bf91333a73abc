"""`resim train world --out`: a finished run resumed, a run folder reused without --resume, another kind of run
or a dataset as --out. One line on stderr with the `resim train world:` prefix, exit 2 (0 for nothing to do)."""
import json

import pytest
import yaml

from resim.cli import main
from resim.train import checkpoint as ckpt

QUIET = ["--set", "trainer.progress_bar=false", "--set", "trainer.tensorboard=false",
         "--set", "trainer.loss_curve_png=false", "--set", "data.num_workers=0"]


def _train(ds, out, *extra):
    return main(["train", "world", "--preset", "tiny", "--shards", str(ds), "--out", str(out), *QUIET, *extra])


def _one_line(capsys, *needles):
    err = capsys.readouterr().err.strip()
    lines = [ln for ln in err.splitlines() if not ln.startswith("[resim")]
    assert "Traceback" not in err and len(lines) == 1, err
    for n in needles:
        assert n in lines[0], err
    return lines[0]


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A tiny world run trained to its trainer.steps (2), and its dataset."""
    from tests.support.training import write_world_dataset

    root = tmp_path_factory.mktemp("runfolder")
    ds = write_world_dataset(root / "ds")
    assert _train(ds, root / "run", "--steps", "2") == 0
    return ds, root / "run"


def _copy(src, dst):
    import shutil

    shutil.copytree(src, dst)
    return dst


def test_resume_of_a_finished_run_has_nothing_to_do(finished, tmp_path, capsys):
    ds, run = finished
    run = _copy(run, tmp_path / "run")
    before = {p: p.stat().st_mtime_ns for p in run.rglob("*") if p.is_file()}
    capsys.readouterr()
    assert _train(ds, run, "--steps", "2", "--resume") == 0
    line = _one_line(capsys, "resim train world:", "is already at step 2 (trainer.steps = 2)", "raise --steps")
    assert "nothing to do" in line
    assert {p: p.stat().st_mtime_ns for p in run.rglob("*") if p.is_file()} == before   # nothing rewritten
    # raising --steps continues it
    assert _train(ds, run, "--steps", "3", "--resume") == 0
    assert [s for s, _ in ckpt.list_complete(run)][-1] == 3
    assert len((run / "metrics.jsonl").read_text().splitlines()) == 3


def test_existing_run_without_resume_is_refused(finished, tmp_path, capsys):
    ds, run = finished
    run = _copy(run, tmp_path / "run")
    cfg_before = (run / "config.yaml").read_text()
    capsys.readouterr()
    assert _train(ds, run, "--steps", "1") == 2
    _one_line(capsys, "resim train world:", f"{run} holds a world run (checkpoints/step_00000002)",
              "--resume", "--overwrite", "choose a new --out")
    assert [s for s, _ in ckpt.list_complete(run)] == [2] and (run / "config.yaml").read_text() == cfg_before
    # --resume and --overwrite together: refused
    assert _train(ds, run, "--steps", "3", "--resume", "--overwrite") == 2
    _one_line(capsys, "resim train world:", "--resume", "--overwrite")


def test_overwrite_starts_over(finished, tmp_path, capsys):
    ds, run = finished
    run = _copy(run, tmp_path / "run")
    (run / "notes.txt").write_text("mine")
    assert _train(ds, run, "--steps", "1", "--overwrite") == 0
    assert [s for s, _ in ckpt.list_complete(run)] == [1]          # the old step-2 checkpoint is gone
    assert len((run / "metrics.jsonl").read_text().splitlines()) == 1
    assert yaml.safe_load((run / "config.yaml").read_text())["trainer"]["steps"] == 1
    assert (run / "notes.txt").read_text() == "mine"                # only the run's own files are removed
    # a later --resume continues the NEW run
    assert _train(ds, run, "--steps", "2", "--resume") == 0
    assert json.loads((ckpt.checkpoint_path(run, 2) / "meta.json").read_text())["config"]["trainer"]["steps"] == 2
    assert len((run / "metrics.jsonl").read_text().splitlines()) == 2


def _fake_reward_run(d):
    d.mkdir(parents=True)
    (d / "config.yaml").write_text("model:\n  num_frames: 8\nepochs: 20\nlr: 0.001\n")
    (d / "reward.safetensors").write_bytes(b"x")
    (d / "meta.json").write_text("{}")
    return d


@pytest.mark.parametrize("flags", [[], ["--resume"], ["--overwrite"]])
def test_another_kind_of_run_or_a_dataset_is_refused(finished, tmp_path, capsys, flags):
    ds, _ = finished
    rw = _fake_reward_run(tmp_path / "reward")
    cfg_before = (rw / "config.yaml").read_text()
    capsys.readouterr()
    assert _train(ds, rw, "--steps", "1", *flags) == 2
    _one_line(capsys, "resim train world:", f"{rw} holds a reward run (reward.safetensors), not a world run",
              "choose a new --out")
    assert (rw / "config.yaml").read_text() == cfg_before and not (rw / "checkpoints").exists()
    assert sorted(p.name for p in rw.iterdir()) == ["config.yaml", "meta.json", "reward.safetensors"]
    assert _train(ds, ds, "--steps", "1", *flags) == 2
    _one_line(capsys, "resim train world:", "holds a shard dataset", "not a world run")


def test_describe_run(finished, tmp_path):
    from resim.train.run import describe_run

    _, run = finished
    assert describe_run(run).kind == "world" and describe_run(run).evidence == "checkpoints/step_00000002"
    assert describe_run(tmp_path / "missing") is None and describe_run(tmp_path) is None
    (tmp_path / "config.yaml").write_text("model_name: world\n")   # stopped before its first checkpoint
    assert describe_run(tmp_path) is None
    idm = tmp_path / "idm"
    (idm / "checkpoints" / "step_00000005").mkdir(parents=True)
    (idm / "checkpoints" / "step_00000005" / "meta.json").write_text("{}")
    (idm / "config.yaml").write_text("model_name: idm\n")
    assert describe_run(idm).kind == "idm"


def test_a_shard_whose_size_is_not_its_indexs_is_left_out_or_refused_when_strict(tmp_path, capsys):
    # the loader's free check (the sha256 is `resim shards verify`'s, docs/security.md): a truncated tar
    from tests.support.training import write_world_dataset

    ds = write_world_dataset(tmp_path / "ds")
    tar = sorted((ds / "shards").glob("*.tar"))[0]
    tar.write_bytes(tar.read_bytes()[:-512])
    # strict: one line, nothing trained
    assert _train(ds, tmp_path / "strict", "--steps", "1", "--set", "data.strict=true") == 4     # data error
    _one_line(capsys, "resim train world: data error:", str(tar), "its index recorded", "resim shards verify")
    assert not (tmp_path / "strict" / "checkpoints").exists()
    # default: the shard is left out with a warning naming it, as unreadable shards are, and training goes on
    assert _train(ds, tmp_path / "run", "--steps", "1") == 0
    err = capsys.readouterr().err
    assert f"skipping shard {tar}" in err and "resim shards verify" in err
