import numpy as np
import pytest
import torch

from resim.models.reward.model import Video2Reward
from resim.sample.reward_score import ScoreError, read_video_file, score_videos, window_starts


def test_window_starts():
    assert window_starts(7, 7, 7) == [0]
    assert window_starts(20, 7, 7) == [0, 7, 13]
    assert window_starts(20, 7, 3) == [0, 3, 6, 9, 12, 13]


def test_score_videos_averages_sliding_windows(tiny_cfg):
    m = Video2Reward(tiny_cfg)  # window: 4 frames every 2 -> 7 frames
    g = torch.Generator().manual_seed(0)
    v = torch.rand(20, 3, 24, 32, generator=g)
    got = score_videos(m, [v])
    with torch.no_grad():
        manual = np.mean([float(m(video=v[s:s + 7:2][None])) for s in (0, 7, 13)])
    assert got.shape == (1,) and got.dtype == np.float32
    assert got[0] == pytest.approx(manual, abs=1e-5)
    # a batch tensor, and a list with other lengths / uint8 layout, agree
    batch = torch.rand(3, 7, 3, 24, 32, generator=g)
    b = score_videos(m, batch)
    u8 = (batch[1].permute(0, 2, 3, 1) * 255).round().to(torch.uint8).numpy()
    lst = score_videos(m, [batch[0], u8, v])
    assert lst[0] == pytest.approx(b[0], abs=1e-5) and lst[2] == pytest.approx(got[0], abs=1e-5)
    assert lst[1] == pytest.approx(b[1], abs=2e-2)


def test_score_videos_bad_input(tiny_cfg):
    m = Video2Reward(tiny_cfg)
    with pytest.raises(ScoreError, match=r"video\[1\]: 6 frames is shorter than the model's window of 7"):
        score_videos(m, [torch.rand(7, 3, 16, 16), torch.rand(6, 3, 16, 16)])
    bad = torch.rand(8, 3, 16, 16)
    bad[5, 0, 3, 3] = float("nan")
    with pytest.raises(ScoreError, match="frame 5 is unreadable"):
        score_videos(m, [bad], names=["clipA"])
    with pytest.raises(ScoreError, match=r"values must be in \[0, 1\]"):
        score_videos(m, [torch.rand(8, 3, 16, 16) * 255])
    with pytest.raises(ScoreError, match="no videos"):
        score_videos(m, [])


def test_read_video_file_errors(tmp_path):
    import cv2

    p = tmp_path / "ok.avi"
    w = cv2.VideoWriter(str(p), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (32, 24))
    for i in range(10):
        w.write(np.full((24, 32, 3), i * 20, np.uint8))
    w.release()
    frames = read_video_file(p)
    assert frames.shape == (10, 24, 32, 3) and frames.dtype == np.uint8
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(b"not a video at all" * 10)
    with pytest.raises(ScoreError, match="junk.mp4"):
        read_video_file(junk)
    # truncated file: decoding stops before the header's frame count -> unreadable frame named
    data = p.read_bytes()
    cut = tmp_path / "cut.avi"
    cut.write_bytes(data[: len(data) * 2 // 3])
    with pytest.raises(ScoreError, match=r"cut.avi: (frame \d+ of 10 is unreadable|no decodable frame|OpenCV cannot)"):
        read_video_file(cut)
