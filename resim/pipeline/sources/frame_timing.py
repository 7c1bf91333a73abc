"""Whether a video's frames are evenly spaced at the rate its container states: ``frame_timing_problem``.

The OpenDV reader resamples by frame index (output frame k takes source frame ``round(t_k * fps)``), which is right
only where the frames come at one constant rate and the container states it. A variable-frame-rate file (a phone or
screen recording, a stream capture) or one whose container states a time base as its rate (90000 fps; 1000 fps in
Matroska) used to be quarantined as "truncated" (the stated rate times the duration promised frames the file does
not have), as "too short" or "below the output rate", or cut into clips whose motion timing is wrong. Now the
reason names the problem.

The timestamps of the first ``SCAN_PACKETS`` video packets are read with PyAV (demuxed, not decoded: a few MB of
a long file); without PyAV, or where it cannot open the file, only the stated rate is checked.
"""
from __future__ import annotations

import math
from pathlib import Path

# No camera a driving dataset comes from records faster; a larger "rate" is a time base (90000 in MPEG-TS and MP4,
# 1000 in Matroska) stated as the rate of a variable-frame-rate stream.
MAX_PLAUSIBLE_FPS = 240.0
SCAN_PACKETS = 600
# an interval this far from the median is irregular (beyond one tick: Matroska's 1 ms ticks make a 29.97 fps
# file's intervals 33 and 34 ms); a single one is tolerated (one dropped frame shifts the resampling by one frame)
INTERVAL_SLACK = 0.10
# the measured rate may differ this much from the stated one (plus 1 / frames scanned: an MP4 of N frames states
# a duration that ends at its last frame's start, so its average rate is N / (N - 1) times the true one)
RATE_SLACK = 0.02
_FIX = "re-encode it at a constant rate, e.g. ffmpeg -i IN -fps_mode cfr -r 30 OUT"


def frame_timing_problem(path: str | Path, stated_fps: float) -> str | None:
    """Why ``path`` (whose first video stream is the video, at ``stated_fps`` as its reader reports it) cannot be
    resampled by frame index, or None: an implausible stated rate, irregular frame intervals, or intervals that do
    not match the stated rate. A stated rate that is not a finite number > 0 is left to the caller."""
    if not (math.isfinite(stated_fps) and stated_fps > 0):
        return None
    if stated_fps > MAX_PLAUSIBLE_FPS:
        return (f"implausible frame rate {stated_fps:g} fps (more than {MAX_PLAUSIBLE_FPS:g}: the container states "
                f"a time base or a variable rate as its rate); {_FIX}")
    scanned = _first_intervals_s(path)
    if scanned is None or len(scanned[0]) < 2:
        return None
    intervals, tick = scanned
    n = len(intervals) + 1
    med = sorted(intervals)[len(intervals) // 2]
    if med <= 0:
        return f"variable frame rate: most of the first {n} frames share a timestamp; {_FIX}"
    off = [d for d in intervals if abs(d - med) > max(INTERVAL_SLACK * med, 1.01 * tick)]
    if len(off) > max(1, len(intervals) // 100):
        return (f"variable frame rate: frame intervals from {min(intervals) * 1e3:.4g} to {max(intervals) * 1e3:.4g} "
                f"ms in the first {n} frames ({len(off)} off the usual {med * 1e3:.4g} ms); {_FIX}")
    measured = len(intervals) / sum(intervals)   # the mean, not the median: ticks do not round it
    if abs(measured - stated_fps) > (RATE_SLACK + 1.0 / len(intervals)) * stated_fps:
        return (f"variable frame rate: the container states {stated_fps:g} fps, the first {n} frames come at "
                f"{measured:.4g} fps; {_FIX}")
    return None


def _first_intervals_s(path: str | Path) -> tuple[list[float], float] | None:
    """(seconds between the presentation timestamps of the first ``SCAN_PACKETS`` packets of the first video
    stream, the one OpenCV decodes, in presentation order; the stream's tick in seconds), or None without PyAV,
    where it cannot open the file, or where the stream has no timestamps (a raw .h264)."""
    try:
        import av
    except ImportError:
        return None
    try:
        with av.open(str(path)) as c:
            if not c.streams.video:
                return None
            s = c.streams.video[0]
            if not s.time_base:
                return None
            pts = []
            for pkt in c.demux(s):
                if pkt.pts is not None:
                    pts.append(pkt.pts)
                    if len(pts) >= SCAN_PACKETS:
                        break
            tb = float(s.time_base)
    except av.error.FFmpegError:
        return None
    pts.sort()   # packets come in decoding order: B-frames are presented after the frames they reference
    return [(b - a) * tb for a, b in zip(pts, pts[1:])], tb
