"""NAVSIM / OpenScene log reader (issue 3).

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

from .episode import Episode, SourceError, decode_image_file, unwrap_yaw
from .safe_pickle import load_restricted

NAVSIM_FPS_HZ = 2.0  # NAVSIM_INTERVAL_LENGTH = 0.5 s (navsim/common/dataclasses.py)
REQUIRED_KEYS = ("token", "timestamp", "ego2global_translation", "ego2global_rotation", "cams")


@dataclass
class NavsimConfig:
    root: Path = Path(".")
    split: str = "mini"
    camera: str = "CAM_F0"
    check_images_on_open: bool = True   # stat every image when opening a log (cheap; reports missing frames early)
    max_timestamp_gap_s: float = 0.75   # consecutive frames further apart than this: a gap, reported

    def __post_init__(self):
        self.root = Path(self.root)
        if not self.split or "/" in self.split:
            raise ConfigError(f"split must be a plain folder name, got {self.split!r}")
        if self.max_timestamp_gap_s <= 0:
            raise ConfigError("max_timestamp_gap_s must be > 0")


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
        if not self.logs_dir.is_dir():
            raise SourceError(str(self.logs_dir), "NAVSIM logs folder does not exist")
        return sorted(p.stem for p in self.logs_dir.glob("*.pkl"))

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
            dyn = fr.get("ego_dynamic_state")
            if dyn is not None and len(dyn) >= 2:
                speed[i] = float(np.hypot(float(dyn[0]), float(dyn[1])))
            dc = fr.get("driving_command")
            if dc is not None and np.asarray(dc).reshape(-1).size == 4:
                cmd[i] = np.asarray(dc).reshape(-1).astype(np.int64)
            else:
                have_cmd = False
            images.append(self.blobs_dir / rel)
        if np.any(np.diff(ts) <= 0):
            raise SourceError(str(path), "timestamps are not strictly increasing")
        gaps = np.flatnonzero(np.diff(ts) > self.cfg.max_timestamp_gap_s)
        if gaps.size:
            raise SourceError(str(path), f"missing frame(s): {gaps.size} gap(s) > {self.cfg.max_timestamp_gap_s} s, "
                              f"first after frame {int(gaps[0])}")
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

        return Episode(source="navsim", item_id=item_id, fps_hz=NAVSIM_FPS_HZ, num_frames=n,
                       frame_size_hw=hw, poses=np.c_[xy, unwrap_yaw(yaw)], speed_mps=speed,
                       driving_command=cmd if have_cmd else None, timestamps_s=ts - ts[0], _loader=loader)
