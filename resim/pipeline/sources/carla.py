"""CARLA / Bench2Drive route-folder reader.

Layout (Bench2Drive ``tools/data_collect.py``; see docs/sources.md)::

    ROOT/<Scenario>_<TownXX>_Route<id>_Weather<id>/anno/00000.json.gz     one per frame, 10 Hz
    ROOT/<Scenario>_<TownXX>_Route<id>_Weather<id>/camera/rgb_front/00000.jpg
    ROOT/*.json                                                           leaderboard results (optional)

Coordinates: anno ``x, y`` are CARLA (Unreal) world metres, **left-handed**
(y to the right/south); ``theta`` is the IMU compass in rad **clockwise from
North**, where North is CARLA -y. We convert to our right-handed frame with
``(x, -y)`` and ``yaw = pi/2 - theta`` (CCW, left +), unwrapped. A NaN/None
compass (anno.md warns it happens) is interpolated from its valid neighbours
and reported in ``Episode.warnings``; more than ``max_nan_theta_fraction`` NaN
frames is an error.

``command_near`` (CARLA RoadOption) becomes a NAVSIM-style one-hot
(left, straight, right, unknown): LEFT -> left, RIGHT -> right,
STRAIGHT/LANEFOLLOW -> straight, VOID/CHANGELANE* -> unknown.

The outcome comes from the results file's record for the route: matched by
``save_name`` == folder name, else by route number (``Route<id>`` in the folder
name vs ``RouteScenario_<id>``). A results file that is bad data is skipped and
reported in ``problems``; a transient ``OSError`` while reading one propagates
(nothing is cached), so the pipeline retries it like any other read.
"""
from __future__ import annotations

import gzip
import json
import math
import re
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from resim.config import ConfigError
from resim.folders import folder_problem

from .episode import Episode, SourceError, decode_image_file
from .listing import children, glob
from .leaderboard import RouteRecord, load_results

B2D_FPS_HZ = 10.0  # Env_Manager.frame_rate
_ROUTE_IN_FOLDER = re.compile(r"Route(\d+)")
ROAD_OPTION_TO_ONEHOT = {1: 0, 2: 2, 3: 1, 4: 1}  # LEFT, RIGHT, STRAIGHT, LANEFOLLOW; others -> 3 (unknown)


@dataclass
class CarlaConfig:
    root: Path = Path(".")
    camera: str = "rgb_front"
    results_glob: str = "*.json"          # leaderboard results files, relative to root
    max_nan_theta_fraction: float = 0.2   # above this share of NaN compass frames the route is refused
    exclude: tuple[Path, ...] = ()        # trees never listed (the pipeline's OUT: sources/listing.py)

    def __post_init__(self):
        self.root = Path(self.root)
        if not 0.0 <= self.max_nan_theta_fraction < 1.0:
            raise ConfigError("max_nan_theta_fraction must be in [0, 1)")


def carla_to_ours(x: np.ndarray, y: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """CARLA (x, y left-handed, compass theta) -> ours (x, y right-handed, yaw CCW)."""
    return np.c_[np.asarray(x, float), -np.asarray(y, float), math.pi / 2 - np.asarray(theta, float)]


def ours_to_carla(x: float, y: float, yaw: float) -> tuple[float, float, float]:
    """Inverse of :func:`carla_to_ours`: returns (x, y, theta) with theta wrapped to [0, 2*pi)."""
    return float(x), float(-y), float((math.pi / 2 - yaw) % (2 * math.pi))


class CarlaReader:
    def __init__(self, cfg: CarlaConfig):
        self.cfg = cfg
        self.problems: list[SourceError] = []   # unreadable results files (not fatal; the pipeline
        #                                         turns them into quarantine rows at enumerate)
        self._records: list[RouteRecord] | None = None

    # results ---------------------------------------------------------------------------------
    def records(self) -> list[RouteRecord]:
        if self._records is None:
            # Built aside and kept only once every file was read: an OSError (transient I/O, see
            # load_results) propagates and leaves nothing cached, so a retry reads all files again
            # instead of finding a partial list (routes silently without outcome).
            records: list[RouteRecord] = []
            problems: list[SourceError] = []
            for p in glob(self.cfg.root, self.cfg.results_glob, self.cfg.exclude):
                try:
                    records.extend(load_results(p).records)
                except SourceError as e:
                    problems.append(SourceError(e.item, f"{e.reason}; results file skipped, so routes "
                                                        "recorded only there get no outcome (hazard unknown)"))
            self._records, self.problems = records, problems
        return self._records

    def record_for(self, item_id: str) -> RouteRecord | None:
        recs = self.records()
        for r in recs:
            if r.save_name == item_id:
                return r
        m = _ROUTE_IN_FOLDER.search(item_id)
        if m:
            hits = [r for r in recs if r.route_number == int(m.group(1))]
            if len(hits) == 1:
                return hits[0]
        return None

    # routes ----------------------------------------------------------------------------------
    def list_items(self) -> list[str]:
        problem = folder_problem(self.cfg.root)
        if problem:
            raise SourceError(str(self.cfg.root), f"CARLA root {problem}")
        self.records()   # read the results files now, so `problems` is complete once the items are listed
        return sorted(p.name for p in children(self.cfg.root, self.cfg.exclude) if (p / "anno").is_dir())

    def open(self, item_id: str) -> Episode:
        folder = self.cfg.root / item_id
        anno_dir = folder / "anno"
        cam_dir = folder / "camera" / self.cfg.camera
        if not anno_dir.is_dir():
            raise SourceError(item_id, f"no anno folder in {folder}")
        annos = sorted(anno_dir.glob("*.json.gz"))
        if not annos:
            raise SourceError(item_id, "anno folder is empty")
        n = len(annos)
        for i, p in enumerate(annos):
            if p.name != f"{i:05d}.json.gz":
                raise SourceError(str(anno_dir / f"{i:05d}.json.gz"), f"missing annotation frame {i} of route {item_id}")
        images = [cam_dir / f"{i:05d}.jpg" for i in range(n)]
        for i, p in enumerate(images):
            if not p.is_file():
                raise SourceError(str(p), f"missing {self.cfg.camera} frame {i} of route {item_id}")
        x, y, theta, speed = (np.empty(n) for _ in range(4))
        cmd = np.zeros((n, 4), dtype=np.int64)
        for i, p in enumerate(annos):
            a = _read_anno(p)
            try:
                x[i], y[i] = _finite(a["x"]), _finite(a["y"])
                theta[i] = np.nan if a.get("theta") is None else float(a["theta"])
                speed[i] = np.nan if a.get("speed") is None else float(a["speed"])
            except KeyError as e:
                raise SourceError(str(p), f"malformed annotation: missing key {e}") from None
            except (TypeError, ValueError) as e:
                raise SourceError(str(p), f"malformed annotation: {e}") from None
            opt = a.get("command_near")
            cmd[i, ROAD_OPTION_TO_ONEHOT.get(opt if isinstance(opt, int) else -1, 3)] = 1
        warnings: list[str] = []
        yaw = _fill_theta(theta, item_id, self.cfg.max_nan_theta_fraction, warnings)
        poses = carla_to_ours(x, y, yaw)
        poses[:, 2] = np.unwrap(poses[:, 2])
        poses[:, 2] -= 2 * math.pi * np.round(poses[0, 2] / (2 * math.pi))  # first yaw in [-pi, pi]
        bad_v = ~np.isfinite(speed)
        if bad_v.any():  # speedometer NaN: take the speed from the poses
            v = np.hypot(*np.diff(poses[:, :2], axis=0).T) * B2D_FPS_HZ
            v = np.r_[v, v[-1:]] if n > 1 else np.zeros(1)
            speed[bad_v] = v[bad_v]
            warnings.append(f"speed NaN in {int(bad_v.sum())} frame(s); taken from the poses")
        first = decode_image_file(images[0], str(images[0]))
        hw = tuple(first.shape[:2])
        rec = self.record_for(item_id)
        if rec is None and self.problems:
            warnings.append("no results record for this route; unreadable results file(s): "
                            + ", ".join(e.item for e in self.problems))

        def loader(a: int, b: int, size_hw):
            for p in images[a:b]:
                yield decode_image_file(p, str(p), size_hw, stored_hw=hw)

        return Episode(source="carla", item_id=item_id, fps_hz=B2D_FPS_HZ, num_frames=n, frame_size_hw=hw,
                       poses=poses, speed_mps=speed, outcome=rec.outcome() if rec else None,
                       driving_command=cmd, timestamps_s=np.arange(n) / B2D_FPS_HZ, warnings=warnings,
                       _loader=loader)


def _finite(v) -> float:
    if isinstance(v, bool) or v is None:
        raise ValueError(f"expected a number, got {v!r}")
    f = float(v)
    if not math.isfinite(f):
        raise ValueError(f"non-finite position {v!r}")
    return f


def _read_anno(p: Path) -> dict:
    # Only decoding errors are bad data. A plain OSError (EIO, a stale NFS handle) may be transient and
    # propagates so the pipeline retries it (quarantine.max_attempts); BadGzipFile is an OSError subclass,
    # hence listed explicitly.
    try:
        with gzip.open(p, "rt", encoding="utf-8") as f:
            a = json.load(f)
    except (gzip.BadGzipFile, EOFError, zlib.error, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise SourceError(str(p), f"malformed annotation ({type(e).__name__}: {e})") from None
    if not isinstance(a, dict):
        raise SourceError(str(p), f"malformed annotation: top level is {type(a).__name__}, expected an object")
    return a


def _fill_theta(theta: np.ndarray, item: str, max_frac: float, warnings: list[str]) -> np.ndarray:
    """Interpolate NaN compass readings (on the unwrapped angle) from valid neighbours."""
    bad = ~np.isfinite(theta)
    if not bad.any():
        return theta
    frac = bad.mean()
    if frac > max_frac or bad.all():
        raise SourceError(item, f"compass theta is NaN in {int(bad.sum())}/{theta.size} frames "
                                f"(> max_nan_theta_fraction {max_frac})")
    idx = np.arange(theta.size)
    good = ~bad
    unwrapped = np.unwrap(theta[good])
    out = theta.copy()
    out[good] = unwrapped
    out[bad] = np.interp(idx[bad], idx[good], unwrapped)
    warnings.append(f"compass theta NaN in {int(bad.sum())} frame(s) {idx[bad][:5].tolist()}...; interpolated")
    return out
