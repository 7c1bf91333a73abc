"""A disk that is full, for a moment or for good, never yields exit 0 with clips missing.

* full for a moment: the stage pauses and retries; the run completes with every unit committed;
* full for good: the run stops with one line naming the unit and the reason; committed units stay, nothing
  half-written is left (no uncommitted tar, no temporary file), and a plain rerun completes the dataset,
  identical to an uninterrupted run;
* a unit that ran without its commit marker fails the run (never counted as done);
* an mp4 that OpenCV could not finish is an OSError (ENOSPC when the temporary folder is full), not a clip
  with a broken ``frames.mp4``.

The full disk is simulated by raising ``OSError(ENOSPC)`` where the writer writes (a real small filesystem
needs root to mount); the local executor runs the same stage classes in this process.
"""
import errno
import json

import numpy as np
import pytest

from resim.pipeline.stages.base import OutputError, Stage

from .conftest import REPO, make_config


@pytest.fixture(autouse=True)
def _no_pauses(monkeypatch):
    monkeypatch.setattr(Stage, "output_pause_s", 0.0)


def _cfg(tmp_path, synth_world, name):
    return make_config(tmp_path / name, [f"sources.synthetic.root={synth_world}", "ray.executor=local",
                                         "sources.synthetic.layouts=[opendv,carla]"])


def _full_for(monkeypatch, calls: int | None):
    """ShardWriter.write raises ENOSPC on its first ``calls`` calls (None: always)."""
    from resim.shards.writer import ShardWriter

    real, seen = ShardWriter.write, {"n": 0}

    def write(self, sample):
        seen["n"] += 1
        if calls is None or seen["n"] <= calls:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, sample)

    monkeypatch.setattr(ShardWriter, "write", write)
    return seen


def _state(out):
    commits = sorted(p.stem for p in (out / "commits").glob("*.json"))
    tars = sorted(p.name for p in (out / "shards").glob("*")) if (out / "shards").is_dir() else []
    index = sorted(p.stem for p in (out / "index").glob("*.json")) if (out / "index").is_dir() else []
    return commits, tars, index


def test_a_moment_of_full_disk_costs_a_pause_not_clips(tmp_path, synth_world, monkeypatch):
    from resim.pipeline import runner

    ref = runner.run(_cfg(tmp_path, synth_world, "ref"))
    seen = _full_for(monkeypatch, calls=2)         # the first unit's first two tries fail, the third succeeds
    res = runner.run(_cfg(tmp_path, synth_world, "out"))
    assert seen["n"] > 2
    assert res.stats["units"] == ref.stats["units"] == {"total": 4, "ok": 4, "quarantined": 0}
    assert res.stats["clips"]["total"] == ref.stats["clips"]["total"] and res.stats["quarantine"]["rows"] == 0


def test_a_full_disk_stops_the_run_loudly_and_a_rerun_completes_it(tmp_path, synth_world, monkeypatch, capsys):
    from resim.pipeline import runner
    from resim.cli import main

    ref = runner.run(_cfg(tmp_path, synth_world, "ref"))
    cfg = _cfg(tmp_path, synth_world, "out")
    out = cfg.out

    # the disk fills up after the first unit's samples: that unit is committed, the next one cannot be
    from resim.shards.writer import ShardWriter

    real, state = ShardWriter.write, {"first": None}

    def write(self, sample):
        unit = sample["__key__"].rsplit("_f", 1)[0]
        state["first"] = state["first"] or unit
        if unit != state["first"]:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, sample)

    monkeypatch.setattr(ShardWriter, "write", write)
    with pytest.raises(OutputError, match=r"write of unit .*No space left on device.*rerun"):
        runner.run(cfg)
    commits, tars, index = _state(out)
    assert len(commits) == 1, commits
    # nothing half-written: every tar has its index and its unit's marker; no temporary files anywhere
    assert [t for t in tars if not t.endswith(".tar")] == [] and len(tars) == len(index)
    assert all(any(t.startswith(c) for c in commits) for t in tars), (tars, commits)
    assert not [p for p in out.rglob(".*") if p.name != ".lock"]

    # the command line says it in one line, exit 1
    monkeypatch.setattr(ShardWriter, "write", write)
    rc = main(["pipeline", "run", str(REPO / "configs/pipeline/synthetic.yaml"), "--out", str(out), "--no-progress",
               "--set", f"sources.synthetic.root={cfg.sources.synthetic.root}", "--set", "ray.executor=local",
               "--set", "sources.synthetic.layouts=[opendv,carla]",
               *[a for kv in ("encode.height_px=16", "encode.width_px=24", "encode.frames_height_px=16",
                              "encode.frames_width_px=24", "clip.stride_frames=40") for a in ("--set", kv)]])
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip() and not line.startswith("[pipeline]")]
    assert rc == 1 and len(err) == 1 and err[0].startswith("resim pipeline run: error: write of unit"), err

    # space again: a plain rerun completes it, equal to an uninterrupted run
    monkeypatch.setattr(ShardWriter, "write", real)
    res = runner.run(cfg)
    assert res.skipped == 1 and res.stats["units"] == ref.stats["units"]
    assert res.stats["clips"]["total"] == ref.stats["clips"]["total"]
    digests = {p.stem: json.loads(p.read_text())["sha256"] for p in sorted((out / "index").glob("*.json"))}
    ref_digests = {p.stem: json.loads(p.read_text())["sha256"] for p in sorted((ref.out / "index").glob("*.json"))}
    assert digests == ref_digests


def test_a_unit_without_its_commit_marker_fails_the_run(tmp_path, synth_world, monkeypatch):
    from resim.pipeline import resume, runner

    monkeypatch.setattr(resume, "write_marker", lambda out, state: None)    # a writer that "forgets" to commit
    with pytest.raises(runner.IncompleteRun, match=r"units ran but did not commit"):
        runner.run(_cfg(tmp_path, synth_world, "out"))


def test_an_unfinished_mp4_is_an_io_error_and_enospc_when_the_temp_folder_is_full(monkeypatch, tmp_path):
    import cv2

    from resim.shards import video

    class Mute:                       # what OpenCV does on a full disk: opens, accepts frames, writes nothing
        def __init__(self, path, *a):
            open(path, "wb").close()

        def isOpened(self):
            return True

        def write(self, frame):
            pass

        def release(self):
            pass

    frames = np.zeros((3, 16, 24, 3), np.uint8)
    assert len(video.encode_mp4(frames, 10.0)) > 0                     # the real writer works
    monkeypatch.setattr(cv2, "VideoWriter", Mute)
    with pytest.raises(OSError) as e:
        video.encode_mp4(frames, 10.0)
    assert e.value.errno == errno.EIO and "incomplete mp4" in str(e.value)

    class Usage:
        free = 0
    monkeypatch.setattr(video.shutil, "disk_usage", lambda p: Usage)
    with pytest.raises(OSError) as e:
        video.encode_mp4(frames, 10.0)
    assert e.value.errno == errno.ENOSPC and "TMPDIR" in str(e.value)


def test_ray_passes_a_stage_output_error_as_text_and_the_driver_finds_it():
    from resim.pipeline.runner import output_error

    class RayLike(Exception):         # Ray Data's UserCodeException keeps the stage's exception as text only
        pass

    text = ("ray::MapWorker(MapBatches(EncodeStage)).submit()\n  File \"base.py\", line 104, in run_one\n"
            "resim.pipeline.stages.base.OutputError: encode of unit u1: cannot write after 4 attempts: [Errno 28] x\n"
            "The above exception was the direct cause of the following exception:\nUserCodeException")
    err = output_error(RayLike(text))
    assert isinstance(err, OutputError) and str(err) == "encode of unit u1: cannot write after 4 attempts: [Errno 28] x"
    assert output_error(RuntimeError("a bug of ours")) is None
    assert output_error(OSError(errno.ENOSPC, "No space left on device")) is not None
    assert output_error(OSError(errno.ENOENT, "gone")) is None
