"""Precomputed DINOv2 features (``dino.npy``) for Video2Reward.

With a frozen backbone, running DINOv2 over every frame every epoch is waste
(issue 8): features of the frames the model's window takes from a clip are
computed once, stored as float16 ``(T, N_tokens, D)`` in the sample's
``dino.npy`` member (shards/schema.py), and named by ``meta.dino_id``
(backbone id | input size | window; see backbone.feature_id). The model rounds
its live backbone output to float16 as well (``feature_dtype``), so training on
stored features and through the backbone see the same numbers.
"""
from __future__ import annotations

import copy
from typing import Iterable, Iterator, Sequence

import numpy as np
import torch

from training.reward.data import RewardClip, frames_to_tensor, window_indices
from training.reward.model import Video2Reward


@torch.no_grad()
def features_for_frames(model: Video2Reward, clips_frames: Sequence[np.ndarray], where: str = "end") -> list[np.ndarray]:
    """For each clip's frames (T_clip, H, W, 3) uint8, the model window's features (T, N, D) float16."""
    if not model.cfg.freeze_backbone:
        raise ValueError("stored features are only valid for a frozen backbone (freeze_backbone: true)")
    model.eval()
    vids = [frames_to_tensor(f[window_indices(len(f), model.cfg, where)]) for f in clips_frames]
    out = []
    for v in vids:  # one clip at a time: clips may differ in size; frames of a clip are one backbone batch
        feats = model.encode(v[None])[0]
        out.append(feats.to(torch.float16).cpu().numpy())
    return out


def add_clip_features(model: Video2Reward, clips: Iterable[RewardClip], where: str = "end") -> list[RewardClip]:
    """Copies of ``clips`` with ``dino``/``dino_id`` filled from their frames."""
    out = []
    for c in clips:
        if c.frames is None:
            raise ValueError(f"clip {c.key} has no frames to compute features from")
        (d,) = features_for_frames(model, [c.frames], where)
        out.append(RewardClip(key=c.key, item_id=c.item_id, infraction_score=c.infraction_score, hazard=c.hazard,
                              frames=c.frames, dino=d, dino_id=model.feature_id))
    return out


def add_sample_features(model: Video2Reward, sample: dict, where: str = "end") -> dict:
    """A shard sample (writer form: ``meta.json`` dict, ``frames.mp4`` bytes, ...) plus ``dino.npy``
    and ``meta.dino_id``. The input sample is not modified."""
    from shards.video import decode_mp4

    frames = sample["frames.mp4"]
    if isinstance(frames, (bytes, bytearray)):
        frames = decode_mp4(bytes(frames))
    (d,) = features_for_frames(model, [frames], where)
    out = dict(sample)
    out["meta.json"] = copy.deepcopy(sample["meta.json"])
    out["meta.json"]["dino_id"] = model.feature_id
    out["dino.npy"] = d
    return out


def iter_samples_with_features(model: Video2Reward, samples: Iterable[dict], where: str = "end") -> Iterator[dict]:
    for s in samples:
        yield add_sample_features(model, s, where)
