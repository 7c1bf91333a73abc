"""Bad input, transient I/O and failed runs, driven through the stage classes and readers directly (no Ray).

* a reader's SourceError reaches the quarantine row with the file/frame it named;
* malformed optional NAVSIM fields, a CSV that is not UTF-8 or has a bad row, a frame rate the clip
  cannot be honestly cut from, an unreadable CARLA results file: quarantined (or a row), never a crash;
* a video whose frame rate is variable or absurd (90000 fps) is quarantined with that reason, not as "truncated";
* a plain OSError is retried (``quarantine.max_attempts``), and the attempt count is the same in the
  row and in the commit marker;
* a run that committed nothing does not lock OUT to its config.
"""
import errno
import gzip
import json
import pathlib
import pickle
import re
import shutil
from fractions import Fraction

import cv2
import numpy as np
import pytest

from resim.config import ConfigError
from resim.pipeline import quarantine, resume, runner
from resim.pipeline.runner import EnumerateStage
from resim.pipeline.sources.safe_pickle import load_restricted
from resim.pipeline.stages.base import Stage
from resim.pipeline.stages.cut import CutStage

from .conftest import make_config

NAVSIM_CLIP = "sources.navsim.clip={fps_hz: 2.0, num_history_frames: 1, num_future_frames: 8, stride_frames: 5}"


def _only(root_kind: str, root, tmp_path, *overrides):
    """A config reading one real-layout source (a copy of part of the synthetic world) and nothing else."""
    extra = [NAVSIM_CLIP, "sources.navsim.split=synth"] if root_kind == "navsim" else []
    return make_config(tmp_path / "out", ["sources.synthetic.root=null", f"sources.{root_kind}.root={root}",
                                          *extra, *overrides])


def _opendv_config(root, tmp_path, *overrides):
    return _only("opendv", root, tmp_path, "sources.opendv.start_discard_s=0", "sources.opendv.end_discard_s=0",
                 "sources.opendv.min_height_px=32", *overrides)


def _cut_all(cfg) -> tuple[dict, list[dict]]:
    """Enumerate + cut: ({item_id: state}, enumerate quarantine rows)."""
    states, bad = EnumerateStage(cfg)()
    stage = CutStage(cfg)
    return {s["item_id"]: stage.run_one(s) for s in states}, bad


@pytest.fixture
def part(tmp_path, synth_world):
    """part("navsim") -> a private copy of that layout of the session's synthetic world."""
    def copy(kind: str) -> pathlib.Path:
        return shutil.copytree(synth_world / kind, tmp_path / kind)
    return copy


def _navsim_log(root) -> pathlib.Path:
    return sorted((root / "navsim_logs" / "synth").glob("*.pkl"))[0]


def _edit_log(path: pathlib.Path, edit) -> None:
    frames = load_restricted(path)   # the readers' restricted unpickler: no code runs, even in a test
    edit(frames)
    path.write_bytes(pickle.dumps(frames, protocol=5))


# ----------------------------------------------------------------------------- reasons name the file
def test_quarantine_reason_names_the_file_and_frame_the_reader_named(part, tmp_path):
    root = part("navsim")
    log = _navsim_log(root)
    _edit_log(log, lambda fr: fr[3].pop("timestamp"))
    units, _ = _cut_all(_only("navsim", root, tmp_path))
    st = units[log.stem]
    assert st["status"] == "quarantined"
    [row] = st["quarantine"]
    assert row["item"] == log.stem                                    # the unit's item
    assert row["reason"].startswith(f"{log} frame 3: ") and "timestamp" in row["reason"]


def test_reason_is_not_prefixed_twice_when_the_reader_names_the_item_itself():
    from resim.pipeline.sources.episode import SourceError
    from resim.pipeline.stages.base import source_error_reason

    assert source_error_reason(SourceError("a.mp4", "too short"), "a.mp4") == "too short"
    e = SourceError("r/anno/00002.json.gz", "malformed")
    assert source_error_reason(e, "r") == "r/anno/00002.json.gz: malformed"


# ------------------------------------------------------------------------- malformed optional fields
@pytest.mark.parametrize("key, value, words", [
    ("ego_dynamic_state", 5.0, "1 value(s)"),
    ("ego_dynamic_state", ["n/a", "n/a"], "n/a"),
    ("driving_command", ["a", "b", "c", "d"], "driving_command"),
    ("driving_command", [0, 1, 0], "3 value(s)"),
    ("driving_command", [0, 2, 0, 0], "one-hot"),
])
def test_malformed_optional_navsim_fields_quarantine_the_log(part, tmp_path, key, value, words):
    root = part("navsim")
    log = _navsim_log(root)
    _edit_log(log, lambda fr: fr[3].__setitem__(key, value))
    st = _cut_all(_only("navsim", root, tmp_path))[0][log.stem]       # was: TypeError / ValueError out of cut
    assert st["status"] == "quarantined"
    reason = st["quarantine"][0]["reason"]
    assert f"{log} frame 3" in reason and key in reason and words in reason, reason


def test_absent_optional_navsim_fields_are_fine(part, tmp_path):
    root = part("navsim")
    log = _navsim_log(root)
    _edit_log(log, lambda fr: [f.pop(k) for f in fr for k in ("ego_dynamic_state", "driving_command")])
    st = _cut_all(_only("navsim", root, tmp_path))[0][log.stem]
    assert st["status"] == "ok" and st["episode"]["has_poses"]


# --------------------------------------------------------------------------- transient I/O is retried
def _flaky(monkeypatch, module, name, match, fail_times: int):
    """Make ``module.name(path, ...)`` raise EIO for the first ``fail_times`` calls on matching paths."""
    real = getattr(module, name)
    calls = {"failed": 0}

    def flaky(self_or_path, *a, **k):
        if match(str(self_or_path)) and calls["failed"] < fail_times:
            calls["failed"] += 1
            raise OSError(errno.EIO, "Input/output error (test)")
        return real(self_or_path, *a, **k)

    monkeypatch.setattr(module, name, flaky)
    return calls


@pytest.mark.parametrize("fail_times, status, attempts", [(1, "ok", 2), (5, "quarantined", 2)])
def test_navsim_pickle_read_error_is_retried(part, tmp_path, monkeypatch, fail_times, status, attempts):
    root = part("navsim")
    cfg = _only("navsim", root, tmp_path, "quarantine.max_attempts=2")
    states, _ = EnumerateStage(cfg)()
    _flaky(monkeypatch, pathlib.Path, "read_bytes", lambda p: p.endswith(".pkl"), fail_times)
    st = CutStage(cfg).run_one(states[0])
    assert (st["status"], st["attempts"]) == (status, attempts)       # was: quarantined on the 1st try
    if status == "quarantined":
        [row] = st["quarantine"]
        assert row["attempts"] == 2 and row["reason"].startswith("I/O error after 2 attempts")


def test_carla_annotation_read_error_is_retried_but_bad_gzip_is_not(part, tmp_path, monkeypatch):
    root = part("carla")
    cfg = _only("carla", root, tmp_path, "quarantine.max_attempts=3")
    states, _ = EnumerateStage(cfg)()
    calls = _flaky(monkeypatch, gzip, "open", lambda p: p.endswith(".json.gz"), 2)
    st = CutStage(cfg).run_one(states[0])
    assert calls["failed"] == 2 and (st["status"], st["attempts"]) == ("ok", 3)

    route = root / states[0]["item_id"]
    (route / "anno" / "00002.json.gz").write_bytes(b"\x1f\x8b\x08garbage")   # corrupt data: not retried
    monkeypatch.undo()                                                # gzip.open as it was
    st = CutStage(cfg).run_one(EnumerateStage(cfg)()[0][0])
    assert (st["status"], st["attempts"]) == ("quarantined", 1)
    assert st["quarantine"][0]["reason"].startswith(f"{route / 'anno' / '00002.json.gz'}: malformed annotation")


class _AlwaysIOError(Stage):
    name = "cut"
    calls = 0

    def process(self, state):
        _AlwaysIOError.calls += 1
        raise OSError(errno.EIO, "NFS hiccup")


def test_retry_counts_agree_between_row_and_marker_across_reruns(config_for):
    cfg = config_for("out", "quarantine.max_attempts=2", "quarantine.retry_quarantined=true")
    states, _ = EnumerateStage(cfg)()
    _AlwaysIOError.calls = 0
    st = _AlwaysIOError(cfg).run_one(states[0])
    assert _AlwaysIOError.calls == 2
    assert st["quarantine"][0]["attempts"] == resume.summary(st)["attempts"] == 2     # marker said 1
    fresh = EnumerateStage(cfg)()[0][0]
    todo, _ = resume.plan([fresh], {st["unit_id"]: resume.summary(st)}, True)
    st2 = _AlwaysIOError(cfg).run_one(todo[0])
    assert st2["quarantine"][0]["attempts"] == resume.summary(st2)["attempts"] == 4   # 2 tries + 2 tries


# ---------------------------------------------------------------------------- CARLA results problems
def test_unreadable_carla_results_file_becomes_a_quarantine_row(part, tmp_path):
    root = part("carla")
    (root / "simulation_results.json").write_text('{"_checkpoint": ')
    units, bad = _cut_all(_only("carla", root, tmp_path))
    [row] = bad                                                       # was: no row at all
    assert row["item"] == str(root / "simulation_results.json") and row["status"] == "dropped"
    assert row["stage"] == "enumerate" and "malformed results JSON" in row["reason"]
    assert "no outcome" in row["reason"]
    for st in units.values():                                         # the routes still run, outcome unknown
        assert st["status"] == "ok" and st["episode"]["hazard"] is None
        assert any("simulation_results.json" in w for w in st["episode"]["warnings"])
    quarantine.write_rows(tmp_path / "out", "_enumerate", bad)        # what runner.run does with them
    assert [r["item"] for r in quarantine.read_table(tmp_path / "out")] == [row["item"]]


@pytest.mark.parametrize("fail_times", [1, 99])
def test_carla_results_file_read_error_is_retried(part, tmp_path, monkeypatch, fail_times):
    root = part("carla")
    cfg = _only("carla", root, tmp_path, "quarantine.max_attempts=2")
    units, bad = _cut_all(cfg)
    hazards = {i: st["episode"]["hazard"] for i, st in units.items()}
    assert bad == [] and None not in hazards.values()

    def flaky():
        return _flaky(monkeypatch, pathlib.Path, "read_text", lambda p: p.endswith("simulation_results.json"),
                      fail_times)

    calls = flaky()
    states, bad = EnumerateStage(cfg)()                                         # driver side: list_items
    if fail_times == 1:                                                         # was: a `dropped` row, no retry
        assert bad == [] and calls["failed"] == 1 and len(states) == len(units)
    else:                                                                       # persistent: quarantines the
        [row] = bad                                                             # source, like any listing failure
        assert states == [] and (row["status"], row["attempts"], row["item"]) == ("quarantined", 2, str(root))
        assert row["reason"].startswith("I/O error after 2 attempts") and "simulation_results.json" in row["reason"]
        monkeypatch.undo()
        states, _ = EnumerateStage(cfg)()
        calls = flaky()
    calls["failed"] = 0
    st = CutStage(cfg).run_one(states[0])                                       # a stage's reader reads it too
    if fail_times == 1:                                                         # was: ok at once, hazard None
        assert (st["status"], st["attempts"]) == ("ok", 2)
        assert st["episode"]["hazard"] == hazards[st["item_id"]] and st["episode"]["warnings"] == []
    else:
        assert (st["status"], st["attempts"]) == ("quarantined", 2)
        assert st["quarantine"][0]["reason"].startswith("I/O error after 2 attempts")


# ---------------------------------------------------------------------------------- episode warnings
def test_episode_warnings_are_saved_as_warning_rows(part, tmp_path):
    from resim.pipeline import report

    root = part("carla")
    route = sorted(p for p in root.iterdir() if (p / "anno").is_dir())[0]
    anno = route / "anno" / "00003.json.gz"
    a = json.loads(gzip.decompress(anno.read_bytes()))
    a["theta"] = None                                                           # NaN compass: interpolated
    anno.write_bytes(gzip.compress(json.dumps(a).encode()))
    cfg = _only("carla", root, tmp_path, "ray.executor=local")
    st = _cut_all(cfg)[0][route.name]
    assert st["status"] == "ok" and "interpolated" in st["episode"]["warnings"][0]
    [row] = st["quarantine"]                                                    # was: no row, only the state
    assert (row["item"], row["status"], row["stage"]) == (route.name, "warning", "cut")
    assert row["reason"] == st["episode"]["warnings"][0]

    res = runner.run(cfg, progress=False)                                       # end to end: saved in OUT
    assert [(r["item"], r["status"], r["reason"]) for r in quarantine.read_table(res.out)] == \
        [(route.name, "warning", row["reason"])]
    marker = resume.read_markers(res.out)[st["unit_id"]]
    assert (marker["status"], marker["num_quarantined"], marker["num_warnings"]) == ("ok", 0, 1)
    assert marker["written"]["num_samples"] > 0                                 # the unit was used
    stats = res.stats
    assert stats["quarantine"]["rows"] == 0 and stats["units"]["quarantined"] == 0
    assert stats["warnings"]["rows"] == 1 and stats["warnings"]["units"] == 1
    assert stats["warnings"]["examples"] == [f"{route.name} [cut]: {row['reason']}"]
    assert "warnings          1 in 1 unit(s)" in report.format_summary(stats, res.out, None)


# ----------------------------------------------------------------------------------- OpenDV videos.csv
def test_opendv_csv_not_utf8_quarantines_the_source_with_a_clear_reason(part, tmp_path):
    root = part("opendv")
    data = "video_id,start_discard_s\nsynth/café,0\n".encode("latin-1")
    (root / "videos.csv").write_bytes(data)
    units, bad = _cut_all(_opendv_config(root, tmp_path))             # was: UnicodeDecodeError
    assert units == {}
    [row] = bad
    assert row["status"] == "quarantined" and row["item"] == str(root)
    offset = data.index(b"\xe9")
    assert row["reason"].startswith(f"{root / 'videos.csv'}: not UTF-8 text (byte b'\\xe9' at offset {offset})"), \
        row["reason"]


def test_opendv_csv_bad_row_quarantines_only_its_video(part, tmp_path):
    root = part("opendv")
    vid, other = sorted((root / "synth").glob("*.mp4"))
    (root / "videos.csv").write_text(f"video_id,start_discard_s,end_discard_s\nsynth/{vid.stem},abc,0\n"
                                     f"synth/{other.stem},0,0\n")
    units, bad = _cut_all(_opendv_config(root, tmp_path))
    assert bad == []                                                  # was: the whole source quarantined
    assert units[f"synth/{other.name}"]["status"] == "ok"
    st = units[f"synth/{vid.name}"]
    assert st["status"] == "quarantined"
    reason = st["quarantine"][0]["reason"]
    assert reason.startswith(f"{root / 'videos.csv'}:2: bad discard value for video 'synth/{vid.stem}'"), reason


def test_opendv_csv_row_without_video_id_still_quarantines_the_source(part, tmp_path):
    root = part("opendv")
    (root / "videos.csv").write_text("video_id,start_discard_s\n,3\n")
    units, bad = _cut_all(_opendv_config(root, tmp_path))
    assert units == {} and "videos.csv:2: row has no video_id" in bad[0]["reason"]


# --------------------------------------------------------------------------------------- frame rates
def test_navsim_frame_rate_comes_from_the_timestamps(part, tmp_path):
    from resim.pipeline.sources.episode import SourceError
    from resim.pipeline.sources.navsim import NavsimConfig, NavsimReader

    root = part("navsim")
    log = _navsim_log(root)
    reader = NavsimReader(NavsimConfig(root=root, split="synth"))
    assert reader.open(log.stem).fps_hz == 2.0                        # the 2 Hz key frames of OpenScene

    def ten_hz(frames):
        t0 = frames[0]["timestamp"]
        for i, f in enumerate(frames):
            f["timestamp"] = t0 + i * 100_000 + (7 if i % 2 else 0)     # 0.1 s apart, µs jitter
    _edit_log(log, ten_hz)
    ep = reader.open(log.stem)
    assert ep.fps_hz == 10.0 and ep.duration_s == pytest.approx(ep.num_frames / 10)   # was: 2.0 (5x too slow)
    # a 10 Hz log cut at 2 Hz takes every 5th frame, and is too short here (16 frames = 1.6 s)
    st = _cut_all(_only("navsim", root, tmp_path))[0][log.stem]
    assert st["status"] == "quarantined" and "too short: 4 frames at 2 Hz" in st["quarantine"][0]["reason"]

    _edit_log(log, lambda fr: fr.pop(5))                              # a missing frame: 0.2 s in a 10 Hz log
    with pytest.raises(SourceError, match=r"missing frame\(s\): 1 gap\(s\) > 0.15 s in a 10 Hz log"):
        reader.open(log.stem)


def test_opendv_video_below_the_clip_rate_is_quarantined(tmp_path):
    src = tmp_path / "videos"
    src.mkdir()
    w = cv2.VideoWriter(str(src / "five_fps.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 5.0, (112, 64))
    for i in range(60):                                               # 12 s at 5 fps
        w.write(np.full((64, 112, 3), 4 * i, np.uint8))
    w.release()
    st = _cut_all(_opendv_config(src, tmp_path))[0]["five_fps.mp4"]   # was: ok, every frame shown twice
    assert st["status"] == "quarantined"
    assert st["quarantine"][0]["reason"] == "frame rate 5 fps is below the output rate 10 Hz (frames would be repeated)"


def _pyav_video(path, pts, rate, time_base=None):
    """A tiny H.264 video (32x32) whose frames have presentation timestamps ``pts`` (in ``time_base``, default
    1 / ``rate``), written with PyAV: timings OpenCV's writer cannot produce."""
    av = pytest.importorskip("av")
    with av.open(str(path), "w") as c:
        s = c.add_stream("libx264", rate=rate)
        s.width = s.height = 32
        s.pix_fmt = "yuv420p"
        if time_base is not None:
            s.codec_context.time_base = time_base
        for i, t in enumerate(pts):
            f = av.VideoFrame.from_ndarray(np.full((32, 32, 3), 6 * i % 256, np.uint8), format="rgb24")
            f.pts = t
            if time_base is not None:
                f.time_base = time_base
            for pkt in s.encode(f):
                c.mux(pkt)
        for pkt in s.encode():
            c.mux(pkt)


_PAUSES = [0] + list(np.cumsum([1 if i % 3 else 7 for i in range(39)]))   # 30 fps ticks, every third frame late


@pytest.mark.parametrize("name,pts,rate,time_base,reason", [
    # the container's rate is its time base: was "too short: 0.0 s minus discards ..."
    ("absurd_rate.mp4", range(12), 90000, None, r"implausible frame rate 90000 fps \(more than 240"),
    # frames 1/30 s apart in a 1/90000 time base stated as the rate; OpenCV: 30000 fps x 1.3 s = 39000 frames, so
    # was "truncated video: header says 39000 frames but frame 38999 cannot be decoded"
    ("time_base_as_rate.mkv", [3000 * i for i in range(40)], 90000, Fraction(1, 90000),
     r"implausible frame rate \d+ fps \(more than 240"),
    # irregular timestamps: was "truncated video: header says 118 frames ..." (mkv) and "frame rate 9.67742 fps is
    # below the output rate" (mp4, whose average rate the pauses lower)
    ("variable_rate.mkv", _PAUSES, 30, None, r"variable frame rate: frame intervals from 33 to 233 ms in the first "),
    ("variable_rate.mp4", _PAUSES, 30, None, r"variable frame rate: frame intervals from 33.33 to 233.3 ms in the "
                                             r"first 40 frames \(13 off the usual 33.33 ms\); re-encode it"),
])
def test_opendv_video_with_a_variable_or_absurd_frame_rate_is_quarantined_with_that_reason(
        tmp_path, name, pts, rate, time_base, reason):
    src = tmp_path / "videos"
    src.mkdir()
    _pyav_video(src / name, pts, rate, time_base)
    st = _cut_all(_opendv_config(src, tmp_path))[0][name]
    assert st["status"] == "quarantined"
    assert re.match(reason, st["quarantine"][0]["reason"]), st["quarantine"][0]["reason"]
    assert "truncated" not in st["quarantine"][0]["reason"]


@pytest.mark.parametrize("name,rate", [("ntsc.mkv", Fraction(30000, 1001)), ("fast.mkv", 120), ("ntsc.mp4", 29.97)])
def test_a_constant_frame_rate_is_not_taken_for_a_variable_one(tmp_path, name, rate):
    """Matroska's 1 ms ticks round a 29.97 fps file's intervals to 33 or 34 ms, a 120 fps file's to 8 or 9 ms."""
    from resim.pipeline.sources.frame_timing import frame_timing_problem

    rate = Fraction(rate).limit_denominator(1001)
    _pyav_video(tmp_path / name, range(30), rate)
    fps = cv2.VideoCapture(str(tmp_path / name)).get(cv2.CAP_PROP_FPS)
    assert abs(fps - float(rate)) < 0.01 and frame_timing_problem(tmp_path / name, fps) is None


# ------------------------------------------------------------------------------ OUT and failed runs
def test_failed_run_with_nothing_committed_does_not_lock_out(config_for, tmp_path, monkeypatch):
    out = tmp_path / "out"
    first = config_for("out", "shards.max_samples_per_shard=7")

    def fail(cfg):
        raise ConfigError("a mistake only found at run time")
    monkeypatch.setattr(runner, "ensure_synthetic", fail)
    with pytest.raises(ConfigError, match="run time"):
        runner.run(first)
    assert (out / "config_hash.txt").exists()
    for sub in ("prompts", "shards", "_staging"):                     # leftovers of the failed attempt
        (out / sub).mkdir(exist_ok=True)
        (out / sub / "leftover").write_text("x")

    fixed = config_for("out", "shards.max_samples_per_shard=8")
    runner.prepare_out(fixed)                                         # was: "a different config"
    from resim.pipeline.stages.encode import data_config_hash

    assert (out / "config_hash.txt").read_text().strip() == data_config_hash(fixed)
    assert not any((out / sub).exists() for sub in ("prompts", "shards", "_staging"))

    resume.write_marker(out, EnumerateStage(fixed)()[0][0])          # one committed unit
    with pytest.raises(ConfigError, match="different config .* 1 committed units"):
        runner.prepare_out(first)
    assert (out / "config_hash.txt").read_text().strip() == data_config_hash(fixed)
    runner.prepare_out(fixed)                                         # the same config resumes
    assert len(resume.read_markers(out)) == 1
