"""The labeler's two decoder paths (labeling/video.py) on an H.264 stream with B-frames."""
import shutil
import subprocess

import numpy as np
import pytest

from labeling.config import FlowConfig, LabelerConfig
from labeling.video import _nonref_skip_ok, iter_grey_samples, probe
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
    assert _nonref_skip_ok(str(path), info.fps_hz, 10.0)          # x264 with B-frames: refs every <= 0.1 s
    assert not _nonref_skip_ok(str(path), info.fps_hz, 20.0)      # ... but not every 0.05 s
    t_av = np.array([t for t, _ in iter_grey_samples(path, 10.0, 128, info, decoder="pyav")])
    t_cv = np.array([t for t, _ in iter_grey_samples(path, 10.0, 128, info, decoder="opencv")])
    assert abs(len(t_av) - len(t_cv)) <= 1
    n = min(len(t_av), len(t_cv))
    assert np.all(np.abs(t_av[:n] - t_cv[:n]) <= 1 / 30 + 1e-6)   # at most one source frame later
    assert np.all(np.diff(t_av) <= 0.1 + 1 / 30 + 1e-6)


def test_both_decoders_give_the_same_heading(h264_30fps):
    path, true = h264_30fps
    est = {d: label_video(path, LabelerConfig(flow=FlowConfig(decoder=d)), window_s=3.0).yaw_inc_deg.sum()
           for d in ("pyav", "opencv")}
    for d, v in est.items():
        assert abs(v - true) <= 0.12 * abs(true), (d, v, true)
