"""A small rendered ground-plane world with exact ego trajectories, written as real shards (for IDM tests/demos).

The project's synthetic world (``resim synth`` → ``resim pipeline run``) produces shards with trajectories
through the real layouts, at the cost of a pipeline run; this module renders clips itself, in a second, so
the IDM's tests can train and check it where the ground truth is exact (``PlaneWorldConfig``; not the
road world of ``pipelines/sources/synth``):

* a pinhole camera ``camera_height_m`` above a flat ground plane; every pixel below the horizon is
  intersected with the ground and coloured by a world-fixed texture (random colour per 4 m cell plus irregular
  cross stripes), fading to grey with distance (anti-aliasing at low resolution); above the horizon a panoramic
  skyline indexed by viewing direction, so yaw shows in the sky and speed in the ground flow;
* episodes drive with a piecewise-constant yaw rate and a smoothly varying speed (the constant-velocity
  baseline is wrong wherever the car turns or changes speed, as on real roads);
* clips of ``num_history_frames + num_future_frames`` frames every ``clip_stride_frames``; ``traj.npy`` =
  the 8 future waypoints (0.5 s steps) in the ego frame at the last history frame (x forward, y left, yaw
  left +), the convention of ``labeling.trajectory_from_poses``.

Shards are written with ``shards.writer.ShardWriter`` (schema-validated); latents are random placeholders
(``vae_placeholder`` true), since the IDM reads pixels only.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from resim.config import ConfigError, check_positive
from shards.schema import ClipSpec


@dataclass
class PlaneWorldConfig:
    episodes: int = 8
    frames_per_episode: int = 109
    fps_hz: float = 10.0
    frames_hw: tuple[int, int] = (32, 48)
    hfov_deg: float = 90.0
    camera_height_m: float = 1.5
    speed_range_mps: tuple[float, float] = (3.0, 12.0)
    max_yaw_rate_deg_s: float = 20.0
    clip_stride_frames: int = 10
    seed: int = 0

    def __post_init__(self):
        if self.episodes < 1:
            raise ConfigError(f"episodes must be >= 1, got {self.episodes}")
        if self.frames_per_episode < 1:
            raise ConfigError(f"frames_per_episode must be >= 1, got {self.frames_per_episode}")
        if self.clip_stride_frames < 1:   # range() would refuse a 0 step; negative ones give no clip
            raise ConfigError(f"clip_stride_frames must be >= 1, got {self.clip_stride_frames}")
        if min(self.frames_hw) < 2:
            raise ConfigError(f"frames_hw must be at least 2x2, got {self.frames_hw}")
        # math.isfinite: nan passes `<= 0` tests
        check_positive("fps_hz", self.fps_hz)
        if not (math.isfinite(self.hfov_deg) and 0 < self.hfov_deg < 180):
            raise ConfigError(f"hfov_deg must be in (0, 180), got {self.hfov_deg}")
        if not (math.isfinite(self.camera_height_m) and self.camera_height_m > 0):
            raise ConfigError(f"camera_height_m must be a finite number > 0, got {self.camera_height_m}")
        lo, hi = self.speed_range_mps
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo <= hi):
            raise ConfigError(f"speed_range_mps must be finite with 0 <= low <= high, got {self.speed_range_mps}")
        if not (math.isfinite(self.max_yaw_rate_deg_s) and self.max_yaw_rate_deg_s >= 0):
            raise ConfigError(f"max_yaw_rate_deg_s must be a finite number >= 0, got {self.max_yaw_rate_deg_s}")


def check_fits(cfg: PlaneWorldConfig, spec: ClipSpec) -> int:
    """Clips per episode; ConfigError when an episode is shorter than one clip (it would write 0 clips and
    look like success) or the spec's fps differs from the world's (the waypoints would be misplaced)."""
    if spec.fps_hz != cfg.fps_hz:
        raise ConfigError(f"the clip spec's fps_hz {spec.fps_hz} differs from the world's {cfg.fps_hz}")
    if cfg.frames_per_episode < spec.num_frames:
        raise ConfigError(f"frames_per_episode {cfg.frames_per_episode} is shorter than one clip of "
                          f"{spec.num_frames} frames ({spec.num_history_frames} history + {spec.num_future_frames} "
                          "future): no clip would be written")
    return len(range(0, cfg.frames_per_episode - spec.num_frames + 1, cfg.clip_stride_frames))


def episode_poses(cfg: PlaneWorldConfig, rng: np.random.Generator) -> np.ndarray:
    """(N, 3) world poses x, y, yaw at ``fps_hz``: piecewise-constant yaw rate, smoothly varying speed."""
    n, dt = cfg.frames_per_episode, 1.0 / cfg.fps_hz
    lo, hi = cfg.speed_range_mps
    speed = np.empty(n)
    v = rng.uniform(lo, hi)
    target = rng.uniform(lo, hi)
    rate = np.empty(n)
    r = 0.0
    for i in range(n):
        if rng.random() < 0.04:
            target = rng.uniform(lo, hi)
        v += np.clip(target - v, -2.5 * dt, 2.5 * dt)   # |accel| <= 2.5 m/s^2
        speed[i] = v
        if rng.random() < 0.05:
            r = np.deg2rad(rng.choice([0.0, 0.0, 1.0, -1.0]) * rng.uniform(5, cfg.max_yaw_rate_deg_s))
        rate[i] = r
    yaw = np.concatenate([[rng.uniform(-np.pi, np.pi)], np.cumsum(rate[:-1] * dt)])
    yaw[1:] += yaw[0]
    x = np.concatenate([[0.0], np.cumsum(speed[:-1] * np.cos(yaw[:-1]) * dt)])
    y = np.concatenate([[0.0], np.cumsum(speed[:-1] * np.sin(yaw[:-1]) * dt)])
    return np.stack([x, y, yaw], -1)


def future_waypoints(poses: np.ndarray, t_index: int, fps_hz: float, num_waypoints: int = 8,
                     waypoint_dt_s: float = 0.5) -> np.ndarray:
    """(N, 3) float32 waypoints in the ego frame at ``t_index`` (x fwd, y left, yaw left +, wrapped)."""
    x0, y0, th0 = poses[t_index]
    c, s = np.cos(th0), np.sin(th0)
    out = []
    for k in range(1, num_waypoints + 1):
        j = t_index + int(round(k * waypoint_dt_s * fps_hz))
        dx, dy = poses[j, 0] - x0, poses[j, 1] - y0
        dyaw = (poses[j, 2] - th0 + np.pi) % (2 * np.pi) - np.pi
        out.append((c * dx + s * dy, -s * dx + c * dy, dyaw))
    return np.asarray(out, np.float32)


class GroundRenderer:
    """Renders (H, W, 3) uint8 RGB views of the textured ground plane + skyline for world poses."""

    def __init__(self, cfg: PlaneWorldConfig, texture_seed: int = 0):
        h, w = cfg.frames_hw
        rng = np.random.default_rng(texture_seed)
        self.cells = rng.integers(60, 200, size=(64, 64, 3)).astype(np.float32)   # one colour per 4 m cell
        self.stripes = rng.random(257) < 0.3                                    # irregular cross stripes (1 m)
        # buildings 6 degrees wide (wider than a pixel's ~2 degrees, so yaw shifts them without aliasing)
        self.skyline = np.repeat(rng.integers(0, 3, size=60), 6)  # building height per degree of azimuth
        self.sky_col = np.repeat(rng.integers(90, 200, size=(60, 3)), 6, axis=0).astype(np.float32)
        self.f = (w / 2) / np.tan(np.deg2rad(cfg.hfov_deg) / 2)
        self.cx, self.cy = (w - 1) / 2, (h - 1) / 2
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        below = v > self.cy + 0.5
        dv = np.where(below, v - self.cy, 1.0)
        self.below = below
        self.fwd = np.where(below, self.f * cfg.camera_height_m / dv, 0.0)     # metres ahead
        self.left = -(u - self.cx) * self.fwd / self.f                         # metres to the left
        self.az = np.arctan2(-(u - self.cx), self.f)                            # viewing azimuth, left +
        self.elev = (self.cy - v) / h                                           # 0 at horizon, up +
        self.fog = np.clip(1.0 - self.fwd / 40.0, 0.0, 1.0)[..., None]

    def render(self, pose: np.ndarray) -> np.ndarray:
        x0, y0, th = pose
        c, s = np.cos(th), np.sin(th)
        wx = x0 + c * self.fwd - s * self.left
        wy = y0 + s * self.fwd + c * self.left
        cell = self.cells[np.floor(wx / 4.0).astype(np.int64) % 64, np.floor(wy / 4.0).astype(np.int64) % 64]
        stripe = self.stripes[np.floor(wx).astype(np.int64) % 257][..., None] * 40.0
        ground = self.fog * (cell + stripe) + (1 - self.fog) * 128.0
        deg = np.floor(np.rad2deg(th + self.az)).astype(np.int64) % 360
        building = self.elev < (self.skyline[deg] + 1) * 0.12
        sky = np.where(building[..., None], self.sky_col[deg], np.array([150.0, 190.0, 235.0]))
        img = np.where(self.below[..., None], ground, sky)
        return np.clip(img, 0, 255).astype(np.uint8)


def make_clips(cfg: PlaneWorldConfig, spec: ClipSpec | None = None) -> list[dict]:
    """Clips ``{"item_id", "start_frame", "frames" (T, H, W, 3) uint8, "traj" (8, 3), "yaw_deg"}``."""
    spec = spec or ClipSpec(fps_hz=cfg.fps_hz)
    rng = np.random.default_rng(cfg.seed)
    renderer = GroundRenderer(cfg, texture_seed=cfg.seed)
    horizon = int(round(spec.num_waypoints * spec.waypoint_dt_s * spec.fps_hz))
    if horizon > spec.num_future_frames:
        raise ValueError(f"waypoints span {horizon} frames, the clip's future only {spec.num_future_frames}")
    check_fits(cfg, spec)
    clips = []
    for e in range(cfg.episodes):
        poses = episode_poses(cfg, rng)
        frames = np.stack([renderer.render(p) for p in poses])
        item = f"synthetic-eval/episode-{cfg.seed:03d}-{e:03d}"
        for start in range(0, cfg.frames_per_episode - spec.num_frames + 1, cfg.clip_stride_frames):
            anchor = start + spec.num_history_frames - 1
            traj = future_waypoints(poses, anchor, spec.fps_hz, spec.num_waypoints, spec.waypoint_dt_s)
            clips.append({"item_id": item, "start_frame": start, "frames": frames[start:start + spec.num_frames],
                          "traj": traj, "yaw_deg": float(np.rad2deg(traj[-1, 2]))})
    return clips


def write_synthetic_shards(root: str | Path, cfg: PlaneWorldConfig, spec: ClipSpec | None = None,
                           prefix: str = "synth-eval", latent_channels: int = 16, latent_hw: tuple[int, int] = (8, 12),
                           text_len: int = 16, text_dim: int = 64) -> int:
    """Render ``cfg.episodes`` episodes and write their clips as shards (+ a placeholder prompt table).

    Latent and prompt shapes default to the ``tiny`` world model's (16 x 8 x 12 latents, 16 x 64 prompts),
    so the same shards drive the world-model evaluations in tests and the demo."""
    from shards.testing import add_dummy_prompts, make_dummy_sample
    from shards.video import encode_mp4
    from shards.writer import ShardWriter

    spec = spec or ClipSpec(fps_hz=cfg.fps_hz)
    clips = make_clips(cfg, spec)
    add_dummy_prompts(root, seq_len=text_len, dim=text_dim, seed=cfg.seed)
    with ShardWriter(root, prefix, max_samples_per_shard=64, config_hash=f"synth-eval-{cfg.seed}") as w:
        for i, c in enumerate(clips):
            yaw = c["yaw_deg"]
            command = "Turning left" if yaw > 15 else "Turning right" if yaw < -15 else "Moving forward"
            s = make_dummy_sample("synthetic", c["item_id"], c["start_frame"], command=command, yaw_deg=yaw,
                                  seed=cfg.seed * 100_000 + i, spec=spec, frames_hw=cfg.frames_hw,
                                  latent_channels=latent_channels, latent_hw=latent_hw)
            s["frames.mp4"] = encode_mp4(c["frames"], spec.fps_hz)
            s["traj.npy"] = c["traj"]
            s["meta.json"].update(command_flow=None, commands_agree=None, yaw_deg_flow=None, confidence=1.0,
                                  command_source="trajectory")
            w.write(s)
    w.close()
    return len(clips)
