"""Precomputed DINOv2 features (``dino.npy``) for Video2Reward.

With a frozen backbone, running DINOv2 over every frame every epoch is waste: features of the frames the model's window takes from a clip are
computed once, stored as float16 ``(T, N_tokens, D)`` in the sample's
``dino.npy`` member (resim/shards/schema.py), and named by ``meta.dino_id``
(backbone id | input size | window; see backbone.feature_id). The model rounds
its live backbone output to float16 as well (``feature_dtype``), so training on
stored features and through the backbone see the same numbers.
"""
from __future__ import annotations

import copy
import shutil
from pathlib import Path
from typing import Iterable, Iterator, Sequence

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import torch
from tqdm import tqdm

from resim.models.reward.model import Video2Reward
from resim.shards import layout
from resim.shards.reader import decode_sample, iter_raw_shard
from resim.shards.video import VideoError, decode_mp4
from resim.shards.writer import ShardWriter
from resim.train.tasks.reward.data import ClipError, RewardClip, frames_to_tensor, window_indices


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
        try:
            (d,) = features_for_frames(model, [c.clip_frames()], where)
        except ClipError as e:
            raise ClipError(f"clip {c.key}: {e}") from None
        out.append(RewardClip(key=c.key, item_id=c.item_id, infraction_score=c.infraction_score, hazard=c.hazard,
                              frames=c.frames, dino=d, dino_id=model.feature_id, mp4=c.mp4))
    return out


def add_sample_features(model: Video2Reward, sample: dict, where: str = "end") -> dict:
    """A shard sample (writer form: ``meta.json`` dict, ``frames.mp4`` bytes, ...) plus ``dino.npy``
    and ``meta.dino_id``. The input sample is not modified."""
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


def check_feature_paths(src_root, dst_root) -> list:
    """The committed shards of ``src_root``; ValueError naming the folder when it has none (or does not
    exist) or when ``dst_root`` is the same folder (the copy would overwrite its own source)."""
    src, dst = Path(src_root), Path(dst_root)
    if not src.is_dir():
        raise ValueError(f"{src}: no such dataset folder")
    if src.resolve() == dst.resolve():
        raise ValueError(f"output folder {dst} is the source dataset {src}: the features are written to a new "
                         "dataset, give another output folder")
    shards = layout.committed_shards(src)
    if not shards:
        raise ValueError(f"{src}: no committed shards (expected DIR/shards/*.tar with DIR/index/*.json)")
    return shards


def add_features_to_dataset(src_root, dst_root, model: Video2Reward, where: str = "end",
                            max_samples_per_shard: int = 1000, progress: bool = False) -> dict:
    """Copy the shard dataset ``src_root`` to ``dst_root`` with ``dino.npy`` + ``meta.dino_id`` added
    to every labelled sample (one with an infraction score; others are copied unchanged).

    Each source shard ``S.tar`` becomes ``dst/shards/S-00000.tar`` (its writer's prefix is the source
    shard's stem, so names never collide and a rerun reproduces the same bytes). The prompt table and
    config are copied. A labelled sample whose clip cannot be featurised (e.g. shorter than the model's
    window, unreadable frames.mp4) is copied without features and recorded in
    ``dst/quarantine/reward-features.parquet`` (item, source, stage, reason, attempts); the job goes on.
    Returns {"samples", "with_features", "quarantined", "shards", "dino_id", "dino_bytes_per_sample"}.
    """
    src, dst = Path(src_root), Path(dst_root)
    shards = check_feature_paths(src, dst)
    if layout.prompts_dir(src).is_dir():
        shutil.copytree(layout.prompts_dir(src), layout.prompts_dir(dst), dirs_exist_ok=True)
    if (src / "config.yaml").is_file():
        dst.mkdir(parents=True, exist_ok=True)
        shutil.copy2(src / "config.yaml", dst / "config.yaml")
    n = n_feat = 0
    dino_bytes = 0
    quarantine: list[dict] = []
    infos = []
    it = shards
    if progress:
        it = tqdm(shards, desc="dino features", unit="shard")
    for shard in it:
        with ShardWriter(dst, layout.stem(shard.name), max_samples_per_shard=max_samples_per_shard,
                         overwrite=True) as w:
            for raw in iter_raw_shard(shard):
                s = decode_sample(raw, latent_as="stored")
                s = {k: v for k, v in s.items() if k == "__key__" or not k.startswith("__")}
                n += 1
                meta = s["meta.json"]
                if meta.get("infraction_score") is not None:
                    try:
                        s = add_sample_features(model, s, where)
                        n_feat += 1
                        dino_bytes += s["dino.npy"].nbytes
                    except (ClipError, VideoError) as e:
                        quarantine.append({"item": s["__key__"], "source": meta.get("source", ""),
                                           "stage": "reward-features", "reason": str(e), "attempts": 1})
                w.write(s)
            infos.extend(w.close())
    if quarantine:
        layout.quarantine_dir(dst).mkdir(parents=True, exist_ok=True)
        tmp = layout.quarantine_dir(dst) / ".reward-features.parquet.tmp"
        pq.write_table(pa.Table.from_pylist(quarantine), tmp)
        tmp.replace(layout.quarantine_dir(dst) / "reward-features.parquet")
    return {"samples": n, "with_features": n_feat, "quarantined": len(quarantine), "shards": len(infos),
            "dino_id": model.feature_id, "dino_bytes_per_sample": dino_bytes / max(n_feat, 1)}
