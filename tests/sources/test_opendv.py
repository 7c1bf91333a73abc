import numpy as np
import pytest

from resim.config import ConfigError
from resim.pipeline.sources.episode import SourceError, scan_items
from resim.pipeline.sources.opendv import OpenDVConfig, OpenDVReader


def reader(root, **kw):
    return OpenDVReader(OpenDVConfig.preset("synthetic", root=str(root), **kw))


def test_lists_videos_recursively(opendv_root):
    items = reader(opendv_root).list_items()
    assert items == ["chanA/good.mp4", "chanA/with_csv.mp4", "chanB/empty.mkv", "chanB/small.mp4",
                     "chanB/truncated.mp4"]


def test_resamples_30fps_to_10hz_nearest_frame(opendv_root):
    ep = reader(opendv_root).open("chanA/good.mp4")
    assert (ep.fps_hz, ep.num_frames, ep.frame_size_hw) == (10.0, 10, (48, 80))
    frames = list(ep.frames())
    assert len(frames) == 10 and frames[0].dtype == np.uint8 and frames[0].shape == (48, 80, 3)
    # fixture frame i has brightness 7*i: output k must be source frame 3k
    got = [int(round(f.mean() / 7)) for f in frames]
    assert got == [3 * k for k in range(10)]
    sub = list(ep.frames(4, 7, size_hw=(24, 40)))
    assert [f.shape for f in sub] == [(24, 40, 3)] * 3 and int(round(sub[0].mean() / 7)) == 12


def test_csv_discards_override_config(opendv_root):
    ep = reader(opendv_root).open("chanA/with_csv.mp4")   # 2 s at 20 fps, 0.5 s cut at each end
    assert ep.num_frames == 10
    first = next(ep.frames())
    assert int(round(first.mean() / 7)) == 10             # t = 0.5 s -> source frame 10


def test_defaults_are_opendv_youtube():
    cfg = OpenDVConfig()
    assert (cfg.fps_hz, cfg.start_discard_s, cfg.end_discard_s, cfg.min_height_px) == (10.0, 90.0, 60.0, 720)
    with pytest.raises(ConfigError):
        OpenDVConfig(fps_hz=0)


def test_broken_items_reported_with_reason(opendv_root):
    good, problems = scan_items(reader(opendv_root, min_height_px=32))
    assert good == ["chanA/good.mp4", "chanA/with_csv.mp4"]
    reasons = {e.item: e.reason for e in problems}
    assert set(reasons) == {"chanB/empty.mkv", "chanB/small.mp4", "chanB/truncated.mp4"}
    assert "min_height_px" in reasons["chanB/small.mp4"]
    assert "cannot open" in reasons["chanB/truncated.mp4"] or "truncated" in reasons["chanB/truncated.mp4"]


def test_default_discards_make_short_videos_too_short(opendv_root):
    r = OpenDVReader(OpenDVConfig(root=opendv_root, min_height_px=16))
    with pytest.raises(SourceError, match="too short"):
        r.open("chanA/good.mp4")


def test_real_dashcam_clip(shared_dashcam):
    r = OpenDVReader(OpenDVConfig(root=shared_dashcam))
    with pytest.raises(SourceError, match="540 px < min_height_px 720"):
        r.open("solidWhiteRight.mp4")
    r = OpenDVReader(OpenDVConfig(root=shared_dashcam, start_discard_s=0, end_discard_s=0, min_height_px=480))
    ep = r.open("solidWhiteRight.mp4")                 # 221 frames at 25 fps = 8.84 s
    assert ep.num_frames == 88 and ep.frame_size_hw == (540, 960)
    fr = list(ep.frames(0, 3, size_hw=(90, 160)))
    assert len(fr) == 3 and fr[0].shape == (90, 160, 3) and fr[0].std() > 10


# ---- a cover picture stored before the video ------------------------------------------------------------------
def _ffmpeg(*args):
    import subprocess

    p = subprocess.run(["ffmpeg", "-v", "error", "-y", *map(str, args)], capture_output=True)
    if p.returncode != 0:
        pytest.skip(f"ffmpeg cannot write the test file: {p.stderr.decode()[-200:]}")


@pytest.mark.parametrize("kind", ["mp4_attached_pic_first", "mkv_png_track_first"])
def test_a_cover_picture_stored_before_the_video_is_quarantined_with_the_reason(tmp_path, kind, udta_before_tracks):
    """OpenCV decodes the first video stream; where that is a cover picture stored before the video, the reader
    used to cut clips of (or fail on) the picture. Now the file is quarantined, naming it and why."""
    import shutil

    import cv2

    if shutil.which("ffmpeg") is None:
        pytest.skip("ffmpeg is needed to write the test videos")
    pytest.importorskip("av")
    root = tmp_path / "opendv"
    root.mkdir()
    _ffmpeg("-f", "lavfi", "-i", "testsrc=size=128x72:rate=25", "-t", "4", "-c:v", "libx264", "-pix_fmt", "yuv420p",
            tmp_path / "v.mp4")
    img = np.full((64, 64, 3), 40, np.uint8)
    img[16:48, 16:48] = (0, 0, 255)
    cv2.imwrite(str(tmp_path / "cover.png"), img)
    if kind == "mp4_attached_pic_first":
        _ffmpeg("-i", tmp_path / "v.mp4", "-i", tmp_path / "cover.png", "-map", "0", "-map", "1", "-c", "copy",
                "-disposition:v:1", "attached_pic", tmp_path / "tagged.mp4")
        item = "cover_first.mp4"
        udta_before_tracks(tmp_path / "tagged.mp4", root / item)
    else:
        item = "cover_first.mkv"
        _ffmpeg("-i", tmp_path / "cover.png", "-i", tmp_path / "v.mp4", "-map", "0", "-map", "1", "-c", "copy",
                root / item)
    import av

    with av.open(str(root / item)) as c:   # the layout the test is about: the cover is stream 0
        assert [s.codec_context.name for s in c.streams.video] == ["png", "h264"]
    (root / "plain.mp4").write_bytes((tmp_path / "v.mp4").read_bytes())
    r = reader(root)
    good, problems = scan_items(r)
    assert good == ["plain.mp4"]                              # the ordinary video is untouched
    ep = r.open("plain.mp4")
    assert ep.frame_size_hw == (72, 128) and ep.num_frames == 40
    [e] = problems
    assert e.item == item
    assert str(root / item) in e.reason and "cover picture" in e.reason and "OpenCV" in e.reason
    assert "-map 0:1" in e.reason
    # without the last-frame check the old reader opened the file and cut clips of the cover picture
    with pytest.raises(SourceError, match="cover picture"):
        reader(root, verify_last_frame=False).open(item)



def test_a_fifo_a_device_link_and_a_dangling_link_are_quarantined_by_name_not_skipped_or_hung(tmp_path,
                                                                                              opendv_root):
    import os
    import shutil

    root = tmp_path / "opendv"
    shutil.copytree(opendv_root, root, symlinks=True)
    os.mkfifo(root / "chanA" / "pipe.mp4")
    (root / "chanA" / "zero.mp4").symlink_to("/dev/zero")
    (root / "chanA" / "gone.mp4").symlink_to(root / "nowhere.mp4")
    good, problems = scan_items(reader(root, min_height_px=32))
    assert good == ["chanA/good.mp4", "chanA/with_csv.mp4"]
    reasons = {e.item: e.reason for e in problems}
    assert "named pipe" in reasons["chanA/pipe.mp4"]
    assert "character device" in reasons["chanA/zero.mp4"]
    assert "dangling symbolic link" in reasons["chanA/gone.mp4"]
