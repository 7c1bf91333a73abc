"""Fixtures for labeling tests: a tiny pinhole renderer of a textured ground plane with posts.

The renderer is deliberately independent of resim/labeling/flow.py: it ray-casts the ground
plane per pixel (x forward, y left world frame, yaw left +) and paints posts as
depth-ordered strips, so a sign or scale error in the estimator cannot cancel here.
"""
from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]


def render_drive(num_frames: int, fps_hz: float, yaw_rate_deg_s, speed_mps: float = 10.0,
                 size_hw: tuple[int, int] = (144, 256), hfov_deg: float = 70.0, cam_height_m: float = 1.5,
                 seed: int = 0, cam_forward_m: float = 0.0, cam_yaw_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Frames (T, H, W, 3) uint8 RGB of a car driving at constant speed, and poses (T, 3).

    ``yaw_rate_deg_s``: one rate, or (T-1,) rates per step. The car moves on arcs (chord along the mean
    heading); the camera sits ``cam_forward_m`` ahead of the pose point (the rear axle), so it also moves
    sideways in turns, and looks ``cam_yaw_deg`` left of the heading (a dashcam mounted askew).
    """
    import cv2

    rng = np.random.default_rng(seed)
    tex = rng.integers(0, 256, size=(256, 256), dtype=np.uint8)
    tex = cv2.GaussianBlur(tex, (0, 0), 1.2)
    tex = cv2.normalize(tex, None, 20, 230, cv2.NORM_MINMAX)
    texel_m = 0.25
    h, w = size_hw
    f = (w / 2) / math.tan(math.radians(hfov_deg) / 2)
    cx, cy = (w - 1) / 2, (h - 1) / 2
    cols, rows = np.meshgrid(np.arange(w), np.arange(h))
    X, Y = (cols - cx) / f, (rows - cy) / f         # camera ray (X right, Y down, Z=1 forward)
    ground = Y > 1e-3
    t = np.where(ground, cam_height_m / np.where(ground, Y, 1.0), 0.0)
    posts = [(float(d), float(s) * float(rng.uniform(4, 12))) for d in np.arange(8, 400, 9) for s in (-1, 1)]
    dt = 1.0 / fps_hz
    rates = np.broadcast_to(np.radians(np.asarray(yaw_rate_deg_s, np.float64)), (num_frames - 1,))
    poses = np.zeros((num_frames, 3))
    for i in range(1, num_frames):
        x, y, a = poses[i - 1]
        a_mid = a + rates[i - 1] * dt / 2
        poses[i] = (x + speed_mps * dt * math.cos(a_mid), y + speed_mps * dt * math.sin(a_mid),
                    a + rates[i - 1] * dt)
    frames = np.zeros((num_frames, h, w, 3), np.uint8)
    sky = np.linspace(200, 150, h)[:, None].repeat(w, 1)
    for i, (px, py, a) in enumerate(poses):
        px, py = px + cam_forward_m * math.cos(a), py + cam_forward_m * math.sin(a)
        a = a + math.radians(cam_yaw_deg)           # from here on: the camera's axes
        fwd, left = np.array([math.cos(a), math.sin(a)]), np.array([-math.sin(a), math.cos(a)])
        gx = px + t * (fwd[0] - X * left[0])        # world point of each ground pixel (right = -left)
        gy = py + t * (fwd[1] - X * left[1])
        img = cv2.remap(tex, (gx / texel_m).astype(np.float32), (gy / texel_m).astype(np.float32),
                        cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
        img = np.where(ground, img, sky).astype(np.uint8)
        # posts: world (d, s) along the initial x axis, 3 m tall, 0.3 m wide, far to near
        rel = [((pd - px) * fwd[0] + (ps - py) * fwd[1], -((pd - px) * left[0] + (ps - py) * left[1]), k)
               for k, (pd, ps) in enumerate(posts)]
        for Z, Xr, k in sorted(rel, reverse=True):
            if Z < 1.0:
                continue
            c0, hw = cx + f * Xr / Z, max(f * 0.15 / Z, 0.6)
            r_top, r_bot = cy + f * (cam_height_m - 3.0) / Z, cy + f * cam_height_m / Z
            a0, a1 = int(max(0, math.floor(c0 - hw))), int(min(w, math.ceil(c0 + hw)))
            b0, b1 = int(max(0, math.floor(r_top))), int(min(h, math.ceil(r_bot)))
            if a0 >= a1 or b0 >= b1:
                continue
            band = ((np.arange(b0, b1) - r_top) / (r_bot - r_top) * 6).astype(int) % 2
            img[b0:b1, a0:a1] = np.where(band[:, None] == 0, 40 + (k * 37) % 60, 235)
        frames[i] = np.repeat(img[:, :, None], 3, axis=2)
    return frames, poses


@pytest.fixture(scope="session")
def render():
    return render_drive


@pytest.fixture(scope="session")
def dashcam_dir() -> Path:
    """The real dashcam clips in ../shared/data/dashcam (RESIM_SHARED_DIR overrides ../shared)."""
    shared = Path(os.environ.get("RESIM_SHARED_DIR", REPO.parent / "shared"))
    d = shared / "data" / "dashcam"
    if not d.is_dir():
        pytest.skip(f"{d} is absent (real dashcam clips live in ../shared, which a user's clone has none of)")
    return d
