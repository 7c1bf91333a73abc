"""Labelled clips for Video2Reward, its stratified held-out split by episode, and its batches.

A ``RewardClip`` is one training example: pixels (uint8 RGB, (T, H, W, 3)) and/or
stored DINOv2 features (``dino.npy``), its episode id and its infraction score.
Clips come from shard samples (``clips_from_samples``), from episode records of
``resim.pipeline.sources`` (``clips_from_episodes``), or from anything else that can
build the dataclass. Only clips with an infraction score are labelled (ReSim:
CARLA samples with their recorded Infraction Score).

The split is by episode (``item_id``), never by clip: overlapping clips of one
episode on both sides would leak. The split itself, the epoch shuffling and the
batched prediction are the small-model harness's (``resim.train.smallfit``), shared
with the IDM; the reward's own parts are its targets, its window and ``collate``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Iterable, Iterator, Sequence

import numpy as np
import torch

from resim.models.reward.config import RewardModelConfig
from resim.shards import safejson
from resim.shards.video import VideoError, decode_mp4
from resim.train import smallfit
# ClipError and frames_to_tensor are the small-model harness's (the IDM uses them too); imported under these
# names because the reward code, its CLI and benches use them from here
from resim.train.smallfit import ClipError, frames_to_tensor


@dataclass
class RewardClip:
    key: str
    item_id: str
    infraction_score: float
    hazard: bool
    frames: np.ndarray | None = None     # (T, H, W, 3) uint8 RGB, the whole clip
    dino: np.ndarray | None = None       # (T_dino, N, D) float16, the model's window only
    dino_id: str | None = None
    mp4: bytes | None = None             # encoded frames (frames.mp4), decoded on demand by clip_frames

    def clip_frames(self) -> np.ndarray:
        """(T, H, W, 3) uint8 RGB frames of the clip (decodes ``mp4`` on first use, then keeps them)."""
        if self.frames is None:
            if self.mp4 is None:
                raise ClipError(f"clip {self.key} has no frames")
            try:
                self.frames = decode_mp4(self.mp4)
            except VideoError as e:
                raise ClipError(f"clip {self.key}: frames.mp4 is unreadable: {e}") from e
        return self.frames


def window_indices(num_clip_frames: int, cfg: RewardModelConfig, where: str = "end", start: int | None = None) -> np.ndarray:
    """Indices of the ``cfg.num_frames`` frames (every ``cfg.frame_step``) one window takes from a clip.

    ``where="end"``: the last window of the clip (the imagined future); ``"start"``: the first;
    ``start`` overrides both. Raises ClipError when the clip is shorter than ``cfg.window_frames``.
    """
    w = cfg.window_frames
    if num_clip_frames < w:
        raise ClipError(f"clip has {num_clip_frames} frames, the model's window needs {w} "
                        f"({cfg.num_frames} frames every {cfg.frame_step})")
    if start is None:
        start = num_clip_frames - w if where == "end" else 0
    if not 0 <= start <= num_clip_frames - w:
        raise ClipError(f"window start {start} out of range for a {num_clip_frames}-frame clip")
    return start + cfg.frame_step * np.arange(cfg.num_frames)


def collate(clips: Sequence[RewardClip], cfg: RewardModelConfig, use_features: bool, where: str = "end"
            ) -> dict[str, Any]:
    """Batch for ``Video2Reward.loss``: ``{"infraction_score" (B,), "hazard" (B,), "keys", and
    "dino" (B, T, N, D) float32 + "dino_id" when use_features, else "video" (B, T, 3, H, W) [0, 1]}``.
    """
    batch: dict[str, Any] = {
        "infraction_score": torch.tensor([c.infraction_score for c in clips], dtype=torch.float32),
        "hazard": torch.tensor([bool(c.hazard) for c in clips]),
        "keys": [c.key for c in clips],
    }
    if use_features:
        missing = [c.key for c in clips if c.dino is None]
        if missing:
            raise ClipError(f"clip {missing[0]} has no stored features (dino.npy)")
        batch["dino"] = torch.from_numpy(np.stack([c.dino for c in clips]).astype(np.float32))
        batch["dino_id"] = [c.dino_id for c in clips]
    else:
        vids = []
        for c in clips:
            f = c.clip_frames()
            try:
                idx = window_indices(len(f), cfg, where)
            except ClipError as e:
                raise ClipError(f"clip {c.key}: {e}") from None
            vids.append(frames_to_tensor(f[idx]))
        shapes = {tuple(v.shape) for v in vids}
        if len(shapes) > 1:  # frames are resized by the model, but a batch must stack
            size = vids[0].shape[-2:]
            vids = [torch.nn.functional.interpolate(v, size=size, mode="bilinear", antialias=True) for v in vids]
        batch["video"] = torch.stack(vids)
    return batch


# ---- sources of clips ---------------------------------------------------------------------------

def clips_from_samples(samples: Iterable[dict]) -> Iterator[RewardClip]:
    """Labelled clips from decoded shard samples (``resim.shards.reader.decode_sample`` output:
    ``meta.json`` dict, ``frames.mp4`` bytes (decoded only when needed) or (T, H, W, 3) uint8,
    optional ``dino.npy``). Samples without an infraction score are skipped (no reward label).
    """
    for s in samples:
        meta = s.get("meta.json") or s.get("meta") or {}
        if isinstance(meta, (bytes, str)):
            meta = safejson.loads(meta)   # size and nesting limits: shard data is untrusted
        if meta.get("infraction_score") is None:
            continue
        key = meta.get("key") or s.get("__key__")
        frames = s.get("frames", s.get("frames.mp4"))
        mp4 = bytes(frames) if isinstance(frames, (bytes, bytearray)) else None
        frames = None if mp4 is not None else frames
        dino = s.get("dino.npy")
        if dino is not None and not meta.get("dino_id"):
            raise ClipError(f"sample {key}: dino.npy present but meta.dino_id is empty")
        yield RewardClip(key=key, item_id=meta["item_id"], infraction_score=float(meta["infraction_score"]),
                         hazard=bool(meta.get("hazard")), frames=frames, dino=dino, dino_id=meta.get("dino_id"),
                         mp4=mp4)


def clips_from_episode(ep: Any, clip_frames: int, stride_frames: int, size_hw: tuple[int, int] | None = None,
                       hold_last: bool = False) -> list[RewardClip]:
    """Cut one ``resim.pipeline.sources`` Episode (with an ``outcome``) into clips of ``clip_frames`` frames
    every ``stride_frames``; every clip carries the episode's infraction score. Returns [] without outcome.

    An episode shorter than ``clip_frames`` gives no clip, unless ``hold_last``: then its last frame is
    repeated up to ``clip_frames`` (one clip). Why: the synthetic world (and CARLA after a
    crash) ends an episode early when the ego has crashed and stopped for good; dropping those
    episodes would remove exactly the early-crash hazards, and a held last frame is what the stopped
    ego's camera would keep seeing. Such clips' keys end in ``+hold<N>`` (N = repeated frames).
    """
    if ep.outcome is None:
        return []
    frames = np.stack(list(ep.frames(0, None, size_hw=size_hw)))
    suffix = ""
    if hold_last and 0 < len(frames) < clip_frames:
        n = clip_frames - len(frames)
        frames = np.concatenate([frames, np.repeat(frames[-1:], n, axis=0)])
        suffix = f"+hold{n}"
    out = []
    for s in range(0, len(frames) - clip_frames + 1, stride_frames):
        out.append(RewardClip(key=f"{ep.item_id}@{s}{suffix}", item_id=ep.item_id,
                              infraction_score=float(ep.outcome.infraction_score), hazard=bool(ep.outcome.hazard),
                              frames=frames[s:s + clip_frames]))
    return out
