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
