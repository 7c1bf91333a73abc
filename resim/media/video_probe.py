"""What a video file holds, for the video readers (resim/media/video.py): ``probe(path)`` -> ``VideoInfo``.

Used by the labeler (resim/labeling/windows.py), the pipeline's checks (resim/pipeline/video_preflight.py) and its OpenDV
reader (``first_stream_not_video``, resim/pipeline/sources/opendv.py).

The video stream is the first one that is not a still picture (``_pick_video_stream``): a cover picture stored as
the first video stream (an attached picture, or FFmpeg 5.1's Matroska PNG track) is skipped by the PyAV reader, and
``probe`` describes the video, not the cover. OpenCV always decodes the first video stream; where that is not the
video, its reader refuses the file with the reason (``VideoInfo.opencv_problem``; without PyAV: a one-frame decode of
a file that states more frames) rather than label the picture.

Unreadable input raises ``VideoError`` naming the file and the reason.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2

from resim.media.files import NotARegularFile, open_regular


class VideoError(Exception):
    """A video that cannot be read or labelled: ``path`` and ``reason``."""

    def __init__(self, path: str | Path, reason: str):
        self.path, self.reason = str(path), reason
        super().__init__(f"{path}: {reason}")


@dataclass(frozen=True)
class VideoInfo:
    path: str
    fps_hz: float
    num_frames: int          # as the container reports it (may be approximate; 0 = unknown)
    width_px: int
    height_px: int
    pixel_aspect: float      # sample aspect ratio (1.0 = square pixels)
    # the video stream's own duration as the container states it (None = unknown): what a complete decode must
    # reach (``iter_samples`` reports a decode that stops short of it, e.g. a truncated download)
    video_duration_s: float | None = None
    # the container's index of the video stream labelled (``_pick_video_stream``; None where PyAV is not installed:
    # OpenCV decodes the first video stream)
    stream_index: int | None = None
    # why OpenCV's reader cannot label this file, None where it can: it decodes the first video stream and cannot be
    # told otherwise, and here that is another stream (a cover picture stored first); the PyAV reader is unaffected
    opencv_problem: str | None = None

    @property
    def duration_s(self) -> float:
        return self.num_frames / self.fps_hz


# AV_DISPOSITION_ATTACHED_PIC (PyAV: ``av.stream.Disposition.attached_pic``): a still picture (cover art) carried
# as a video stream of one frame, e.g. MP4's ``covr`` or a Matroska attachment; AV_DISPOSITION_STILL_IMAGE
_ATTACHED_PIC, _STILL_IMAGE = 0x400, 0x100000


def _is_attached_pic(s) -> bool:
    return bool(int(getattr(s, "disposition", 0) or 0) & _ATTACHED_PIC)


def _is_still(s) -> bool:
    """A video stream that holds a picture rather than a video: flagged still image, or the container states a single
    frame or less than half a second (FFmpeg 5.1's Matroska muxer writes a cover picture as an ordinary PNG track of
    one frame, without the attached-picture flag; its ``DURATION`` tag says 0.12 s)."""
    if int(getattr(s, "disposition", 0) or 0) & _STILL_IMAGE or s.frames == 1:
        return True
    dur = _stream_duration_s(s)
    return dur is not None and dur < 0.5


def _pick_video_stream(c):
    """The video stream of PyAV container ``c`` to label, or None where it has none but attached pictures.

    Never an attached picture (cover art: an MP4 whose ``covr`` box comes before its tracks, or an audio file with a
    cover, has it as its first video stream, which both readers used to decode as a one-frame video), and, of the
    others, the first that is not a still picture (``_is_still``), else the first. A file with one video stream
    (every ordinary one) has no choice to make; several videos (two cameras) keep the first, as before.
    """
    vids = [s for s in c.streams.video if not _is_attached_pic(s)]
    return next((s for s in vids if not _is_still(s)), vids[0] if vids else None)


def _stream_duration_s(s) -> float | None:
    """Stream ``s``'s duration as the container states it: the stream's duration (MP4, AVI, TS), else Matroska/WebM's
    ``DURATION`` tag (what FFmpeg's muxer writes); None where it states none. Not the format's duration, which runs
    to the end of the longest stream (an audio track that outlasts the video)."""
    if s.duration and s.time_base:
        return float(s.duration * s.time_base)
    tag = s.metadata.get("DURATION") or s.metadata.get("duration")
    try:
        h, m, sec = tag.split(":")
        return int(h) * 3600 + int(m) * 60 + float(sec)
    except (AttributeError, ValueError):      # no tag, or not H:MM:SS.fff
        return None


@dataclass(frozen=True)
class _AvVideo:
    """What PyAV says about the video stream to label (``_pyav_video``)."""

    index: int | None               # None: no video stream but attached pictures (an audio file with a cover)
    duration_s: float | None
    first_video: str                # the first video stream, which OpenCV decodes: "" where it is this one, else
    #                                 what it is ("stream 0, png 64x64, an attached picture")
    fps_hz: float = 0.0             # rate, frames, geometry of the stream to label (used where OpenCV reads another)
    num_frames: int = 0
    width_px: int = 0
    height_px: int = 0
    pixel_aspect: float = 1.0


def _pyav_video(path: str) -> _AvVideo | None:
    """PyAV's view of ``path``'s video stream (``_pick_video_stream``); None without PyAV, where PyAV cannot open
    the file, or where it has no video stream at all."""
    try:
        import av
    except ImportError:
        return None
    try:
        with av.open(path) as c:
            if not c.streams.video:
                return None
            s, first = _pick_video_stream(c), c.streams.video[0]
            desc = ""
            if s is None or first.index != s.index:
                cc = first.codec_context
                what = ("an attached picture (cover art)" if _is_attached_pic(first)
                        else "a still picture" if _is_still(first) else "another video")
                desc = f"stream {first.index}, {cc.name} {cc.width}x{cc.height}: {what}"
            if s is None:
                return _AvVideo(None, None, desc)
            dur = _stream_duration_s(s)
            rate = s.guessed_rate or s.average_rate or s.base_rate      # guessed: what OpenCV reports
            fps = float(rate) if rate else 0.0
            n = int(s.frames or 0) or (int(round(dur * fps)) if dur and fps > 0 else 0)
            sar = s.sample_aspect_ratio or s.codec_context.sample_aspect_ratio
            return _AvVideo(s.index, dur, desc, fps, n, s.codec_context.width, s.codec_context.height,
                            float(sar) if sar and sar > 0 else 1.0)
    except av.error.FFmpegError:
        return None


def first_stream_not_video(path: str | Path) -> tuple[int | None, str] | None:
    """Where the first video stream of ``path`` (the one OpenCV decodes) is not the video to label: ``(index of the
    video stream or None where there is none, what the first stream is)``; None where it is the video, or PyAV is
    missing or cannot open the file. One PyAV open and no decode (for readers that open the file with OpenCV
    anyway, e.g. the OpenDV source; ``probe`` does this and more)."""
    v = _pyav_video(str(path))
    return None if v is None or not v.first_video else (v.index, v.first_video)


def _have_pyav() -> bool:
    try:
        import av  # noqa: F401
    except ImportError:
        return False
    return True


def _open(path: str, convert_rgb: bool = True) -> cv2.VideoCapture:
    cap = cv2.VideoCapture(path, cv2.CAP_FFMPEG, [cv2.CAP_PROP_N_THREADS, 1])
    if cap.isOpened() and not convert_rgb:
        cap.set(cv2.CAP_PROP_CONVERT_RGB, 0)
    return cap


def probe(path: str | Path) -> VideoInfo:
    """Open ``path`` and read its geometry; raises VideoError naming the file and the reason."""
    p = Path(path)
    try:   # a FIFO named f.mp4 would block OpenCV's open forever; a directory, a device: refused by name
        with open_regular(p) as fh:
            fh.read(1)
    except NotARegularFile as e:
        raise VideoError(p, e.reason) from None
    except OSError as e:
        raise VideoError(p, f"cannot be read ({e.strerror})") from None
    prev = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)   # we report the failure ourselves
    cap = _open(str(p))
    cv2.utils.logging.setLogLevel(prev)
    try:
        if not cap.isOpened():
            raise VideoError(p, "OpenCV/FFmpeg cannot open it (not a video, or an unsupported container/codec)")
        fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        n = cap.get(cv2.CAP_PROP_FRAME_COUNT)
        # raw streams (.h264) report garbage (-1.9e17 seen): 0 = unknown
        n = int(n) if math.isfinite(n) and n > 0 else 0
        num, den = cap.get(cv2.CAP_PROP_SAR_NUM), cap.get(cv2.CAP_PROP_SAR_DEN)
        sar = (num / den) if (num and den and num > 0 and den > 0) else 1.0
        av_video = _pyav_video(str(p))
        if av_video is not None and av_video.index is None:
            raise VideoError(p, f"no video stream, only a still picture ({av_video.first_video})")
        other = av_video is not None and bool(av_video.first_video)
        if other:
            # OpenCV decodes another stream (a cover picture stored first): the video's rate, size and frames are
            # the stream PyAV picks, and OpenCV's reader refuses the file (``opencv_problem``)
            fps, n, w, h, sar = (av_video.fps_hz, av_video.num_frames, av_video.width_px, av_video.height_px,
                                 av_video.pixel_aspect)
        if not math.isfinite(fps) or fps <= 0 or w <= 0 or h <= 0:
            raise VideoError(p, f"no usable video stream (fps={fps}, size={w}x{h})")
        if not other and not cap.grab():
            raise VideoError(p, "no decodable video frame")
    finally:
        cap.release()
    if av_video is None:
        # without PyAV (or where it cannot open the file): OpenCV's frame count / fps, which for Matroska and TS is
        # the format's duration; None where PyAV failed on a file OpenCV opened
        dur = n / fps if n > 0 and not _have_pyav() else None
        return VideoInfo(str(p), fps, n, w, h, float(sar), dur)
    problem = None
    if other:
        problem = (f"OpenCV's reader decodes the first video stream ({av_video.first_video}), not the video (stream "
                   f"{av_video.index}), and cannot be told otherwise: label it with decoder 'auto' or 'pyav', or keep "
                   f"only the video: ffmpeg -i IN -map 0:{av_video.index} -c copy OUT")
    return VideoInfo(str(p), fps, n, w, h, float(sar), av_video.duration_s, av_video.index, problem)
