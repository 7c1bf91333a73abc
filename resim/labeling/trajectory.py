"""World poses -> future ego trajectory in the ego frame (shard member ``traj.npy``)."""
from __future__ import annotations

import numpy as np


def wrap_angle(a):
    """Wrap radians to [-pi, pi]."""
    return np.arctan2(np.sin(a), np.cos(a))


def trajectory_from_poses(poses: np.ndarray, t_index: int, fps_hz: float, num_waypoints: int = 8,
                          waypoint_dt_s: float = 0.5) -> np.ndarray:
    """Future waypoints relative to the pose at ``t_index``.

    poses: (N, 3) float [x m, y m, yaw rad] in a right-handed world frame, yaw CCW (left +).
    Returns (num_waypoints, 3) float32: x forward m, y left m, yaw rad (left +, wrapped to [-pi, pi]),
    at ``waypoint_dt_s, 2*waypoint_dt_s, ...`` seconds after ``t_index`` (ReSim: 8 at 2 Hz = 0.5..4 s).
    Waypoint times that fall between frames are linearly interpolated (yaw unwrapped first).
    Raises ValueError when the poses do not reach the last waypoint.
    """
    p = np.asarray(poses, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"poses must have shape (N, 3), got {p.shape}")
    if fps_hz <= 0 or waypoint_dt_s <= 0 or num_waypoints < 1:
        raise ValueError("fps_hz, waypoint_dt_s and num_waypoints must be positive")
    if not 0 <= t_index < len(p):
        raise ValueError(f"t_index {t_index} outside poses of length {len(p)}")
    times = t_index + np.arange(1, num_waypoints + 1) * waypoint_dt_s * fps_hz  # fractional frame indices
    if times[-1] > len(p) - 1 + 1e-6:
        raise ValueError(
            f"poses end at frame {len(p) - 1} but the last waypoint needs frame {times[-1]:.2f} "
            f"({num_waypoints} x {waypoint_dt_s} s at {fps_hz} Hz after frame {t_index})")
    yaw = np.unwrap(p[:, 2])
    idx = np.arange(len(p))
    x = np.interp(times, idx, p[:, 0])
    y = np.interp(times, idx, p[:, 1])
    a = np.interp(times, idx, yaw)
    x0, y0, a0 = p[t_index, 0], p[t_index, 1], yaw[t_index]
    dx, dy = x - x0, y - y0
    c, s = np.cos(a0), np.sin(a0)
    out = np.stack([c * dx + s * dy, -s * dx + c * dy, wrap_angle(a - a0)], axis=1)
    return out.astype(np.float32)
