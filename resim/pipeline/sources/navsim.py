"""NAVSIM / OpenScene log reader.

Layout (navsim docs/install.md; see docs/sources.md)::

    ROOT/navsim_logs/<split>/<log_name>.pkl              list of per-frame dicts, 2 Hz, time order
    ROOT/sensor_blobs/<split>/<log_name>/CAM_F0/<16-hex>.jpg

Per frame we read ``token, timestamp (us), log_name, ego2global_translation
(3,), ego2global_rotation (4,) quaternion [w, x, y, z], ego_dynamic_state
[vx, vy, ax, ay] (ego frame), driving_command one-hot (left, straight, right,
unknown), cams['CAM_F0']['data_path']`` (relative to ``sensor_blobs/<split>/``).
The pose is NAVSIM's: ``(t[0], t[1], yaw(q))`` in the global nuPlan frame,
right-handed, yaw CCW from +x (the rear axle). Pickles are read with the
restricted unpickler (:mod:`.safe_pickle`), never ``pickle.load``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from resim.config import ConfigError
from resim.folders import folder_problem

from .episode import Episode, SourceError, decode_image_file, unwrap_yaw
from .listing import glob
from .safe_pickle import load_restricted

NAVSIM_FPS_HZ = 2.0  # NAVSIM_INTERVAL_LENGTH = 0.5 s (navsim/common/dataclasses.py); used for 1-frame logs
REQUIRED_KEYS = ("token", "timestamp", "ego2global_translation", "ego2global_rotation", "cams")


@dataclass
class NavsimConfig:
    root: Path = Path(".")
    split: str = "mini"
    camera: str = "CAM_F0"
    check_images_on_open: bool = True   # stat every image when opening a log (cheap; reports missing frames early)
    max_timestamp_gap_s: float = 0.75   # consecutive frames further apart than this: a gap, reported
    exclude: tuple[Path, ...] = ()      # trees never listed (the pipeline's OUT: sources/listing.py)

    def __post_init__(self):
        self.root = Path(self.root)
        if not self.split or "/" in self.split or self.split in (".", ".."):
            raise ConfigError(f"split must be a plain folder name, got {self.split!r}")
        if not (self.max_timestamp_gap_s > 0):   # `not >` so NaN is refused too
            raise ConfigError(f"max_timestamp_gap_s must be > 0, got {self.max_timestamp_gap_s}")


def quaternion_yaw(q: np.ndarray) -> np.ndarray:
    """Yaw (rad, CCW about +z) of quaternions ``[..., (w, x, y, z)]``; equals
    ``pyquaternion.Quaternion(*q).yaw_pitch_roll[0]`` for unit quaternions."""
    q = np.asarray(q, dtype=np.float64)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def yaw_quaternion(yaw: float) -> np.ndarray:
    """Unit quaternion ``[w, x, y, z]`` of a rotation by ``yaw`` about +z."""
    return np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])


class NavsimReader:
    def __init__(self, cfg: NavsimConfig):
        self.cfg = cfg
        self.logs_dir = cfg.root / "navsim_logs" / cfg.split
        self.blobs_dir = cfg.root / "sensor_blobs" / cfg.split

    def list_items(self) -> list[str]:
        """Log names (pickle stems) of the split, sorted."""
        problem = folder_problem(self.logs_dir)
        if problem:
            raise SourceError(str(self.logs_dir), f"NAVSIM logs folder {problem}")
        return sorted(p.stem for p in glob(self.logs_dir, "*.pkl", self.cfg.exclude))

    def open(self, item_id: str) -> Episode:
        path = self.logs_dir / f"{item_id}.pkl"
        if not path.is_file():
            raise SourceError(item_id, f"log pickle {path} does not exist")
        frames = load_restricted(path)
        if not isinstance(frames, list) or not frames:
            raise SourceError(str(path), f"expected a non-empty list of frame dicts, got {type(frames).__name__}"
                              + (" (empty)" if isinstance(frames, list) else ""))
        n = len(frames)
        xy = np.empty((n, 2))
        yaw = np.empty(n)
        speed = np.full(n, np.nan)
        ts = np.empty(n, dtype=np.float64)
        cmd = np.zeros((n, 4), dtype=np.int64)
        have_cmd = True
        images: list[Path] = []
        for i, fr in enumerate(frames):
            where = f"{path} frame {i}"
            if not isinstance(fr, dict):
                raise SourceError(where, f"expected a dict, got {type(fr).__name__}")
            missing = [k for k in REQUIRED_KEYS if k not in fr]
            if missing:
                raise SourceError(where, f"missing keys {missing}")
            try:
                t = np.asarray(fr["ego2global_translation"], dtype=np.float64).reshape(-1)
                q = np.asarray(fr["ego2global_rotation"], dtype=np.float64).reshape(-1)
                if t.size < 2 or q.size != 4:
                    raise ValueError(f"translation size {t.size}, rotation size {q.size}")
                ts[i] = int(fr["timestamp"]) * 1e-6
                rel = fr["cams"][self.cfg.camera]["data_path"]
                if not isinstance(rel, str):
                    raise ValueError(f"cams.{self.cfg.camera}.data_path is {type(rel).__name__}")
            except (KeyError, TypeError, ValueError) as e:
                raise SourceError(where, f"malformed frame ({type(e).__name__}: {e})") from None
            if not (np.isfinite(t[:2]).all() and np.isfinite(q).all()) or np.linalg.norm(q) < 1e-6:
                raise SourceError(where, "non-finite or zero ego pose")
            xy[i] = t[:2]
            yaw[i] = quaternion_yaw(q / np.linalg.norm(q))
            # Optional fields: absent (or None) is fine, but present and malformed is bad input like any
            # other field — a SourceError naming the frame and the field, never a TypeError of ours.
            dyn = _optional_vector(fr, "ego_dynamic_state", where, min_size=2)
            if dyn is not None:
                speed[i] = float(np.hypot(dyn[0], dyn[1]))   # NaN stays NaN: speed from the poses below
            dc = _optional_vector(fr, "driving_command", where, size=4)
            if dc is not None:
                if not np.isin(dc, (0.0, 1.0)).all():
                    raise SourceError(where, f"malformed driving_command {dc.tolist()} (expected a one-hot of 4)")
                cmd[i] = dc.astype(np.int64)
            else:
                have_cmd = False
            images.append(self.blobs_dir / rel)
        dt = np.diff(ts)
        if np.any(dt <= 0):
            raise SourceError(str(path), "timestamps are not strictly increasing")
        # The frame rate comes from the timestamps, not from the format's nominal 2 Hz: a log of all
        # 10 Hz sweeps would otherwise be cut as if 2 Hz (clips 5x too long, commands over the wrong
        # horizon). The median interval ignores a few gaps; the rate is snapped to a whole Hz when
        # within 1% of it, since timestamps jitter (µs to ms) around nominal 2 / 10 / 20 Hz.
        fps_hz = _nominal_rate(1.0 / float(np.median(dt))) if n > 1 else NAVSIM_FPS_HZ
        # a gap is more than 1.5 intervals (a missing frame), and never more than max_timestamp_gap_s
        max_gap_s = min(self.cfg.max_timestamp_gap_s, 1.5 / fps_hz)
        gaps = np.flatnonzero(dt > max_gap_s)
        if gaps.size:
            raise SourceError(str(path), f"missing frame(s): {gaps.size} gap(s) > {max_gap_s:g} s in a "
                              f"{fps_hz:g} Hz log, first after frame {int(gaps[0])}")
        if self.cfg.check_images_on_open:
            for i, p in enumerate(images):
                if not p.is_file():
                    raise SourceError(str(p), f"missing {self.cfg.camera} image of frame {i} of log {item_id}")
        first = decode_image_file(images[0], str(images[0]))
        hw = tuple(first.shape[:2])
        if np.isnan(speed).any():  # no dynamic state: speed from the poses
            v = np.r_[np.hypot(*np.diff(xy, axis=0).T) / np.diff(ts), np.nan]
            v[-1] = v[-2] if n > 1 else 0.0
            speed = np.where(np.isnan(speed), v, speed)

        def loader(a: int, b: int, size_hw):
            for p in images[a:b]:
                yield decode_image_file(p, str(p), size_hw, stored_hw=hw)

        return Episode(source="navsim", item_id=item_id, fps_hz=fps_hz, num_frames=n,
                       frame_size_hw=hw, poses=np.c_[xy, unwrap_yaw(yaw)], speed_mps=speed,
                       driving_command=cmd if have_cmd else None, timestamps_s=ts - ts[0], _loader=loader)


def _nominal_rate(hz: float) -> float:
    whole = round(hz)
    return float(whole) if whole >= 1 and abs(hz - whole) <= 0.01 * hz else round(hz, 3)


def _optional_vector(fr: dict, key: str, where: str, size: int | None = None, min_size: int | None = None):
    """``fr[key]`` as a flat float64 array, None when absent; ``SourceError`` naming frame and field if malformed."""
    v = fr.get(key)
    if v is None:
        return None
    try:
        a = np.asarray(v, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as e:
        raise SourceError(where, f"malformed {key} {v!r:.80} ({type(e).__name__}: {e})") from None
    if (size is not None and a.size != size) or (min_size is not None and a.size < min_size):
        want = f"{size}" if size is not None else f">= {min_size}"
        raise SourceError(where, f"malformed {key}: {a.size} value(s), expected {want}")
    return a
