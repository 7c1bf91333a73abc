"""Procedural toy clips for Video2Reward's unit tests and benchmark (NOT the synthetic world).

Each episode has an infraction score s in [0, 1] (1 = clean). Its frames show a
grey road under a sky, with an obstacle (a red box) ahead whose size grows over
the clip in proportion to (1 - s): hazardous episodes close in on the obstacle,
clean ones keep it small and far. Noise and a per-episode colour jitter keep
episodes apart. So the score is visible in the pixels, and a model that learns
anything at all can rank it; the real test set is the synthetic world of
``resim.pipeline.sources``.
"""
from __future__ import annotations

import numpy as np

from resim.train.tasks.reward.data import RewardClip


def toy_episode_frames(score: float, num_frames: int, h: int, w: int, rng: np.random.Generator) -> np.ndarray:
    """(num_frames, h, w, 3) uint8 RGB frames for an episode of infraction score ``score``."""
    yy = np.arange(h)[:, None]
    base = np.empty((h, w, 3), np.float32)
    base[:] = (0.55, 0.7, 0.9)                                      # sky
    base[yy[:, 0] >= h // 2] = (0.35, 0.35, 0.37)                    # road
    base += rng.normal(0, 0.03, 3).astype(np.float32)                # episode colour jitter
    danger = 1.0 - score
    cx = w / 2 + rng.uniform(-0.15, 0.15) * w
    frames = np.empty((num_frames, h, w, 3), np.float32)
    for t in range(num_frames):
        prog = t / max(num_frames - 1, 1)
        half = 0.04 * w + danger * prog * 0.35 * w                  # obstacle grows when approaching
        y0, y1 = int(h * 0.5 - half * 0.6), int(h * 0.5 + half)
        x0, x1 = int(cx - half), int(cx + half)
        f = base.copy()
        f[max(y0, 0):max(y1, 0), max(x0, 0):max(x1, 0)] = (0.85, 0.15, 0.1)
        frames[t] = f + rng.normal(0, 0.02, f.shape)
    return (np.clip(frames, 0, 1) * 255).round().astype(np.uint8)


def toy_clips(num_episodes: int, clips_per_episode: int, clip_frames: int, h: int = 32, w: int = 48,
              seed: int = 0, hazard_threshold: float = 0.7) -> list[RewardClip]:
    """Clips of ``num_episodes`` toy episodes (scores spread over [0, 1]); hazard = score < threshold."""
    rng = np.random.default_rng(seed)
    clips = []
    scores = rng.permutation(np.linspace(0.0, 1.0, num_episodes))
    stride = max(1, clip_frames // 2)
    for e, s in enumerate(scores):
        ep_len = clip_frames + stride * (clips_per_episode - 1)
        frames = toy_episode_frames(float(s), ep_len, h, w, rng)
        for c in range(clips_per_episode):
            start = c * stride
            clips.append(RewardClip(key=f"toy{e:03d}@{start}", item_id=f"toy/{e:03d}", infraction_score=float(s),
                                    hazard=bool(s < hazard_threshold), frames=frames[start:start + clip_frames]))
    return clips


def toy_split(clips, **cfg):
    """The dataset split (resim.shards.split) of in-memory clips, all of one source."""
    from resim.shards import split

    return split.of_episodes({c.item_id: ("carla", c.hazard) for c in clips}, split.SplitConfig(**cfg), "toy clips")
