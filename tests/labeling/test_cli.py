"""`resim label`: output per window, and clear errors on unreadable input."""
import json
import os

import cv2
import pytest

from resim.cli import main


@pytest.fixture(scope="module")
def left_turn_video(tmp_path_factory, render):
    frames, _ = render(61, 10.0, 8.0, speed_mps=6.0, hfov_deg=80.0, seed=5)   # 6 s, +48 deg
    path = tmp_path_factory.mktemp("vid") / "left.mp4"
    wr = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (frames.shape[2], frames.shape[1]))
    assert wr.isOpened()
    for f in frames:
        wr.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    wr.release()
    return path


def test_label_json_lines(left_turn_video, capsys):
    assert main(["label", str(left_turn_video), "--json", "--window-s", "4", "--stride-s", "1"]) == 0
    out = capsys.readouterr()
    rows = [json.loads(line) for line in out.out.splitlines()]
    assert [(r["start_s"], r["end_s"]) for r in rows] == [(0.0, 4.0), (1.0, 5.0), (2.0, 6.0)]
    for r in rows:
        assert set(r) == {"start_s", "end_s", "command", "yaw_deg", "confidence", "turn_threshold_deg",
                          "turn_rate_threshold_deg_s"}
        assert (r["turn_threshold_deg"], r["turn_rate_threshold_deg_s"]) == (15.5, 3.875)
        assert r["command"] == "Turning left"
        assert 28 < r["yaw_deg"] < 36                          # 8 deg/s x 4 s = 32
        assert 0.5 < r["confidence"] <= 1
    assert "left.mp4" in out.err and "10 Hz" in out.err and "rig unknown" in out.err
    # one curve from the first frame: no straight driving to pool the FOE over, and the summary says so
    assert "FOE per_pair (per pair until 3 s of straight driving is seen)" in out.err


def test_steady_curve_is_a_turn_at_a_2_s_window_and_says_which_threshold(render, tmp_path, capsys):
    """6.5 deg/s for 4 s: --window-s 2 reads ~13 deg per window, "Moving forward" against 15.5 deg per window
    before; the threshold now scales with the window (7.75 deg over 2 s, 3.875 deg/s), and says so."""
    frames, _ = render(41, 10.0, 6.5, speed_mps=6.0, hfov_deg=80.0, seed=7)
    path = tmp_path / "curve.mp4"
    wr = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (frames.shape[2], frames.shape[1]))
    for f in frames:
        wr.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    wr.release()
    for window_s, thr in (("2", 7.75), ("4", 15.5)):
        assert main(["label", str(path), "--json", "--window-s", window_s]) == 0
        out = capsys.readouterr()
        rows = [json.loads(line) for line in out.out.splitlines()]
        assert rows and all(r["command"] == "Turning left" for r in rows), rows
        assert all(r["turn_threshold_deg"] == thr and r["turn_rate_threshold_deg_s"] == 3.875 for r in rows)
        assert f"turn threshold {thr:g} deg over {window_s} s (3.875 deg/s)" in out.err


def test_help_states_the_threshold_as_degrees_per_window_and_a_rate(capsys):
    with pytest.raises(SystemExit):
        main(["label", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "15.5 by default) is degrees over a 4-s window" in text and "3.875 deg/s" in text
    assert "--window-s 2: 7.75 deg" in text


def test_label_with_known_rig(left_turn_video, capsys):
    # the renderer's camera is on the pose point (0 m ahead), 1.5 m high
    assert main(["label", str(left_turn_video), "--json", "--set", "flow.camera_ahead_m=0",
                 "--set", "flow.camera_height_m=1.5"]) == 0
    out = capsys.readouterr()
    rows = [json.loads(line) for line in out.out.splitlines()]
    assert rows and all(r["command"] == "Turning left" and 28 < r["yaw_deg"] < 36 for r in rows), rows
    assert "rig: camera 0 m ahead of the rear axle, 1.5 m high" in out.err


def test_label_table_and_short_video(left_turn_video, capsys):
    assert main(["label", str(left_turn_video), "--window-s", "10"]) == 0
    out = capsys.readouterr()
    lines = out.out.splitlines()
    assert lines[0].split() == ["start_s", "end_s", "command", "yaw_deg", "confidence"]
    assert len(lines) == 2 and "Turning left" in lines[1]    # one short window for a 6 s video
    assert "one short window" in out.err


@pytest.mark.parametrize("content,reason", [(None, "no such file"), (b"not a video at all\n" * 10, "cannot open")])
def test_unreadable_input_names_file_and_reason(tmp_path, capsys, content, reason):
    p = tmp_path / "broken.mp4"
    if content is not None:
        p.write_bytes(content)
    assert main(["label", str(p)]) == 1
    err = capsys.readouterr().err
    assert str(p) in err and reason in err


def test_bad_override_is_a_config_error(left_turn_video, capsys):
    assert main(["label", str(left_turn_video), "--set", "flow.hfov_deg=500"]) == 2
    assert "hfov_deg" in capsys.readouterr().err


def test_progress_bar_reports_video_seconds_and_changes_nothing(left_turn_video, capsys):
    from resim.labeling.windows import label_video

    quiet = label_video(left_turn_video)
    assert capsys.readouterr().err == ""                     # the library is silent unless asked
    shown = label_video(left_turn_video, progress=True)
    err = capsys.readouterr().err
    assert "left.mp4" in err and "/6 s of video" in err and "100%" in err, err
    assert [w.yaw_deg for w in shown.windows] == [w.yaw_deg for w in quiet.windows]


def test_cli_draws_no_progress_bar_when_stderr_is_not_a_terminal(left_turn_video, capsys):
    assert main(["label", str(left_turn_video), "--json"]) == 0
    assert "s of video" not in capsys.readouterr().err     # logs and pipes get the summary line only


@pytest.mark.parametrize("args,msg", [
    (["--window-s", "nan"], "window_s must be finite"),
    (["--stride-s", "inf"], "--stride-s must be a finite number > 0"),
    (["--set", "flow.sample_hz=.nan"], "sample_hz must be finite"),
    (["--set", "command.confidence_scale_deg=.nan"], "confidence_scale_deg must be finite"),
    (["--set", "flow.max_flow_frac=0"], "max_flow_frac must be in (0, 1]"),
    (["--set", "flow.robust_scale_px=-1"], "robust_scale_px > 0"),
])
def test_nan_and_out_of_range_values_are_config_errors(left_turn_video, capsys, args, msg):
    """NaN passed every `x <= 0` check: zero windows and exit 0, a NaN confidence in --json, or a traceback."""
    assert main(["label", str(left_turn_video), *args]) == 2
    assert msg in capsys.readouterr().err


def test_window_length_comes_from_the_config_unless_given(left_turn_video, capsys):
    assert main(["label", str(left_turn_video), "--json", "--set", "command.window_s=6"]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [(r["start_s"], r["end_s"]) for r in rows] == [(0.0, 6.0)]
    assert main(["label", str(left_turn_video), "--json", "--set", "command.window_s=6", "--window-s", "4"]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [(r["start_s"], r["end_s"]) for r in rows] == [(0.0, 4.0), (2.0, 6.0)]


def test_a_window_between_samples_sums_its_own_length_of_pairs(left_turn_video):
    """Pairs count in the window holding their midpoint: [0.25, 4.25] at 10 Hz sums 40 pairs (4 s), as [0, 4]
    does; both ends inclusive summed 41 (4.1 s, +2.5 % on every such window)."""
    from resim.labeling.windows import label_video

    aligned = label_video(left_turn_video, window_s=4.0, stride_s=1.0)
    offset = label_video(left_turn_video, window_s=4.0, stride_s=0.25)
    inc = aligned.yaw_inc_deg
    w = {(x.start_s, x.end_s): x.yaw_deg for x in offset.windows}
    assert w[(0.25, 4.25)] == pytest.approx(inc[2:42].sum())    # pairs (0.2, 0.3) ... (4.1, 4.2)
    assert w[(0.0, 4.0)] == pytest.approx(inc[0:40].sum())


def test_truncated_file_is_labelled_up_to_the_cut_with_a_warning(left_turn_video, tmp_path, capsys):
    """A download cut short: the labels of the part that decodes, exit 0, and a warning on stderr naming the file,
    the seconds decoded and the container's duration (the PyAV reader used to abort: "decoding failed")."""
    import shutil
    import subprocess

    if shutil.which("ffmpeg") is None:
        pytest.skip("ffmpeg is needed to write the test video")
    whole = tmp_path / "whole.mp4"   # index (moov) in front, as a streamed download has it
    p = subprocess.run(["ffmpeg", "-v", "error", "-y", "-i", str(left_turn_video), "-c:v", "libx264", "-crf", "18",
                        "-movflags", "+faststart", str(whole)], capture_output=True)
    if p.returncode != 0:
        pytest.skip(f"ffmpeg/libx264 unavailable: {p.stderr.decode()[-200:]}")
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(whole.read_bytes()[: int(whole.stat().st_size * 0.6)])
    for decoder in ("pyav", "opencv"):
        assert main(["label", str(cut), "--json", "--window-s", "2", "--set", f"flow.decoder={decoder}"]) == 0
        out = capsys.readouterr()
        rows = [json.loads(line) for line in out.out.splitlines()]
        assert rows and rows[-1]["end_s"] < 5.0 and all(12 < r["yaw_deg"] < 20 for r in rows), rows   # 8 deg/s
        warn = [line for line in out.err.splitlines() if "warning" in line]
        assert len(warn) == 1 and str(cut) in warn[0] and "of the 6.10 s the container states" in warn[0], out.err
        assert "the labels cover 0-" in warn[0]
    assert main(["label", str(whole), "--json", "--window-s", "2"]) == 0
    assert "warning" not in capsys.readouterr().err


def test_a_truncated_video_is_one_line_without_ffmpegs_own_complaint(left_turn_video, tmp_path):
    # FFmpeg writes "moov atom not found" to the process's stderr (not through Python): run the real command
    import subprocess
    import sys

    p = tmp_path / "cut.mp4"
    p.write_bytes(left_turn_video.read_bytes()[:3000])           # the index (moov box) is at the end: cut off
    env = {k: v for k, v in os.environ.items() if k != "OPENCV_FFMPEG_LOGLEVEL"}
    r = subprocess.run([sys.executable, "-m", "resim", "label", str(p)], capture_output=True, text=True,
                       env=env, timeout=120)
    assert r.returncode == 1 and str(p) in r.stderr
    assert "moov atom" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
