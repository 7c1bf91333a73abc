"""Clips of the synthetic road world (``resim synth``'s world, ``synthworld``) in memory and as
shards, for the evaluation tests: exact ego poses, no pipeline run. Tests may import the pipeline; the product's
evaluation code reads only the shards."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from resim.labeling.trajectory import trajectory_from_poses
from resim.pipeline.sources.synth.generate import preset, render_episode
from resim.shards.schema import ClipSpec
from tests.support.shards import add_dummy_prompts, make_dummy_sample
from resim.shards.video import encode_mp4
from resim.shards.writer import ShardWriter


def road_world_clips(episodes: int, frames_per_episode: int, *, seed: int = 0, frames_hw: tuple[int, int] = (32, 48),
                     clip_stride_frames: int = 10, spec: ClipSpec | None = None) -> list[dict]:
    """Clips ``{"item_id", "start_frame", "frames" (T, H, W, 3) uint8, "traj" (8, 3), "yaw_deg"}`` of expert
    drives of the road world; ``traj`` = the waypoints after the last history frame (labeling's convention)."""
    spec = spec or ClipSpec()
    cfg = preset("tiny", height_px=frames_hw[0], width_px=frames_hw[1], episode_s=frames_per_episode / spec.fps_hz)
    clips = []
    for e in range(episodes):
        frames, poses = render_episode(e, seed, cfg, spec.fps_hz)
        item = f"synth-road/s{seed}-{e:03d}"
        for start in range(0, len(frames) - spec.num_frames + 1, clip_stride_frames):
            anchor = start + spec.num_history_frames - 1
            traj = trajectory_from_poses(poses, anchor, spec.fps_hz, spec.num_waypoints, spec.waypoint_dt_s)
            clips.append({"item_id": item, "start_frame": start, "frames": frames[start:start + spec.num_frames],
                          "traj": traj, "yaw_deg": float(np.rad2deg(traj[-1, 2]))})
    assert clips, "no clip fits: frames_per_episode is shorter than one clip"   # the test's own mistake
    return clips


def write_road_world_shards(root: str | Path, episodes: int, frames_per_episode: int, *, seed: int = 0,
                            frames_hw: tuple[int, int] = (32, 48), clip_stride_frames: int = 10,
                            spec: ClipSpec | None = None, latent_channels: int = 16,
                            latent_hw: tuple[int, int] = (8, 12), text_len: int = 16, text_dim: int = 64) -> int:
    """Write the clips as shards (+ a placeholder prompt table); random latents (``vae_placeholder``) of the
    ``tiny`` world model's shape, the command from the recorded heading change (15 degrees)."""
    spec = spec or ClipSpec()
    clips = road_world_clips(episodes, frames_per_episode, seed=seed, frames_hw=frames_hw,
                             clip_stride_frames=clip_stride_frames, spec=spec)
    add_dummy_prompts(root, seq_len=text_len, dim=text_dim, seed=seed)
    with ShardWriter(root, "synth-road", max_samples_per_shard=64, config_hash=f"synth-road-{seed}") as w:
        for i, c in enumerate(clips):
            yaw = c["yaw_deg"]
            command = "Turning left" if yaw > 15 else "Turning right" if yaw < -15 else "Moving forward"
            s = make_dummy_sample("synthetic", c["item_id"], c["start_frame"], command=command, yaw_deg=yaw,
                                  seed=seed * 100_000 + i, spec=spec, frames_hw=frames_hw,
                                  latent_channels=latent_channels, latent_hw=latent_hw)
            s["frames.mp4"] = encode_mp4(c["frames"], spec.fps_hz)
            s["traj.npy"] = c["traj"]
            s["meta.json"].update(command_flow=None, commands_agree=None, yaw_deg_flow=None, confidence=1.0,
                                  command_source="trajectory")
            w.write(s)
    return len(clips)


@pytest.fixture(scope="session")
def road_world():
    """``road_world.clips(...)`` / ``road_world.write_shards(root, ...)``: see the functions above."""
    class _RoadWorld:
        clips = staticmethod(road_world_clips)
        write_shards = staticmethod(write_road_world_shards)
    return _RoadWorld
