"""The one episode record every source yields.

An :class:`Episode` is one work unit of a source (an OpenDV video, a NAVSIM
log, a Bench2Drive route folder): a sequence of front-camera frames at a known
rate with, where the source has them, per-frame ego poses, speed, the dataset's
own driving command and an episode-level outcome. Frames are decoded lazily
through a loader the reader supplies, so a long video is never held in memory.

Conventions (all sources, after conversion by the reader):

* poses are ``(num_frames, 3)`` float64 ``[x m, y m, yaw rad]`` in a
  right-handed world frame (x, y in the ground plane, z up), yaw measured
  counter-clockwise from world +x, i.e. a left turn increases yaw; yaw is
  *unwrapped* along the episode (no 2*pi jumps between frames);
* frames are RGB uint8 ``(H, W, 3)``;
* bad input raises :class:`SourceError` naming the item and the reason; readers
  never raise anything else for bad data.
"""
from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from typing import Callable, Iterator

import cv2
import numpy as np

from resim.media.frames import resize_rgb


class SourceError(Exception):
    """Bad input: ``item`` (file or work unit) and ``reason`` (what is wrong)."""

    def __init__(self, item: str, reason: str):
        super().__init__(f"{item}: {reason}")
        self.item = str(item)
        self.reason = reason


@dataclass
class Outcome:
    """Episode-level result. ``infraction_score`` is 1.0 for a clean run and is
    multiplied down per infraction (CARLA leaderboard ``score_penalty``)."""

    hazard: bool
    infraction_score: float
    infractions: list[str] = field(default_factory=list)


# A frame loader: (start, stop, size_hw or None) -> iterator of RGB uint8 frames.
FrameLoader = Callable[[int, int, "tuple[int, int] | None"], Iterator[np.ndarray]]


@dataclass
class Episode:
    """One video / log / route; frames read lazily via :meth:`frames`."""

    source: str                              # "opendv" | "navsim" | "carla" | "synthetic"
    item_id: str                             # stable id of the work unit (relative path or log name)
    fps_hz: float                            # rate of the frames this record exposes
    num_frames: int
    frame_size_hw: tuple[int, int]           # (H, W) of the frames as stored (before any resize)
    poses: np.ndarray | None = None          # (num_frames, 3) float64 x m, y m, yaw rad (CCW, unwrapped)
    speed_mps: np.ndarray | None = None      # (num_frames,) float64
    outcome: Outcome | None = None
    driving_command: np.ndarray | None = None  # dataset's own per-frame command (NAVSIM one-hot (N, 4))
    timestamps_s: np.ndarray | None = None   # (num_frames,) seconds from the episode's first frame
    warnings: list[str] = field(default_factory=list)  # repaired defects (e.g. NaN compass interpolated)
    source_duration_s: float | None = None   # the whole recording, before any discard (None: num_frames / fps_hz)
    held_frames: int = 0                     # trailing copies of the last recorded frame (:meth:`hold_last`)
    _loader: FrameLoader | None = field(default=None, repr=False, compare=False)

    def __post_init__(self):
        # Our own invariants: a reader that builds an inconsistent record is a bug, fail loudly.
        if self.poses is not None:
            self.poses = np.asarray(self.poses, dtype=np.float64)
            if self.poses.shape != (self.num_frames, 3):
                raise ValueError(f"{self.item_id}: poses shape {self.poses.shape} != ({self.num_frames}, 3)")
        if self.speed_mps is not None:
            self.speed_mps = np.asarray(self.speed_mps, dtype=np.float64)
            if self.speed_mps.shape != (self.num_frames,):
                raise ValueError(f"{self.item_id}: speed shape {self.speed_mps.shape} != ({self.num_frames},)")
        if self.driving_command is not None and len(self.driving_command) != self.num_frames:
            raise ValueError(f"{self.item_id}: driving_command has {len(self.driving_command)} rows")

    @property
    def duration_s(self) -> float:
        return self.num_frames / self.fps_hz

    def frames(self, start: int = 0, stop: int | None = None,
               size_hw: tuple[int, int] | None = None) -> Iterator[np.ndarray]:
        """Yield RGB uint8 frames ``start .. stop-1`` (each ``(H, W, 3)``, 0..255),
        resized to ``size_hw`` = (H, W) right after decoding when given.
        Raises :class:`SourceError` when the underlying data turn out bad
        (truncated video, unreadable image)."""
        stop = self.num_frames if stop is None else stop
        if not (0 <= start <= stop <= self.num_frames):
            raise IndexError(f"{self.item_id}: frames [{start}, {stop}) outside [0, {self.num_frames})")
        if self._loader is None:
            raise RuntimeError(f"{self.item_id}: episode has no frame loader")
        return self._loader(start, stop, size_hw)

    def replace(self, **changes) -> "Episode":
        return dataclasses.replace(self, **changes)

    def hold_last(self, num_frames: int) -> "Episode":
        """This episode lengthened to ``num_frames`` by repeating its last frame: what the camera of an ego
        that has stopped for good keeps seeing (a CARLA / synthetic route ends early after a crash). The
        held frames repeat the last pose, command and outcome, with speed 0 and timestamps going on at
        ``fps_hz``; ``warnings`` says how many frames are held. ``num_frames`` <= ours: returned as is."""
        extra = num_frames - self.num_frames
        if extra <= 0:
            return self
        if self.num_frames < 1:
            raise ValueError(f"{self.item_id}: an episode without frames has no last frame to hold")
        last, loader = self.num_frames - 1, self._loader

        def held(start: int, stop: int, size_hw):
            if loader is None:
                raise RuntimeError(f"{self.item_id}: episode has no frame loader")
            frame, got = None, 0
            if start <= last:
                for frame in loader(start, min(stop, last + 1), size_hw):
                    got += 1
                    yield frame
                if got != min(stop, last + 1) - start:
                    return   # the recording ended early: no frame to hold (the stages count what they got)
            if stop > last + 1:
                if frame is None:   # the window starts in the held part: decode the last frame once
                    frame = next(iter(loader(last, last + 1, size_hw)), None)
                    if frame is None:
                        return
                for _ in range(max(start, last + 1), stop):
                    yield frame.copy()

        def pad(a):
            return None if a is None else np.concatenate([a, np.repeat(np.asarray(a)[-1:], extra, axis=0)])

        ts = self.timestamps_s
        if ts is not None:
            ts = np.concatenate([ts, ts[-1] + np.arange(1, extra + 1) / self.fps_hz])
        return self.replace(num_frames=num_frames, poses=pad(self.poses), driving_command=pad(self.driving_command),
                            speed_mps=None if self.speed_mps is None else np.r_[self.speed_mps, np.zeros(extra)],
                            timestamps_s=ts, held_frames=self.held_frames + extra, _loader=held,
                            warnings=[*self.warnings, f"{extra} frame(s) appended holding the last frame "
                                                      f"(an episode shorter than one clip)"])


def decode_image_file(path, item: str, size_hw: tuple[int, int] | None = None,
                      stored_hw: tuple[int, int] | None = None) -> np.ndarray:
    """Read a jpg/png as RGB uint8, resized as early as possible; SourceError if missing/unreadable.

    When the stored size is known and the target is at most 1/2, 1/4 or 1/8 of it, libjpeg
    decodes at that reduced scale directly (``IMREAD_REDUCED_COLOR_*``), which is what
    'resize as early as possible' buys for 1600x900 / 1920x1080 frames.
    """
    if not _exists(path):
        raise SourceError(item, f"missing image {path}")
    data = np.fromfile(str(path), dtype=np.uint8)
    flag = cv2.IMREAD_COLOR
    if size_hw is not None and stored_hw is not None:
        for r, f in ((8, cv2.IMREAD_REDUCED_COLOR_8), (4, cv2.IMREAD_REDUCED_COLOR_4),
                     (2, cv2.IMREAD_REDUCED_COLOR_2)):
            if stored_hw[0] // r >= size_hw[0] and stored_hw[1] // r >= size_hw[1]:
                flag = f
                break
    img = cv2.imdecode(data, flag) if data.size else None
    if img is None:
        raise SourceError(item, f"cannot decode image {path} ({data.size} bytes)")
    img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    return resize_rgb(img, size_hw)


def _exists(path) -> bool:
    return os.path.isfile(str(path))


def unwrap_yaw(yaw: np.ndarray) -> np.ndarray:
    """Remove 2*pi jumps between consecutive yaws (rad)."""
    return np.unwrap(np.asarray(yaw, dtype=np.float64))


def scan_items(reader, read_frames: bool = True, size_hw: tuple[int, int] | None = (32, 56)):
    """Open every item of ``reader`` (and decode its frames when ``read_frames``); bad items are
    collected, not raised. Returns ``(good_item_ids, problems: list[SourceError])``."""
    good, problems = [], []
    for item in reader.list_items():
        try:
            ep = reader.open(item)
            if read_frames:
                for _ in ep.frames(size_hw=size_hw):
                    pass
        except SourceError as e:
            problems.append(e)
        else:
            good.append(item)
    return good, problems
