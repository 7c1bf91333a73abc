"""The labeler's two decoder paths (resim/media/video.py, read through resim.labeling.flow_sampling.iter_grey_samples) on an
H.264 stream with B-frames."""
import shutil
import subprocess
import sys

import numpy as np
import pytest

from resim.labeling.config import FlowConfig, LabelerConfig
from resim.labeling.flow_sampling import iter_grey_samples, prepare_frame
from resim.labeling.windows import label_video
from resim.media.video import _iter_pyav, _pyav_samples, iter_samples
from resim.media.video_probe import VideoError, probe

pytest.importorskip("av")


def _grey128(frame, pixel_aspect):
    """What ``iter_grey_samples(..., 128)`` makes of each of the reader's frames."""
    return prepare_frame(frame, 128, pixel_aspect, bgr=True)


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
    assert st10["nonref_skipped_until_s"] is None and st10["frames_redecoded"] == 0   # nothing decoded twice
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
    ts = [t for t, _ in _iter_pyav(info, 10.0, _grey128, probe_s=10.0, stats=st)]
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


def _cut(src, dst, frac: float):
    data = src.read_bytes()
    dst.write_bytes(data[: int(len(data) * frac)])
    return dst


@pytest.mark.parametrize("kind", ["mp4_cut", "mkv_cut", "mp4_damaged"])
def test_truncated_or_damaged_file_is_labelled_up_to_the_damage_by_both_readers(tmp_path, left_turn_25fps, kind):
    """A download cut short (MP4 with its index in front: the index promises 5 s; Matroska: nothing promises
    anything but the DURATION tag) or a file damaged in the middle. The PyAV reader used to abort with "decoding
    failed" where OpenCV's labelled the readable part, and both labelled a cut Matroska file as if it were whole.
    Now both label the part that decodes and say, in ``decode["incomplete"]``, how much of how much and why."""
    if shutil.which("ffmpeg") is None:
        pytest.skip("ffmpeg is needed to write the test videos")
    frames, _ = left_turn_25fps   # 126 frames at 25 fps: 5.04 s
    if kind == "mkv_cut":
        path = _cut(_x264(tmp_path / "whole.mkv", frames, "25"), tmp_path / "cut.mkv", 0.5)
    else:
        whole = _x264(tmp_path / "whole.mp4", frames, "25", "-movflags", "+faststart")
        if kind == "mp4_cut":
            path = _cut(whole, tmp_path / "cut.mp4", 0.5)
        else:   # 3 kB of zeros in the middle of the frame data: the rest of the file is intact
            data = bytearray(whole.read_bytes())
            mid = len(data) // 2
            data[mid: mid + 3000] = bytes(3000)
            path = tmp_path / "damaged.mp4"
            path.write_bytes(bytes(data))
    res = {d: label_video(path, LabelerConfig(flow=FlowConfig(decoder=d)), window_s=1.0, stride_s=1.0)
           for d in ("pyav", "opencv")}
    for d, r in res.items():
        msg = r.decode["incomplete"]
        assert msg and "of the 5.04 s the container states" in msg, (d, r.decode)
        assert 1.0 < r.decode["decoded_s"] < 4.0 and r.times_s[-1] < r.decode["decoded_s"], (d, r.decode)
        assert np.all(np.diff(r.times_s) > 0) and r.windows[-1].end_s <= r.times_s[-1] + 1e-6
        assert all(w.command == "Turning left" or abs(w.yaw_deg) > 4.0 for w in r.windows)   # 8 deg/s: real frames
    if kind != "mkv_cut":   # FFmpeg reports the broken packet; the Matroska demuxer just stops
        assert "Invalid data" in res["pyav"].decode["incomplete"]
    # the two readers stop at the same place, give or take the frames the decoder holds back for reordering
    # (x264 -bf 3): PyAV drains them after the broken packet, OpenCV does not
    assert abs(res["pyav"].times_s[-1] - res["opencv"].times_s[-1]) <= 0.3
    assert abs(len(res["pyav"].times_s) - len(res["opencv"].times_s)) <= 3


def test_a_complete_file_is_not_reported_incomplete_even_where_audio_outlasts_the_video(tmp_path, left_turn_25fps):
    """Matroska's (and TS's) format duration runs to the end of the longest stream: the check compares with the
    video stream's own duration, so 5 s of video with 8 s of sound is complete."""
    if shutil.which("ffmpeg") is None:
        pytest.skip("ffmpeg is needed to write the test videos")
    frames, _ = left_turn_25fps
    video = _x264(tmp_path / "v.mkv", frames, "25")
    path = tmp_path / "with_audio.mkv"
    p = subprocess.run(["ffmpeg", "-v", "error", "-y", "-i", str(video), "-f", "lavfi", "-i", "sine=d=8", "-c:v", "copy",
                        "-c:a", "aac", str(path)], capture_output=True)
    if p.returncode != 0:
        pytest.skip(f"ffmpeg cannot add an audio track: {p.stderr.decode()[-200:]}")
    assert probe(path).duration_s > 7.5   # what OpenCV's frame count says: the audio's length
    for d in ("pyav", "opencv"):
        r = label_video(path, LabelerConfig(flow=FlowConfig(decoder=d)))
        assert r.decode["incomplete"] is None, (d, r.decode)
        assert abs(r.decode["decoded_s"] - 5.04) <= 0.1 and abs(r.decode["video_duration_s"] - 5.04) <= 0.05


@pytest.fixture(scope="module")
def refs_thin_out_after_3s(tmp_path_factory, left_turn_25fps):
    """x264 at 25 fps, B-frames not used as references (b-pyramid none): P B P B ... for 3 s (reference frames
    0.08 s apart: the reader's 2-s check passes), then P B B B P (0.16 s apart). Frame types are forced; x264's
    adaptive B-frames do the same on their own when the picture changes character (a car that stops)."""
    import fractions

    import av

    if "libx264" not in av.codecs_available:
        pytest.skip("PyAV's FFmpeg has no libx264")
    frames, _ = left_turn_25fps
    out = {}
    for ext in ("mp4", "ts"):   # MP4 seeks to a key frame by its index; TS cannot (the reader then starts over)
        path = tmp_path_factory.mktemp("refs") / f"thin.{ext}"
        with av.open(str(path), "w") as c:
            s = c.add_stream("libx264", rate=25)
            s.width, s.height, s.pix_fmt = frames.shape[2], frames.shape[1], "yuv420p"
            s.options = {"x264-params": "bframes=3:b-pyramid=none:b-adapt=0:keyint=50:scenecut=0", "crf": "18",
                         "preset": "veryfast"}
            for i, fr in enumerate(frames):
                f = av.VideoFrame.from_ndarray(fr, format="rgb24")
                f.pts, f.time_base = i, fractions.Fraction(1, 25)
                f.pict_type = 1 if i == 0 else 2 if (i % 2 == 0 if i < 75 else i % 4 == 0) else 3   # I / P / B
                for p in s.encode(f):
                    c.mux(p)
            for p in s.encode():
                c.mux(p)
        out[ext] = path
    return out


@pytest.mark.parametrize("ext", ["mp4", "ts"])
def test_pyav_keeps_every_tick_when_reference_frames_thin_out_after_the_check(refs_thin_out_after_3s, ext):
    """The check that skipping non-reference frames still leaves a frame every 0.1 s looked at the first 2 s
    only: here reference frames come 0.16 s apart from 3 s on, and the old reader gave 45 samples for 51 ticks
    (two ticks sharing one frame, ~6 Hz). Now a gap found later seeks back to the key frame before it and decodes
    every frame from there: one sample per tick, as OpenCV's reader gives."""
    path = refs_thin_out_after_3s[ext]
    info = probe(path)
    st, stcv = {}, {}
    got = list(iter_grey_samples(path, 10.0, 128, info, decoder="pyav", stats=st))
    t = np.array([x[0] for x in got])
    t_cv = np.array([t for t, _ in iter_grey_samples(path, 10.0, 128, info, decoder="opencv", stats=stcv)])
    assert len(t) == len(t_cv) == 51, (len(t), len(t_cv))
    d = t - t_cv   # a reference frame at or after each tick: never earlier than OpenCV's pick, at most 2 frames later
    assert np.all(d >= -1e-6) and np.all(d <= 2 / 25 + 1e-6), np.round(d, 3)
    assert st["nonref_skipped"] and st["nonref_skipped_until_s"] == pytest.approx(3.04) and st["nonref_gap_s"] > 0.15
    # from the gap on, exactly what a decode of every frame gives (same frames, bit for bit)
    full = [x for x in _pyav_samples(info, 10.0, _grey128, False, 0.0, {}) if x[0] > 3.04 + 1e-6]
    after = [x for x in got if x[0] > 3.04 + 1e-6]
    assert [x[0] for x in after] == [x[0] for x in full]
    assert all(np.array_equal(a[1], b[1]) for a, b in zip(after, full))
    assert st["incomplete"] is None and st["frames_decoded"] < stcv["frames_decoded"]   # still skipped up to 3 s


@pytest.mark.parametrize("decoder", ["pyav", "opencv"])
def test_the_media_reader_yields_stored_frames_and_the_labeler_shrinks_them(refs_thin_out_after_3s, decoder):
    """resim/media/video.py knows nothing of the labeler: without ``prepare`` it yields each sample as decoded (the luma
    plane at the stored size); the labeler's grey samples are exactly those, shrunk by ``prepare_frame``."""
    path = refs_thin_out_after_3s["mp4"]
    info = probe(path)
    st_plain, st_grey = {}, {}
    plain = list(iter_samples(path, 10.0, info=info, decoder=decoder, stats=st_plain))
    grey = list(iter_grey_samples(path, 10.0, 128, info, decoder=decoder, stats=st_grey))
    assert len(plain) == len(grey) == 51 and [t for t, _ in plain] == [t for t, _ in grey]
    assert all(f.dtype == np.uint8 and f.shape == (info.height_px, info.width_px) for _, f in plain)
    assert all(g.shape == (72, 128) and np.array_equal(prepare_frame(f, 128, info.pixel_aspect), g)
               for (_, f), (_, g) in zip(plain, grey))
    assert st_plain == st_grey


def test_the_labeler_and_the_cli_report_the_switch(refs_thin_out_after_3s, capsys):
    from resim.cli import main

    path = refs_thin_out_after_3s["mp4"]
    r = {d: label_video(path, LabelerConfig(flow=FlowConfig(decoder=d))) for d in ("pyav", "opencv")}
    assert len(r["pyav"].times_s) == len(r["opencv"].times_s)
    assert abs(r["pyav"].yaw_inc_deg.sum() - r["opencv"].yaw_inc_deg.sum()) < 1.0
    assert main(["label", str(path), "--json"]) == 0
    assert "non-reference frames not decoded until 3.04 s" in capsys.readouterr().err


def _ffmpeg(*args):
    p = subprocess.run(["ffmpeg", "-v", "error", "-y", *map(str, args)], capture_output=True)
    if p.returncode != 0:
        pytest.skip(f"ffmpeg cannot write the test file: {p.stderr.decode()[-200:]}")


@pytest.fixture
def cover_png(tmp_path):
    import cv2

    img = np.full((64, 64, 3), 40, np.uint8)
    img[16:48, 16:48] = (0, 0, 255)
    cv2.imwrite(str(tmp_path / "cover.png"), img)
    return tmp_path / "cover.png"


@pytest.mark.parametrize("kind", ["mp4_attached_pic_first", "mkv_png_track_first"])
def test_a_cover_picture_stored_before_the_video_is_not_what_gets_labelled(tmp_path, left_turn_25fps, cover_png,
                                                                          udta_before_tracks,
                                                                          kind, monkeypatch):
    """A cover picture as the first video stream: an MP4 whose ``covr`` comes before the tracks (flagged attached
    picture), or Matroska as FFmpeg 5.1 writes a cover (an ordinary one-frame PNG track, unflagged). Both readers
    decoded the 64x64 cover as a one-frame video ("too short: 1 frame(s)" for a 5-s clip) and ``probe`` described
    the cover (64x64, 90000 fps). Now PyAV labels the video stream, exactly as the bare video, and OpenCV's reader,
    which cannot pick a stream, refuses with the reason instead of labelling the cover."""
    if shutil.which("ffmpeg") is None:
        pytest.skip("ffmpeg is needed to write the test videos")
    frames, true = left_turn_25fps
    video = _x264(tmp_path / "v.mp4", frames, "25")
    if kind == "mp4_attached_pic_first":
        _ffmpeg("-i", video, "-i", cover_png, "-map", "0", "-map", "1", "-c", "copy", "-disposition:v:1",
                "attached_pic", tmp_path / "tagged.mp4")
        path = udta_before_tracks(tmp_path / "tagged.mp4", tmp_path / "cover_first.mp4")
    else:
        path = tmp_path / "cover_first.mkv"
        _ffmpeg("-i", cover_png, "-i", video, "-map", "0", "-map", "1", "-c", "copy", path)
    import av

    with av.open(str(path)) as c:   # the layout the test is about: the cover is stream 0
        assert [s.codec_context.name for s in c.streams.video] == ["png", "h264"]
    info = probe(path)
    assert (info.width_px, info.height_px, info.fps_hz) == (256, 144, 25.0), info     # the video's, not the cover's
    assert info.stream_index == 1
    assert abs(info.video_duration_s - 5.04) <= 0.1 and abs(info.num_frames - 126) <= 2, info
    r = label_video(path, LabelerConfig(flow=FlowConfig(decoder="pyav")))
    assert [(w.start_s, w.end_s, w.command) for w in r.windows] == [(0.0, 4.0, "Turning left")], r.windows
    assert abs(r.yaw_inc_deg.sum() - true) <= 0.12 * true and r.decode["incomplete"] is None
    if kind == "mp4_attached_pic_first":   # the same stream, the same times: the same labels as the bare video
        bare = label_video(video, LabelerConfig(flow=FlowConfig(decoder="pyav")))
        assert np.array_equal(r.yaw_inc_deg, bare.yaw_inc_deg) and np.array_equal(r.times_s, bare.times_s)
    # OpenCV decodes the first video stream and cannot be told otherwise: a clear refusal, not the cover's labels
    with pytest.raises(VideoError) as e:
        label_video(path, LabelerConfig(flow=FlowConfig(decoder="opencv")))
    assert e.value.path == str(path) and "first video stream (stream 0, png 64x64" in e.value.reason
    assert "-map 0:1" in e.value.reason
    # without PyAV nothing can tell the streams apart before decoding: the one-frame decode of a file that states
    # 126 frames is refused
    monkeypatch.setitem(sys.modules, "av", None)
    info = probe(path)
    assert (info.width_px, info.stream_index) == (64, None)    # OpenCV's view: the cover
    with pytest.raises(VideoError) as e:
        label_video(path)
    assert e.value.path == str(path) and "single picture" in e.value.reason and "cover" in e.value.reason


def test_an_audio_file_with_a_cover_is_not_a_video(tmp_path, cover_png):
    """Audio with cover art has one video stream, the attached picture: it used to be labelled as a one-frame video
    ("too short"); now probe says there is no video."""
    if shutil.which("ffmpeg") is None:
        pytest.skip("ffmpeg is needed to write the test file")
    path = tmp_path / "song.m4a"
    _ffmpeg("-f", "lavfi", "-i", "sine=d=3", "-i", cover_png, "-map", "0", "-map", "1", "-c:a", "aac", "-c:v", "copy",
            "-disposition:v:0", "attached_pic", path)
    with pytest.raises(VideoError) as e:
        probe(path)
    assert e.value.path == str(path) and "no video stream, only a still picture" in e.value.reason
