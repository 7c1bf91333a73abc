"""Reading the synthetic world's ground truth (``ground_truth.json``).

``ground_truth.json`` has one entry per episode with simulation-rate arrays
``t_s, x_m, y_m, yaw_rad`` (unwrapped, CCW, left +), ``speed_mps``, the outcome,
and ``layout = {reader, item_id, reader_stride}``: frame k of the episode as the
named reader yields it is simulation step ``k * reader_stride``. So

    gt = GroundTruth.load(DIR)
    yaw = gt.yaw_for("opendv", item_id)          # (num_reader_frames,) rad, aligned with Episode frames
    dyaw = gt.heading_change_deg("opendv", item_id, start=0, num_frames=40)

gives the exact heading the labeler calibrates against.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

TURN_THRESHOLD_DEG = 15.0   # |heading change over a window| above this counts as a turn (for the share)
SHARE_WINDOW_S = 4.0        # ReSim's future window: 40 frames at 10 Hz


@dataclass
class GroundTruth:
    data: dict

    @classmethod
    def load(cls, root: str | Path) -> "GroundTruth":
        return cls(json.loads((Path(root) / "ground_truth.json").read_text(encoding="utf-8")))

    @property
    def episodes(self) -> list[dict]:
        return self.data["episodes"]

    def entry(self, reader: str, item_id: str) -> dict:
        for e in self.episodes:
            if e["layout"]["reader"] == reader and e["layout"]["item_id"] == item_id:
                return e
        raise KeyError(f"no ground truth for {reader}:{item_id}")

    def _aligned(self, reader: str, item_id: str, key: str) -> np.ndarray:
        e = self.entry(reader, item_id)
        return np.asarray(e[key], dtype=np.float64)[:: e["layout"]["reader_stride"]]

    def yaw_for(self, reader: str, item_id: str) -> np.ndarray:
        """Heading (rad, left +, unwrapped) per reader frame."""
        return self._aligned(reader, item_id, "yaw_rad")

    def poses_for(self, reader: str, item_id: str) -> np.ndarray:
        """(num_reader_frames, 3) x, y, yaw."""
        return np.stack([self._aligned(reader, item_id, k) for k in ("x_m", "y_m", "yaw_rad")], -1)

    def heading_change_deg(self, reader: str, item_id: str, start: int, num_frames: int) -> float:
        """Heading change (deg, left +) from reader frame ``start`` to ``start + num_frames - 1``."""
        yaw = self.yaw_for(reader, item_id)
        return math.degrees(yaw[start + num_frames - 1] - yaw[start])


def window_commands(yaw_rad: np.ndarray, fps_hz: float, window_s: float = SHARE_WINDOW_S,
                    threshold_deg: float = TURN_THRESHOLD_DEG) -> np.ndarray:
    """For every start frame with a full window: 'left' / 'straight' / 'right' by heading change."""
    n = int(round(window_s * fps_hz))
    if len(yaw_rad) <= n:
        return np.array([], dtype=object)
    d = np.degrees(yaw_rad[n:] - yaw_rad[:-n])
    return np.where(d > threshold_deg, "left", np.where(d < -threshold_deg, "right", "straight"))


def command_share(episodes: list[dict]) -> dict:
    """Share of left / straight / right 4 s windows (all start frames at 10 Hz) over the expert episodes."""
    counts = {"left": 0, "straight": 0, "right": 0}
    for e in episodes:
        if e["driver"] != "expert":
            continue
        stride = max(1, int(round(e["sim_hz"] / 10.0)))
        yaw = np.asarray(e["yaw_rad"])[::stride]
        for c in window_commands(yaw, 10.0):
            counts[str(c)] += 1
    total = sum(counts.values())
    return {"window_s": SHARE_WINDOW_S, "threshold_deg": TURN_THRESHOLD_DEG, "windows": total,
            **{k: (v / total if total else 0.0) for k, v in counts.items()}}
