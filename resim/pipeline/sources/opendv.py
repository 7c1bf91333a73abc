"""OpenDV-YouTube-style reader: a folder of front-camera videos, no poses.

Layout (the OpenDV-YouTube toolkit stores ``<channel>/<video_id>.<ext>``)::

    ROOT/**/<video_id>.{mp4,mkv,webm,mov}
    ROOT/videos.csv        optional: video_id,start_discard_s,end_discard_s,notes

Defaults follow the OpenDV-YouTube toolkit: resample to 10 Hz, discard the
first 90 s (intros) and the last 60 s (outros), skip videos whose height is
under 720 px. The synthetic world's OpenDV part is read with
``OpenDVConfig.preset("synthetic", root=...)`` (no discards, low minimum height).

Frames are decoded lazily and resized right after decoding (before colour
conversion); resampling keeps, for output frame k at ``t_k = start + k / fps_hz``,
the source frame nearest to ``t_k``.

Frames are read with OpenCV, which always decodes the file's first video stream. A file whose first video
stream is a cover picture stored before the video (an MP4 ``covr`` box ahead of the tracks, a Matroska PNG
track) is quarantined with that reason rather than cut into clips of the picture: ``open`` asks media's
probe (``resim.media.video_probe.first_stream_not_video``, PyAV) which stream is the video. Resampling
by frame index needs a constant frame rate that the container states: a variable or implausible rate is
quarantined with that reason (``frame_timing.frame_timing_problem``).
"""
from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from resim.config import ConfigError, from_dict
from resim.folders import folder_problem
from resim.media.files import NotARegularFile, check_regular
from resim.media.frames import MIN_RATE_SLACK, resize_rgb
from resim.media.video_probe import first_stream_not_video

from .episode import Episode, SourceError
from .frame_timing import frame_timing_problem
from .listing import walk_files

VIDEO_EXTENSIONS = ("mp4", "mkv", "webm", "mov")


@dataclass
class OpenDVConfig:
    root: Path = Path(".")
    fps_hz: float = 10.0                 # output rate after resampling
    start_discard_s: float = 90.0        # default discard at the start (per-video CSV overrides)
    end_discard_s: float = 60.0          # default discard at the end
    min_height_px: int = 720             # videos lower than this are skipped (reported)
    metadata_csv: str = "videos.csv"     # relative to root; absent file = no per-video metadata
    extensions: tuple[str, ...] = VIDEO_EXTENSIONS
    verify_last_frame: bool = True       # on open, seek to the last frame to catch truncated files early
    seek_gap_s: float = 2.0              # seek instead of decoding through gaps longer than this
    exclude: tuple[Path, ...] = ()       # trees never listed (the pipeline's OUT: sources/listing.py)

    def __post_init__(self):
        self.root = Path(self.root)
        # written as `not (x > 0)` / isfinite so NaN and inf are refused too
        if not (self.fps_hz > 0 and math.isfinite(self.fps_hz)):
            raise ConfigError(f"fps_hz must be a finite number > 0, got {self.fps_hz}")
        if not all(x >= 0 and math.isfinite(x) for x in (self.start_discard_s, self.end_discard_s)):
            raise ConfigError("start_discard_s and end_discard_s must be finite numbers >= 0")
        if self.min_height_px < 1:
            raise ConfigError(f"min_height_px must be >= 1, got {self.min_height_px}")

    @classmethod
    def preset(cls, name: str, **overrides) -> "OpenDVConfig":
        if name not in OPENDV_PRESETS:
            raise ConfigError(f"unknown OpenDV preset {name!r}; known: {sorted(OPENDV_PRESETS)}")
        return from_dict(cls, {**OPENDV_PRESETS[name], **overrides})


OPENDV_PRESETS: dict[str, dict] = {
    # the OpenDV-YouTube toolkit's defaults
    "opendv_youtube": {},
    # our synthetic world: short clips, nothing to discard, low resolution
    "synthetic": {"start_discard_s": 0.0, "end_discard_s": 0.0, "min_height_px": 32},
}


@dataclass
class _VideoMeta:
    start_discard_s: float | None = None
    end_discard_s: float | None = None
    notes: str = ""


@dataclass
class OpenDVReader:
    cfg: OpenDVConfig
    # videos.csv is read on first use (list_items / open), not here: building a reader only checks its
    # config (the pipeline builds every reader at load time), and a bad CSV is then a SourceError the
    # enumerate stage can quarantine instead of an exception out of the constructor.
    _meta: dict[str, _VideoMeta] | None = field(default=None, init=False, repr=False)
    _bad_meta: dict[str, tuple[str, str]] = field(default_factory=dict, init=False, repr=False)  # id -> (where, why)

    # -- metadata --------------------------------------------------------------------------
    def _metadata(self) -> dict[str, _VideoMeta]:
        if self._meta is None:
            self._meta = self._read_metadata()
        return self._meta

    def _read_metadata(self) -> dict[str, _VideoMeta]:
        """Parse videos.csv. A file that cannot be read as a CSV at all (not UTF-8, not CSV) or a row
        without a video id is a ``SourceError`` for the whole source (no video's discards can be trusted);
        a bad value in a row that names its video only quarantines that video (kept in ``_bad_meta``)."""
        path = self.cfg.root / self.cfg.metadata_csv
        if not path.is_file():
            return {}
        out: dict[str, _VideoMeta] = {}
        data = path.read_bytes()
        try:
            # utf-8-sig: a spreadsheet's byte-order mark would otherwise become part of the first header
            text = data.decode("utf-8-sig")
        except UnicodeDecodeError as e:
            raise SourceError(str(path), f"not UTF-8 text (byte {data[e.start:e.start + 1]!r} at offset "
                                         f"{e.start}); save the metadata CSV as UTF-8") from None
        try:
            rows = list(csv.DictReader(io.StringIO(text, newline="")))
        except csv.Error as e:
            raise SourceError(str(path), f"malformed CSV ({e})") from None
        for i, row in enumerate(rows, start=2):  # line numbers as a spreadsheet shows them
            vid = (row.get("video_id") or row.get("videoid") or "").strip()
            if not vid:
                raise SourceError(f"{path}:{i}", "row has no video_id")
            try:
                out[vid] = _VideoMeta(
                    _opt_float(row.get("start_discard_s", row.get("start_discard"))),
                    _opt_float(row.get("end_discard_s", row.get("end_discard"))),
                    (row.get("notes") or "").strip(),
                )
            except ValueError as e:
                self._bad_meta[vid] = (f"{path}:{i}", f"bad discard value for video {vid!r} ({e})")
        return out

    def _video_meta(self, item_id: str) -> _VideoMeta:
        p = Path(item_id)
        keys = (item_id, str(p.with_suffix("")), p.stem)
        meta = self._metadata()
        for k in keys:
            if k in meta:
                return meta[k]
            if k in self._bad_meta:
                raise SourceError(*self._bad_meta[k])
        return _VideoMeta()

    def discards_s(self, item_id: str) -> tuple[float, float]:
        """(start, end) seconds dropped from video ``item_id``: its videos.csv row, else the config's."""
        meta = self._video_meta(item_id)
        start_s = self.cfg.start_discard_s if meta.start_discard_s is None else meta.start_discard_s
        end_s = self.cfg.end_discard_s if meta.end_discard_s is None else meta.end_discard_s
        return start_s, end_s

    # -- listing / opening -------------------------------------------------------------------
    def list_items(self) -> list[str]:
        """Relative paths (posix) of all videos under root, sorted."""
        root = self.cfg.root
        problem = folder_problem(root)
        if problem:
            raise SourceError(str(root), f"OpenDV root {problem}")
        self._metadata()   # an unreadable videos.csv makes the whole source unusable: fail at listing
        exts = {"." + e.lower().lstrip(".") for e in self.cfg.extensions}
        return sorted(p.relative_to(root).as_posix()
                      for p in walk_files(root, self.cfg.exclude, exts, special=True))

    def open(self, item_id: str) -> Episode:
        path = self.cfg.root / item_id
        try:   # a FIFO would block OpenCV's open for ever; a device, a dangling link: quarantined, named
            check_regular(path)
        except NotARegularFile as e:
            raise SourceError(item_id, f"video file {e}") from None
        _refuse_cover_first(path, item_id)
        cap = cv2.VideoCapture(str(path))
        try:
            if not cap.isOpened():
                raise SourceError(item_id, "cannot open video (unreadable or truncated container)")
            src_fps = float(cap.get(cv2.CAP_PROP_FPS))
            # before the frame count, which OpenCV derives from the rate where the container states none: a
            # variable or absurd rate then promises frames the file lacks, which read as "truncated"
            timing = frame_timing_problem(path, src_fps)
            if timing:
                raise SourceError(item_id, timing)
            count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
            w = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))
            h = int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
            if not (src_fps > 0 and math.isfinite(src_fps)) or count <= 0 or h <= 0 or w <= 0:
                raise SourceError(item_id, f"video header unusable (fps={src_fps}, frames={count}, size={w}x{h})")
            if h < self.cfg.min_height_px:
                raise SourceError(item_id, f"height {h} px < min_height_px {self.cfg.min_height_px} (skipped)")
            # Resampling keeps the nearest source frame: below the output rate that repeats frames (a
            # 5 fps video at 10 Hz is every frame twice), i.e. invents motion timing (pipelines.frames).
            if src_fps < self.cfg.fps_hz * (1 - MIN_RATE_SLACK):
                raise SourceError(item_id, f"frame rate {src_fps:g} fps is below the output rate "
                                           f"{self.cfg.fps_hz:g} Hz (frames would be repeated)")
            if self.cfg.verify_last_frame:
                cap.set(cv2.CAP_PROP_POS_FRAMES, count - 1)
                if not cap.grab():
                    raise SourceError(item_id, f"truncated video: header says {count} frames but frame "
                                               f"{count - 1} cannot be decoded")
        finally:
            cap.release()

        start_s, end_s = self.discards_s(item_id)
        duration_s = count / src_fps
        usable_s = duration_s - start_s - end_s
        n_out = int(math.floor(usable_s * self.cfg.fps_hz + 1e-9))
        if n_out < 1:
            raise SourceError(item_id, f"too short: {duration_s:.1f} s minus discards "
                                       f"{start_s:.0f} s + {end_s:.0f} s leaves nothing")
        t = start_s + np.arange(n_out) / self.cfg.fps_hz
        src_idx = np.minimum(np.round(t * src_fps).astype(np.int64), count - 1)

        def loader(a: int, b: int, size_hw):
            return _decode(path, item_id, src_idx[a:b], src_fps, size_hw, self.cfg.seek_gap_s, count)

        return Episode(source="opendv", item_id=item_id, fps_hz=self.cfg.fps_hz, num_frames=n_out,
                       frame_size_hw=(h, w), timestamps_s=t - start_s, source_duration_s=duration_s,
                       _loader=loader)


def _refuse_cover_first(path: Path, item_id: str) -> None:
    """``SourceError`` where OpenCV would decode a cover picture instead of the video: the first video stream is
    an attached or still picture stored before the video (``resim.media.video_probe``; needs PyAV, without it nothing
    is checked here). Every other problem is left to ``open``'s own checks, which name it as before."""
    found = first_stream_not_video(path)
    if found is None:
        return
    index, what = found
    if index is None:   # e.g. an audio file with cover art
        raise SourceError(item_id, f"video file {path}: no video stream, only a still picture ({what}); OpenCV "
                                   "would read the picture as a one-frame video")
    raise SourceError(item_id, f"video file {path}: its first video stream is a cover picture stored before the "
                               f"video ({what}; the video is stream {index}); OpenCV, which this reader decodes with, "
                               f"would read the cover picture instead of the video. Keep only the video: "
                               f"ffmpeg -i IN -map 0:{index} -c copy OUT")


def _opt_float(v) -> float | None:
    if v is None or str(v).strip() == "":
        return None
    x = float(v)
    if not math.isfinite(x) or x < 0:
        raise ValueError(f"{v!r} is not a finite number >= 0")
    return x


def _decode(path: Path, item_id: str, wanted: np.ndarray, src_fps: float, size_hw, seek_gap_s: float,
            count: int) -> Iterator[np.ndarray]:
    """Decode the source frames ``wanted`` (non-decreasing indices) one at a time."""
    if len(wanted) == 0:
        return
    cap = cv2.VideoCapture(str(path))
    try:
        if not cap.isOpened():
            raise SourceError(item_id, "cannot open video (unreadable or truncated container)")
        pos = 0  # index of the next frame grab() returns
        if wanted[0] > seek_gap_s * src_fps:
            cap.set(cv2.CAP_PROP_POS_FRAMES, int(wanted[0]))
            pos = int(cap.get(cv2.CAP_PROP_POS_FRAMES))
        last_idx, last_img = -1, None
        for idx in wanted:
            idx = int(idx)
            if idx == last_idx:              # upsampling: the same source frame again
                yield last_img.copy()
                continue
            if idx - pos > seek_gap_s * src_fps:
                cap.set(cv2.CAP_PROP_POS_FRAMES, idx)
                pos = int(cap.get(cv2.CAP_PROP_POS_FRAMES))
            while pos <= idx:
                if not cap.grab():
                    raise SourceError(item_id, f"truncated video: frame {pos} of {count} cannot be decoded")
                pos += 1
            ok, bgr = cap.retrieve()
            if not ok or bgr is None:
                raise SourceError(item_id, f"frame {idx} cannot be decoded")
            if size_hw is not None:
                bgr = resize_rgb(bgr, size_hw)   # resize first: colour conversion on fewer pixels
            last_idx, last_img = idx, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
            yield last_img
    finally:
        cap.release()
