"""The labeler's two decoder paths (labeling/video.py) on an H.264 stream with B-frames."""
import shutil
import subprocess

import numpy as np
import pytest

from labeling.config import FlowConfig, LabelerConfig
from labeling.video import iter_grey_samples, probe
from labeling.windows import label_video

pytest.importorskip("av")


@pytest.fixture(scope="module")
def h264_30fps(tmp_path_factory, render):
    if shutil.which("ffmpeg") is None:
        pytest.skip("ffmpeg is needed to write an H.264 test video")
    frames, poses = render(91, 30.0, 10.0, speed_mps=6.0, hfov_deg=80.0, seed=7)    # 3 s, +30 deg
    h, w = frames.shape[1:3]
    path = tmp_path_factory.mktemp("h264") / "turn30.mp4"
    p = subprocess.run(["ffmpeg", "-v", "error", "-y", "-f", "rawvideo", "-pix_fmt", "rgb24", "-s", f"{w}x{h}",
                        "-r", "30", "-i", "-", "-c:v", "libx264", "-preset", "veryfast", "-bf", "3", "-crf", "18",
                        "-pix_fmt", "yuv420p", str(path)], input=frames.tobytes(), capture_output=True)
    if p.returncode != 0:
        pytest.skip(f"ffmpeg/libx264 unavailable: {p.stderr.decode()[-200:]}")
    return path, float(np.degrees(poses[-1, 2] - poses[0, 2]))


def test_pyav_skips_nonreference_frames_and_keeps_the_samples(h264_30fps):
    path, _ = h264_30fps
    info = probe(path)
    st10, st20, stcv = {}, {}, {}
    t_av = np.array([t for t, _ in iter_grey_samples(path, 10.0, 128, info, decoder="pyav", stats=st10)])
    t_cv = np.array([t for t, _ in iter_grey_samples(path, 10.0, 128, info, decoder="opencv", stats=stcv)])
    # x264 with B-frames: reference frames come every <= 0.1 s, so the non-reference ones are not decoded
    assert st10["nonref_skipped"] and st10["frames_decoded"] < 0.8 * stcv["frames_decoded"], (st10, stcv)
    assert stcv["frames_decoded"] == 91 and not stcv["nonref_skipped"]
    assert abs(len(t_av) - len(t_cv)) <= 1
    n = min(len(t_av), len(t_cv))
    assert np.all(np.abs(t_av[:n] - t_cv[:n]) <= 1 / 30 + 1e-6)   # at most one source frame later
    assert np.all(np.diff(t_av) <= 0.1 + 1 / 30 + 1e-6)
    # ... but not every 0.05 s: at 20 Hz the reader finds that out in the same decode and restarts with
    # every frame; nothing from the aborted pass may leak into the output
    t20 = np.array([t for t, _ in iter_grey_samples(path, 20.0, 128, info, decoder="pyav", stats=st20)])
    assert not st20["nonref_skipped"] and st20["frames_decoded"] == 91, st20
    assert np.all(np.diff(t20) > 0) and np.all(np.diff(t20) <= 0.05 + 1 / 30 + 1e-6)
    assert len(t20) >= 2 * len(t_av) - 2


def test_pyav_probe_on_a_clip_shorter_than_the_probe(h264_30fps):
    path, _ = h264_30fps
    info = probe(path)
    st = {}
    # probe window longer than the 3-s clip: the held-back samples must still all come out, once
    from labeling.video import _iter_pyav
    ts = [t for t, _ in _iter_pyav(info, 10.0, 128, probe_s=10.0, stats=st)]
    ref = [t for t, _ in iter_grey_samples(path, 10.0, 128, info, decoder="pyav")]
    assert ts == ref and st["nonref_skipped"]


def test_both_decoders_give_the_same_heading(h264_30fps):
    path, true = h264_30fps
    est = {d: label_video(path, LabelerConfig(flow=FlowConfig(decoder=d)), window_s=3.0).yaw_inc_deg.sum()
           for d in ("pyav", "opencv")}
    for d, v in est.items():
        assert abs(v - true) <= 0.12 * abs(true), (d, v, true)


def _x264(path, frames, fps: str, *extra):
    h, w = frames.shape[1:3]
    p = subprocess.run(["ffmpeg", "-v", "error", "-y", "-f", "rawvideo", "-pix_fmt", "rgb24", "-s", f"{w}x{h}",
                        "-r", fps, "-i", "-", "-c:v", "libx264", "-preset", "veryfast", "-bf", "3", "-crf", "18",
                        "-pix_fmt", "yuv420p", *extra, str(path)], input=frames.tobytes(), capture_output=True)
    if p.returncode != 0:
        pytest.skip(f"ffmpeg/libx264 unavailable: {p.stderr.decode()[-200:]}")
    return path


@pytest.fixture(scope="module")
def left_turn_25fps(render):
    frames, poses = render(126, 25.0, 8.0, speed_mps=6.0, hfov_deg=80.0, seed=5)    # 5 s, +40 deg
    return frames, float(np.degrees(poses[-1, 2] - poses[0, 2]))


@pytest.mark.parametrize("kind", ["rotated", "raw_h264", "avi"])
def test_both_decoders_read_odd_containers_alike(tmp_path, left_turn_25fps, kind):
    """A phone clip stored sideways with a rotation tag (PyAV used to label it from the sideways frames:
    'Moving forward'), a raw Annex-B stream with no frame times (times came from the decoded-frame count
    while B-frames were skipped: windows squeezed), and H.264 in AVI (decode-order times that go back)."""
    if shutil.which("ffmpeg") is None:
        pytest.skip("ffmpeg is needed to write the test videos")
    frames, true = left_turn_25fps
    if kind == "rotated":   # stored turned a quarter left; the tag turns it back for display
        stored = _x264(tmp_path / "stored.mp4", np.ascontiguousarray(np.rot90(frames, 1, axes=(1, 2))), "25")
        path = tmp_path / "rot.mp4"   # ffmpeg 5 writes the tag (a display matrix) only when remuxing
        subprocess.run(["ffmpeg", "-v", "error", "-y", "-i", str(stored), "-c", "copy", "-metadata:s:v:0",
                        "rotate=270", str(path)], check=True)
    elif kind == "raw_h264":
        path = _x264(tmp_path / "raw.h264", frames, "25", "-f", "h264")
    else:
        path = _x264(tmp_path / "v.avi", frames, "25")
    res = {d: label_video(path, LabelerConfig(flow=FlowConfig(decoder=d))) for d in ("pyav", "opencv")}
    for d, r in res.items():
        assert [(w.start_s, w.end_s) for w in r.windows] == [(0.0, 4.0)], (d, r.windows)
        assert np.all(np.diff(r.times_s) > 0) and abs(r.times_s[-1] - 5.0) <= 0.05, (d, r.times_s[-3:])
        assert abs(r.yaw_inc_deg.sum() - true) <= 0.12 * true, (d, r.yaw_inc_deg.sum(), true)
        assert r.windows[0].command == "Turning left", (d, r.windows)
    if kind == "raw_h264":
        assert res["pyav"].decode["timestamps"] == "frame count / fps"


def test_variable_frame_rate_uses_the_frame_times(tmp_path, render):
    """30 fps for 4 s, then 10 fps (a phone slowing its rate in the dark): OpenCV's path took frame count /
    average fps as the time and put the 4-s window's end 1.2 s late."""
    import fractions

    import av

    frames, poses = render(160, 30.0, 8.0, speed_mps=6.0, hfov_deg=80.0, seed=5)
    path = tmp_path / "vfr.mp4"
    with av.open(str(path), "w") as c:
        s = c.add_stream("mpeg4", rate=30)
        s.width, s.height, s.pix_fmt = frames.shape[2], frames.shape[1], "yuv420p"
        s.codec_context.time_base = fractions.Fraction(1, 30)
        s.bit_rate = 8_000_000   # the default (~1 Mbit/s) leaves blocks that shrink the flow
        for i in [i for i in range(160) if i < 120 or i % 3 == 0]:
            f = av.VideoFrame.from_ndarray(frames[i], format="rgb24")
            f.pts, f.time_base = i, fractions.Fraction(1, 30)
            for p in s.encode(f):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    true4 = float(np.degrees(poses[120, 2] - poses[0, 2]))
    for d in ("pyav", "opencv"):
        r = label_video(path, LabelerConfig(flow=FlowConfig(decoder=d)))
        assert abs(r.times_s[-1] - 159 / 30) <= 0.05, (d, r.times_s[-3:])
        assert abs(r.windows[0].yaw_deg - true4) <= 0.12 * true4, (d, r.windows[0], true4)
