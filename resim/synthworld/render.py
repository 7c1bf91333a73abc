"""A cheap pinhole-camera renderer for the synthetic world.

Per frame (numpy + OpenCV, no GPU):

* ground: every pixel below the horizon is intersected with the ground plane
  (depth depends only on the pixel row, so the ray table is built once), then
  looked up in a top-down texture of the world (grass noise, asphalt, lane
  markings) with ``cv2.remap``; a blurred copy is used far away (anti-aliasing),
  and a fine detail tile (``BORDER_WRAP``) adds texture near the camera so that
  optical flow has something to track;
* sky: a vertical gradient plus a distant hill silhouette that depends only on
  the azimuth (it moves with pure rotation, like anything at infinity);
* scenery: trees/bushes/posts as billboards and cars as shaded boxes, painted
  far to near; fog blends everything towards the horizon colour by
  ``exp(-depth / visibility)``, and a brightness factor sets the time of day.

The camera sits ``CAM_FORWARD_M`` ahead of the pose point at ``CAM_HEIGHT_M``,
looking along the pose yaw with zero pitch and roll, so the camera heading *is*
the pose heading (the ground truth the labeler calibrates against).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from .world import (DS_M, INTERSECTION_CLEAR_M, LANE_OFFSET_M, PROP_BUSH, PROP_POST, PROP_TREE,
                    ROAD_HALF_WIDTH_M, World)

CAM_HEIGHT_M = 1.5
CAM_FORWARD_M = 1.0
NEAR_M = 1.2
FAR_M = 120.0
MAP_RES_M = 0.2           # metres per texel of the top-down texture
DETAIL_RES_M = 0.03       # metres per texel of the fine detail tile
MAP_MARGIN_M = 60.0


@dataclass(frozen=True)
class Camera:
    height_px: int
    width_px: int
    hfov_deg: float = 80.0
    horizon_frac: float = 0.42   # horizon row / height (a dashcam tilted slightly down)

    @property
    def f_px(self) -> float:
        return self.width_px / 2 / math.tan(math.radians(self.hfov_deg) / 2)

    @property
    def cx(self) -> float:
        return (self.width_px - 1) / 2

    @property
    def cy(self) -> float:
        return self.horizon_frac * self.height_px

    def intrinsic(self) -> np.ndarray:
        return np.array([[self.f_px, 0, self.cx], [0, self.f_px, self.cy], [0, 0, 1.0]])


def _noise(rng: np.random.Generator, h: int, w: int, octaves=(4, 16, 64), weights=(0.5, 0.3, 0.2)) -> np.ndarray:
    """Smooth multi-octave value noise in [0, 1], (h, w) float32."""
    out = np.zeros((h, w), np.float32)
    for cells, wt in zip(octaves, weights):
        small = rng.random((max(2, h // cells), max(2, w // cells)), dtype=np.float32)
        out += wt * cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
    return np.clip(out, 0, 1)


class Renderer:
    """Renders frames of one world; heavy set-up (textures, ray table) in ``__init__``."""

    def __init__(self, world: World, camera: Camera, rng: np.random.Generator):
        self.world, self.cam = world, camera
        self._build_map(rng)
        self._build_rays()
        a = world.appearance
        self.horizon_rgb = np.array(a.sky_horizon_rgb, np.float32)
        phases = rng.uniform(0, 2 * math.pi, 4)
        amps = rng.uniform(0.3, 1.2, 4)
        self._hills = (phases, amps)

    # -- set-up ---------------------------------------------------------------------------------
    def _build_map(self, rng):
        w = self.world
        pts = np.concatenate([r.xy for r in w.roads])
        lo, hi = pts.min(0) - MAP_MARGIN_M, pts.max(0) + MAP_MARGIN_M
        res = MAP_RES_M
        size = np.ceil((hi - lo) / res).astype(int)
        while size.max() > 4096:  # cap memory on very long routes
            res *= 1.25
            size = np.ceil((hi - lo) / res).astype(int)
        self.map_lo, self.map_hi, self.map_res = lo, hi, res
        W, H = int(size[0]), int(size[1])
        a = w.appearance
        n = _noise(rng, H, W, octaves=(64, 16, 4), weights=(0.45, 0.35, 0.2))
        n = (0.85 * n + 0.15 * rng.random((H, W), dtype=np.float32))[..., None]
        grass = np.array(a.grass2_rgb, np.float32) + (np.array(a.grass_rgb, np.float32)
                                                      - np.array(a.grass2_rgb, np.float32)) * n
        road_mask = np.zeros((H, W), np.uint8)
        px = lambda xy: np.round(np.c_[(xy[:, 0] - lo[0]) / res, (hi[1] - xy[:, 1]) / res]).astype(np.int32)  # noqa
        self._to_px = px
        road_w = int(round(2 * ROAD_HALF_WIDTH_M / res))
        for r in w.roads:
            cv2.polylines(road_mask, [px(r.xy)], False, 255, thickness=road_w)
        asphalt = a.asphalt_gray * (0.85 + 0.3 * _noise(rng, H, W, octaves=(32, 8, 2), weights=(0.3, 0.3, 0.4)))
        # a dirt shoulder just outside the road
        shoulder = np.zeros((H, W), np.uint8)
        for r in w.roads:
            cv2.polylines(shoulder, [px(r.xy)], False, 255, thickness=road_w + int(round(2.4 / res)))
        img = grass
        sh = (shoulder > 0) & (road_mask == 0)
        img[sh] = img[sh] * 0.5 + np.array([120, 105, 80], np.float32) * 0.5
        rm = road_mask > 0
        img[rm] = asphalt[rm][:, None]
        # lane markings: solid white edges, dashed centre line, none inside intersections
        thick = max(1, int(round(0.15 / res)))
        centres = w.intersections
        for r in w.roads:
            clear = np.ones(len(r.xy), bool)
            if len(centres):
                clear = np.sqrt(((r.xy[:, None] - centres[None]) ** 2).sum(-1)).min(1) > INTERSECTION_CLEAR_M
            for lat in (-ROAD_HALF_WIDTH_M + 0.25, ROAD_HALF_WIDTH_M - 0.25):
                for run in _runs(clear):
                    cv2.polylines(img, [px(r.offset(lat)[run])], False, (235, 235, 235), thickness=thick)
            dash = clear & ((r.s % 9.0) < 3.0)
            for run in _runs(dash):
                cv2.polylines(img, [px(r.xy[run])], False, a.centre_line_rgb, thickness=thick)
        self.map_near = np.clip(img, 0, 255).astype(np.uint8)
        self.map_far = cv2.GaussianBlur(self.map_near, (0, 0), 2.5)
        tile = _noise(rng, 256, 256, octaves=(32, 8, 2), weights=(0.3, 0.3, 0.4))
        self.detail = (0.75 + 0.5 * tile).astype(np.float32)

    def _build_rays(self):
        c = self.cam
        H, W = c.height_px, c.width_px
        v = np.arange(H, dtype=np.float64)[:, None] + 0.5
        u = np.arange(W, dtype=np.float64)[None, :]
        dv = v - c.cy
        ground = dv > 0.5
        z = np.where(ground, c.f_px * CAM_HEIGHT_M / np.maximum(dv, 0.5), FAR_M)
        z = np.minimum(z, FAR_M)
        z = np.broadcast_to(z, (H, W))
        x = (u - c.cx) * z / c.f_px                      # metres to the right
        self.r0 = int(np.argmax(ground[:, 0]))            # first ground row
        r0 = self.r0
        self.ray_z, self.ray_x = z[r0:].astype(np.float32), x[r0:].astype(np.float32)
        self.far_w = np.clip((self.ray_z - 12.0) / 25.0, 0, 1)[..., None]
        self.detail_w = np.clip(1 - self.ray_z / 15.0, 0, 1)[..., None]
        self.fog_w = np.exp(-self.ray_z / self.world.appearance.fog_visibility_m)[..., None]
        self.az = np.arctan2(c.cx - u[0], c.f_px)        # azimuth of each column (left +)
        a = self.world.appearance
        rows = np.arange(r0, dtype=np.float32)[:, None]
        t = np.clip(1 - rows / max(c.cy, 1), 0, 1)[..., None]   # 0 at horizon, 1 at top
        sky = np.array(a.sky_horizon_rgb, np.float32) * (1 - t) + np.array(a.sky_zenith_rgb, np.float32) * t
        self.sky = np.ascontiguousarray(np.broadcast_to(sky, (r0, W, 3)))
        self.rows_sky = rows

    # -- per frame ------------------------------------------------------------------------------
    def render(self, pose: np.ndarray, t_s: float) -> np.ndarray:
        """RGB uint8 (H, W, 3) seen from pose (x, y, yaw) at time t_s."""
        c, w = self.cam, self.world
        a = w.appearance
        x0, y0, yaw = float(pose[0]), float(pose[1]), float(pose[2])
        cy_, sy_ = math.cos(yaw), math.sin(yaw)
        camx, camy = x0 + CAM_FORWARD_M * cy_, y0 + CAM_FORWARD_M * sy_
        wx = camx + self.ray_z * cy_ + self.ray_x * sy_
        wy = camy + self.ray_z * sy_ - self.ray_x * cy_
        mu = ((wx - self.map_lo[0]) / self.map_res).astype(np.float32)
        mv = ((self.map_hi[1] - wy) / self.map_res).astype(np.float32)
        near = cv2.remap(self.map_near, mu, mv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        far = cv2.remap(self.map_far, mu, mv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        img = near.astype(np.float32) * (1 - self.far_w) + far.astype(np.float32) * self.far_w
        du = (wx / DETAIL_RES_M).astype(np.float32) % 256
        dv = (wy / DETAIL_RES_M).astype(np.float32) % 256
        det = cv2.remap(self.detail, du, dv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)[..., None]
        img *= 1 + (det - 1) * self.detail_w
        img = img * self.fog_w + self.horizon_rgb * (1 - self.fog_w)
        img = np.concatenate([self._sky(yaw), img], axis=0)
        img = np.clip(img, 0, 255).astype(np.uint8)
        self._draw_objects(img, camx, camy, yaw, t_s)
        out = img.astype(np.float32) * a.brightness
        return np.clip(out, 0, 255).astype(np.uint8)

    def _sky(self, yaw: float) -> np.ndarray:
        """Sky rows (above the first ground row): gradient plus an azimuth-fixed hill silhouette."""
        c, a = self.cam, self.world.appearance
        phases, amps = self._hills
        az = yaw + self.az                                                  # world azimuth of each column
        elev = sum(amps[i] * (1 + np.sin((i + 2) * az + phases[i])) for i in range(4)) * 0.9  # degrees
        top = c.cy - c.f_px * np.tan(np.radians(elev))                      # hill top row per column
        hill = self.rows_sky >= top[None, :]
        hills_rgb = np.array(a.hills_rgb, np.float32) * 0.6 + self.horizon_rgb * 0.4
        return np.where(hill[..., None], hills_rgb, self.sky)

    def _project(self, pts_xy: np.ndarray, camx, camy, yaw):
        """World ground points (N, 2) -> camera depth z (fwd) and lateral x (right)."""
        dx, dy = pts_xy[:, 0] - camx, pts_xy[:, 1] - camy
        cy_, sy_ = math.cos(yaw), math.sin(yaw)
        return dx * cy_ + dy * sy_, dx * sy_ - dy * cy_

    def _draw_objects(self, img: np.ndarray, camx, camy, yaw, t_s):
        c, w = self.cam, self.world
        f, cx, cy = c.f_px, c.cx, c.cy
        fogv = w.appearance.fog_visibility_m
        items = []  # (depth, kind, payload)
        p = w.props
        if len(p.xy):
            z, x = self._project(p.xy, camx, camy, yaw)
            far = min(FAR_M, 3.0 * fogv)
            vis = (z > NEAR_M) & (z < far) & (np.abs(x) < z * 1.3 + 5) & (p.height_m * c.f_px > 1.5 * z)
            for i in np.flatnonzero(vis):
                items.append((float(z[i]), 0, i, float(x[i])))
        poses = w.car_poses(t_s)
        for j, (car, pose) in enumerate(zip(w.cars, poses)):
            z, x = self._project(pose[None, :2], camx, camy, yaw)
            if NEAR_M + 2.5 < z[0] < FAR_M and abs(x[0]) < z[0] * 1.5 + 10:
                items.append((float(z[0]), 1, j, float(x[0])))
        items.sort(key=lambda it: -it[0])
        for z, kind, i, x in items:
            fog = math.exp(-z / fogv)
            if kind == 0:
                self._billboard(img, i, z, x, fog)
            else:
                self._car(img, w.cars[i], poses[i], camx, camy, yaw, fog)

    def _billboard(self, img, i, z, x, fog):
        c, p = self.cam, self.world.props
        f, cx, cy = c.f_px, c.cx, c.cy
        hor = self.horizon_rgb
        u = cx + f * x / z
        vb = cy + f * CAM_HEIGHT_M / z
        h_px = f * p.height_m[i] / z
        w_px = max(1.0, f * p.width_m[i] / z)
        col = tuple(float(v) for v in (p.rgb[i] * fog + hor * (1 - fog)))
        k = p.kind[i]
        if k == PROP_TREE:
            trunk = tuple(float(v) for v in (np.array([90, 65, 40]) * fog + hor * (1 - fog)))
            tw = max(1, int(round(f * 0.35 / z)))
            cv2.rectangle(img, (int(u - tw / 2), int(vb - h_px * 0.5)), (int(u + tw / 2), int(vb)), trunk, -1)
            cv2.ellipse(img, (int(round(u)), int(round(vb - h_px * 0.65))),
                        (max(1, int(w_px / 2)), max(1, int(h_px * 0.35))), 0, 0, 360, col, -1)
            dark = tuple(v * 0.75 for v in col)
            cv2.ellipse(img, (int(round(u + w_px * 0.1)), int(round(vb - h_px * 0.55))),
                        (max(1, int(w_px / 3)), max(1, int(h_px * 0.2))), 0, 0, 360, dark, -1)
        elif k == PROP_BUSH:
            cv2.ellipse(img, (int(round(u)), int(round(vb - h_px * 0.45))),
                        (max(1, int(w_px / 2)), max(1, int(h_px * 0.5))), 0, 0, 360, col, -1)
        else:  # post: white with a red band
            pw = max(1, int(round(w_px)))
            cv2.rectangle(img, (int(u - pw / 2), int(vb - h_px)), (int(u + pw / 2), int(vb)), col, -1)
            red = tuple(float(v) for v in (np.array([200, 30, 30]) * fog + hor * (1 - fog)))
            cv2.rectangle(img, (int(u - pw / 2), int(vb - h_px)), (int(u + pw / 2), int(vb - h_px * 0.8)), red, -1)

    def _car(self, img, car, pose, camx, camy, yaw, fog):
        c = self.cam
        f, cx, cy = c.f_px, c.cx, c.cy
        L, Wd, Hh = car.length_m / 2, car.width_m / 2, car.height_m
        ch, sh = math.cos(pose[2]), math.sin(pose[2])
        corners = np.array([[L, Wd], [L, -Wd], [-L, -Wd], [-L, Wd]])
        gxy = pose[:2] + corners @ np.array([[ch, sh], [-sh, ch]])
        z, x = self._project(gxy, camx, camy, yaw)
        if (z < NEAR_M).any():
            return
        u = cx + f * x / z
        vb = cy + f * CAM_HEIGHT_M / z
        vt = cy + f * (CAM_HEIGHT_M - Hh) / z
        base = np.array(car.rgb, np.float32) * fog + self.horizon_rgb * (1 - fog)
        P = lambda i, top: (u[i], vt[i] if top else vb[i])  # noqa: E731
        faces = []
        for a_, b_ in ((0, 1), (1, 2), (2, 3), (3, 0)):        # sides: front, right, back, left
            quad = [P(a_, 0), P(b_, 0), P(b_, 1), P(a_, 1)]
            depth = (z[a_] + z[b_]) / 2
            faces.append((depth, quad, 0.7 if (a_, b_) in ((0, 1), (2, 3)) else 0.85))
        faces.sort(key=lambda fc: -fc[0])
        for depth, quad, shade in faces:
            cv2.fillConvexPoly(img, np.round(np.array(quad)).astype(np.int32), tuple(float(v) for v in base * shade))
        top = np.round(np.array([P(i, 1) for i in range(4)])).astype(np.int32)
        cv2.fillConvexPoly(img, cv2.convexHull(top), tuple(float(v) for v in np.minimum(base * 1.15, 255)))
        # a dark window band on the nearest end face
        near_end = (2, 3) if (z[2] + z[3]) < (z[0] + z[1]) else (0, 1)
        i, j = near_end
        vm = lambda k, fr: vb[k] + (vt[k] - vb[k]) * fr  # noqa: E731
        band = np.array([(u[i], vm(i, 0.95)), (u[j], vm(j, 0.95)), (u[j], vm(j, 0.65)), (u[i], vm(i, 0.65))])
        cv2.fillConvexPoly(img, np.round(band).astype(np.int32), tuple(float(v) for v in base * 0.3 + 20))


def _runs(mask: np.ndarray) -> list[slice]:
    """Slices of consecutive True runs (length >= 2) in a boolean array."""
    m = np.r_[False, mask, False].astype(np.int8)
    d = np.diff(m)
    starts, stops = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    return [slice(a, b) for a, b in zip(starts, stops) if b - a >= 2]


__all__ = ["Camera", "Renderer", "CAM_HEIGHT_M", "CAM_FORWARD_M", "LANE_OFFSET_M", "DS_M"]
