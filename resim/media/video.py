"""Read a video file at a sampling rate: decode only what is needed, hand each sample on as soon as it is decoded.

``iter_samples`` yields ``(t_s, frame)``: the frame as stored (the 8-bit luma plane, or BGR where OpenCV's reader
cannot give the plane; not square pixels), passed first through the caller's ``prepare(frame, pixel_aspect)``. The
labeler (resim/labeling/flow_sampling.py, ``iter_grey_samples``) shrinks it there to its working width, so that the samples
the PyAV reader holds back (below) are small ones.

Two decoder paths (``decoder="auto"`` takes PyAV when it is installed):

* **PyAV** (FFmpeg's own API): the 8-bit luma plane is read straight from the decoded
  frame (no colour conversion), and, where the stream has non-reference
  frames (B-frames) and skipping them still leaves at least ``sample_hz`` frames per
  second (checked on the first 2 s of the same decode, and kept true to the end: a later gap between reference
  frames makes it seek back and decode every frame from there on), they are not decoded at all (``skip_frame=NONREF``:
  ~40 % less decode time on x264's default stream; the frames that are decoded are
  bit-identical). Skipping the deblocking filter too (``skip_loop_filter=all``) saved
  another ~15 % but moved the yaw of the straight real clip by 3 deg over 9 s (block
  edges fixed in the image pull flow to zero), so it is not done; on B-frames only
  (``bidir``, -10 %) it still moved 4 s windows by up to 0.9 deg on the real clips. Samples are then the first decoded
  frame at or after each tick (at most one source frame late); the labeler's window sums
  of per-pair yaw do not need evenly spaced samples.
* **OpenCV**: every frame must pass through the decoder (``grab``), but only the frames
  sampled at ``sample_hz`` are converted (``retrieve``). Where the stream is 8-bit
YUV, OpenCV is asked not to convert to BGR (``CAP_PROP_CONVERT_RGB = 0``) and the
luma plane it returns *is* the greyscale image the flow needs; this is verified on
the first frame against a normal BGR decode, and the reader falls back to BGR
otherwise. The sample aspect ratio (anamorphic video) goes to ``prepare`` (the labeler applies it when resizing).

Both read the video stream that ``probe`` (resim/media/video_probe.py) picks: never a cover picture stored first (the
OpenCV reader, which cannot pick a stream, refuses such a file).

Both readers end a truncated or damaged file where it stops decoding (the first packet FFmpeg rejects; PyAV
also at the first frame FFmpeg flags as concealed after a clean one) and report it in ``stats["incomplete"]``: the part before is
labelled, nothing after it is made up (docs/labeling.md, "Odd files").
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Callable, Iterator

import cv2
import numpy as np

from resim.media.video_probe import VideoError, VideoInfo, _open, _pick_video_stream, probe

# prepare(frame, pixel_aspect) -> what ``iter_samples`` yields for that sample
Prepare = Callable[[np.ndarray, float], np.ndarray]


def _plain(frame: np.ndarray, pixel_aspect: float) -> np.ndarray:
    return frame


def _luma_plane_ok(path: str, h: int, w: int) -> bool:
    """True when a CONVERT_RGB=0 decode returns the 8-bit luma plane (checked against BGR->grey)."""
    prev = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)  # "treated as 8UC1" warning per frame
    try:
        a, b = _open(path, convert_rgb=False), _open(path)
        ok_a, ya = a.read()
        ok_b, bgr = b.read()
        a.release()
        b.release()
    finally:
        cv2.utils.logging.setLogLevel(prev)
    if not (ok_a and ok_b) or ya is None or ya.dtype != np.uint8 or ya.ndim != 2:
        return False
    if ya.shape[0] < h or ya.shape[1] != w:
        return False
    grey = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    # BT.601 limited-range luma vs OpenCV's full-range grey: allow the range difference
    return float(np.mean(np.abs(ya[:h].astype(np.float32) * (219 / 255) + 16 - grey.astype(np.float32)))) < 12.0 \
        or float(np.mean(np.abs(ya[:h].astype(np.float32) - grey.astype(np.float32)))) < 12.0


def iter_samples(path: str | Path, sample_hz: float, prepare: Prepare | None = None,
                 info: VideoInfo | None = None, use_luma: bool = True,
                 decoder: str = "auto", stats: dict | None = None) -> Iterator[tuple[float, np.ndarray]]:
    """Yield (t_s, ``prepare(frame, info.pixel_aspect)``) for frames sampled at ``sample_hz``.

    ``frame`` is the decoded picture, upright, at its stored size (``info.pixel_aspect`` says how wide one stored
    pixel is): uint8 (H, W), the luma plane, or uint8 (H, W, 3) BGR where the OpenCV reader cannot hand over the
    plane (not 8-bit YUV, or ``use_luma=False``). ``prepare`` None yields ``frame`` itself.

    Frames are taken at the first decoded frame at or after each tick k / sample_hz (all
    frames when the video is slower than ``sample_hz``). Raises VideoError on undecodable input.
    ``decoder``: "auto" (PyAV if installed, else OpenCV), "pyav", "opencv". ``stats``, if given, is
    filled with ``decoder``, ``frames_decoded``, ``nonref_skipped`` (PyAV skipped non-reference frames; with
    ``nonref_skipped_until_s`` / ``nonref_gap_s`` where a gap between reference frames made it decode every frame
    from there on, ``frames_redecoded`` the frames decoded twice for that), ``timestamps``, ``decoded_s`` (seconds
    decoded), ``video_duration_s`` (the container's) and ``incomplete``: None, or why the decode stopped short of
    the container's duration (a truncated or damaged file: the samples before are yielded, ``_check_complete``).
    """
    stats = {} if stats is None else stats
    prepare = prepare or _plain
    info = info or probe(path)
    if decoder not in ("auto", "pyav", "opencv"):
        raise ValueError(f"decoder must be auto, pyav or opencv, got {decoder!r}")
    if decoder != "opencv":
        try:
            import av  # noqa: F401  (optional: the pipeline extra installs it)
        except ImportError:
            if decoder == "pyav":
                raise VideoError(info.path, "decoder='pyav' but PyAV is not installed (pip install av)") from None
        else:
            stats["decoder"] = "pyav"
            yield from _iter_pyav(info, sample_hz, prepare, stats=stats)
            _check_complete(info, sample_hz, stats)
            return
    if info.opencv_problem:
        raise VideoError(info.path, info.opencv_problem)
    stats.update(decoder="opencv", nonref_skipped=False, timestamps="stream")
    yield from _iter_opencv(info, sample_hz, prepare, use_luma, stats)
    _check_complete(info, sample_hz, stats)


def _check_complete(info: VideoInfo, sample_hz: float, stats: dict) -> None:
    """A decode that stopped early (truncated or damaged file) ends the video there, in both readers: the samples
    decoded so far are labelled, and ``stats["incomplete"]`` says so (None for a complete decode), with
    ``decoded_s`` (seconds decoded) and ``video_duration_s`` (the container's). Early = FFmpeg reported damage
    (PyAV), or the decoded part falls short of the container's video duration by more than one sampling period
    and two frames (what skipped trailing non-reference frames and rounded durations can account for)."""
    end, full = stats.get("decoded_s"), info.video_duration_s
    stats["video_duration_s"] = full
    err = stats.get("decode_error")
    short = full is not None and end is not None and end < full - (1.0 / sample_hz + 2.0 / info.fps_hz)
    if not (err or short):
        stats["incomplete"] = None
        return
    of = f" of the {full:.2f} s the container states" if full is not None else ""
    why = err or "the decoder found no more frames: the file is truncated or damaged"
    stats["incomplete"] = f"decoded {end:.2f} s{of} ({why})"


def _av_open(path: str, skip_nonref: bool, index: int | None = None):
    """Open ``path`` and its video stream ``index`` (None: the one ``_pick_video_stream`` picks), one thread."""
    import av

    c = av.open(path)
    s = c.streams[index] if index is not None else _pick_video_stream(c)
    if s is None:
        c.close()
        raise VideoError(path, "no video stream, only a still picture (cover art)")
    s.thread_type = "NONE"                      # one thread: the pipeline runs one labeler per core
    s.codec_context.thread_count = 1
    if skip_nonref:
        s.codec_context.skip_frame = "NONREF"
    return c, s


def _luma(frame, rot90: int = 0) -> np.ndarray:
    """8-bit luma plane of a PyAV frame (no copy of the chroma, no colour conversion), turned upright by
    ``rot90`` quarter turns (the stream's display matrix, as OpenCV applies it: a phone clip stored
    sideways would otherwise read its turns as vertical flow)."""
    if frame.format.name in ("yuv420p", "yuvj420p", "yuv422p", "yuvj422p", "yuv444p", "yuvj444p", "nv12", "nv21"):
        pl = frame.planes[0]
        y = np.frombuffer(pl, np.uint8).reshape(frame.height, pl.line_size)[:, : frame.width]
    else:
        y = frame.to_ndarray(format="gray")
    return np.ascontiguousarray(np.rot90(y, rot90)) if rot90 % 4 else y


def _rot90_of(frame) -> int:
    """Quarter turns that make ``frame`` upright: PyAV's ``rotation`` (degrees, display matrix), e.g. -90 -> -1."""
    deg = getattr(frame, "rotation", 0) or 0
    return int(round(deg / 90.0)) % 4


class _RefsTooSparse(Exception):
    """Reference frames alone leave a gap longer than one sampling period (raised while probing)."""


class _BadTimestamps(Exception):
    """Frames without a time, or times that do not increase (raised while probing)."""


def _frames(c, s, stats: dict):
    """Decoded frames of stream ``s``, in display order, up to the first packet FFmpeg cannot read or decode, or
    the first frame it flags as damaged (errors concealed) after a clean one, whichever comes first.

    A truncated or damaged file ends the video there (``docs/labeling.md``, "Odd files"): the frames the decoder
    still holds are drained and returned (after a rejected packet), and ``stats["decode_error"]`` says what stopped
    it and where. OpenCV's reader also stops at the first packet it cannot decode; carrying on past the damage
    would give frames made up by FFmpeg's error concealment until the next key frame.
    """
    import av

    cc = s.codec_context
    at, good = None, False
    try:
        for p in c.demux(s):
            if p.pts is not None and p.time_base is not None:
                at = float(p.pts * p.time_base)
            try:
                frames = cc.decode(p)
            except av.error.FFmpegError as e:
                stats["decode_error"] = _ffmpeg_reason(e, "decoding", at)
                break
            for f in frames:
                if f.is_corrupt:               # decoded, but with errors concealed: pixels FFmpeg made up
                    if not good:               # a stream (or a seek) that starts before a clean key frame: skip
                        continue
                    stats["decode_error"] = f"FFmpeg found damaged data in the frame at {f.time:.2f} s"
                    return
                good = True
                yield f
        else:
            return
    except av.error.FFmpegError as e:          # the demuxer: a container cut short or damaged
        stats["decode_error"] = _ffmpeg_reason(e, "reading", at)
    try:
        drained = cc.decode(None)              # drain: frames decoded before the damage are good
    except av.error.FFmpegError:
        return
    for f in drained:
        f.time_base = s.time_base              # no packet to take it from: ``time`` would be NaN
        if f.is_corrupt:
            return
        yield f


def _ffmpeg_reason(e, what: str, at_s: float | None) -> str:
    msg = getattr(e, "strerror", None) or str(e)
    return f"FFmpeg stopped {what} the stream" + (f" at {at_s:.2f} s" if at_s is not None else "") + f": {msg}"


def _pyav_samples(info: VideoInfo, sample_hz: float, prepare: Prepare, skip_nonref: bool,
                  probe_s: float, stats: dict, count_frames: bool = False) -> Iterator[tuple[float, np.ndarray]]:
    """One decode: yield (t_s, prepare(luma, pixel_aspect)) at the first decoded frame at or after each tick.

    Within the first ``probe_s`` seconds (nothing is yielded from there before it passes, ``_iter_pyav``):
    with ``skip_nonref``, raises ``_RefsTooSparse`` if two decoded frames are further apart than
    1 / sample_hz (+ a quarter frame of slack); without ``count_frames``, raises ``_BadTimestamps`` at a
    frame without a time (raw .h264) or whose time does not increase (H.264 in AVI carries decode-order
    stamps). ``count_frames``: times are frame count / fps (every frame decoded, constant rate assumed).
    After ``probe_s``, such a gap (the encoder's choice of frame types can change within a video: x264's
    adaptive B-frames) is repaired in the same decode: it seeks back to the key frame at or before the last
    frame handled and decodes every frame from there to the end (``stats["nonref_skipped_until_s"]``), so the
    samples never miss a tick while skipping; the common case decodes nothing twice. Where the container
    cannot seek there, the file is reopened and decoded from the start, frames already handled dropped.
    """
    import av

    try:
        c, s = _av_open(info.path, skip_nonref, info.stream_index)
    except av.error.FFmpegError as e:
        raise VideoError(info.path, f"PyAV/FFmpeg cannot open it ({e})") from None
    period, half = 1.0 / sample_hz, 0.5 / info.fps_hz
    max_gap = period + 0.25 / info.fps_hz
    eps = 0.25 / info.fps_hz
    nxt, n, t0, prev, rot = 0.0, 0, None, None, None
    prev_pts = None
    resume = None          # after a seek back: frames at or before this time were handled already
    first_after_seek = reopened = False
    skipping = skip_nonref
    stats.update(decode_error=None, nonref_skipped_until_s=None, nonref_gap_s=None, frames_redecoded=0, decoded_s=0.0)
    frames = _frames(c, s, stats)

    def reopen():
        # every frame from the start of the file; ``resume`` drops the frames handled already
        nonlocal c, s
        c.close()
        c, s = _av_open(info.path, False, info.stream_index)
        stats["decode_error"] = None
        return _frames(c, s, stats)

    try:
        while frames is not None:
            it, frames = frames, None
            for fr in it:
                if count_frames:
                    t = n / info.fps_hz
                elif fr.time is None or (prev is not None and resume is None and fr.time - t0 <= prev):
                    if prev is None or prev < probe_s:
                        raise _BadTimestamps
                    raise VideoError(info.path, f"frame times stop increasing after {prev:.2f} s (frame {n}: "
                                                f"{fr.time}); remux the file (e.g. ffmpeg -i IN -c copy OUT.mp4)")
                else:
                    t = fr.time
                t0 = t if t0 is None else t0
                t -= t0                                  # times from the first decoded frame
                if resume is not None:
                    if first_after_seek and t > resume + eps and not reopened:
                        # the seek landed after the frame we need: decode from the start instead
                        it.close()
                        frames, reopened = reopen(), True
                        break
                    first_after_seek = False
                    if t <= resume + eps:                # handled before the seek
                        stats["frames_redecoded"] += 1
                        continue
                    resume = None
                n += 1
                stats["frames_decoded"] = n
                if skipping and prev is not None and t - prev > max_gap:
                    if prev < probe_s:
                        raise _RefsTooSparse
                    # reference frames alone are too sparse from here on: every frame from the key frame at or
                    # before ``prev`` to the end (nothing after ``prev`` has been handled yet)
                    n -= 1
                    it.close()
                    skipping, resume, first_after_seek = False, prev, True
                    stats.update(frames_decoded=n, nonref_skipped_until_s=round(prev, 3),
                                 nonref_gap_s=round(t - prev, 3))
                    s.codec_context.skip_frame = "DEFAULT"
                    try:
                        c.seek(prev_pts, stream=s, backward=True)
                        frames = _frames(c, s, stats)
                    except av.error.FFmpegError:
                        frames, reopened = reopen(), True
                    break
                prev, prev_pts = t, fr.pts
                stats["decoded_s"] = t + 1.0 / info.fps_hz
                if t + half < nxt:
                    continue
                rot = _rot90_of(fr) if rot is None else rot
                yield t, prepare(_luma(fr, rot), info.pixel_aspect)
                while nxt <= t + half:
                    nxt += period
            else:
                if resume is not None and not reopened:
                    # the seek found no decodable frame (it landed past the last key frame: TS seeks by bytes):
                    # decode from the start instead
                    frames, reopened = reopen(), True
    except av.error.FFmpegError as e:
        raise VideoError(info.path, f"decoding failed after {n} frames ({e})") from None
    finally:
        c.close()
    if n == 0:
        err = stats.get("decode_error")
        raise VideoError(info.path, "no decodable video frame" + (f" ({err})" if err else ""))


def _iter_pyav(info: VideoInfo, sample_hz: float, prepare: Prepare, probe_s: float = 2.0,
               stats: dict | None = None) -> Iterator[tuple[float, np.ndarray]]:
    """PyAV path: non-reference frames are skipped where reference frames alone still come at least
    every 1 / sample_hz s, and the stream's frame times are used where they increase. Both are checked on
    the first ``probe_s`` of the same decode, not by a second pass (which cost ~6 % of labeling a 30-s
    clip): the samples of that stretch are held back until it passes, and where it fails the decode
    restarts (nothing has been yielded yet) with every frame, or with frame count / fps as the time.
    A gap between reference frames later on is repaired inside ``_pyav_samples`` (seek back, every frame
    from there)."""
    stats = {} if stats is None else stats
    stats["frames_decoded"] = 0
    skip, count = info.fps_hz >= 1.5 * sample_hz, False
    while True:   # at most three decodes: skip -> every frame -> counted; each failure only narrows the next try
        stats.update(nonref_skipped=skip, timestamps="frame count / fps" if count else "stream")
        held: list[tuple[float, np.ndarray]] = []
        gen = _pyav_samples(info, sample_hz, prepare, skip, probe_s, stats, count_frames=count)
        try:
            for t, g in gen:
                if t < probe_s:
                    held.append((t, g))
                    continue
                yield from held
                yield t, g
                yield from gen
                return
        except _RefsTooSparse:
            gen.close()
            skip = False
            continue
        except _BadTimestamps:
            gen.close()
            skip, count = False, True   # counting frames needs every frame decoded
            continue
        yield from held                 # a video shorter than probe_s that passed
        return


def _iter_opencv(info: VideoInfo, sample_hz: float, prepare: Prepare,
                 use_luma: bool, stats: dict) -> Iterator[tuple[float, np.ndarray]]:
    luma = use_luma and _luma_plane_ok(info.path, info.height_px, info.width_px)
    prev_level = cv2.utils.logging.getLogLevel()
    if luma:
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    cap = _open(info.path, convert_rgb=not luma)
    try:
        if not cap.isOpened():
            raise VideoError(info.path, "OpenCV/FFmpeg cannot open it")
        period = 1.0 / sample_hz
        half = 0.5 / info.fps_hz
        nxt, i, ms0, prev, stamped = 0.0, 0, 0.0, 0.0, True
        while cap.grab():
            # the frame's own time where the container has one (variable frame rate: phone video), else
            # frame count / fps; raw streams (.h264) report 0 for every frame, so the second frame decides
            ms = cap.get(cv2.CAP_PROP_POS_MSEC)
            if i == 0:
                ms0, t = ms, 0.0
            else:
                t_pos = (ms - ms0) / 1000.0
                if i == 1:
                    stamped = math.isfinite(t_pos) and t_pos > 0
                    stats["timestamps"] = "stream" if stamped else "frame count / fps"
                if not stamped:
                    t = i / info.fps_hz
                else:   # a time that does not increase (AVI's end, a glitch): one nominal frame on
                    t = t_pos if math.isfinite(t_pos) and t_pos > prev else prev + 1.0 / info.fps_hz
            prev = t
            i += 1
            stats["frames_decoded"] = i
            stats["decoded_s"] = t + 1.0 / info.fps_hz
            if t + half < nxt:
                continue
            ok, img = cap.retrieve()
            if not ok or img is None:
                raise VideoError(info.path, f"frame {i - 1} could not be decoded")
            if luma:
                img = img[: info.height_px]
            yield t, prepare(img, info.pixel_aspect)
            while nxt <= t + half:
                nxt += period
        if i == 0:
            raise VideoError(info.path, "no decodable video frame")
        if i == 1 and info.num_frames > 1:
            # what OpenCV does where the first video stream is a cover picture (it cannot pick another stream):
            # one frame, whatever the video's length; PyAV's probe catches that before decoding (``opencv_problem``),
            # this is the check where PyAV is not installed
            raise VideoError(info.path, f"OpenCV decoded a single picture where the container states "
                                        f"{info.num_frames} frames: the first video stream is most likely a still "
                                        f"picture (cover art) stored before the video, which OpenCV cannot skip (or "
                                        f"the file is damaged after its first frame); install PyAV (pip install av), "
                                        f"whose reader picks the video stream, or keep only the video: ffmpeg -i IN "
                                        f"-map 0:v:1 -c copy OUT (ffprobe IN lists the streams)")
    finally:
        cap.release()
        cv2.utils.logging.setLogLevel(prev_level)
