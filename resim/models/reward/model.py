"""Video2Reward: a video -> one scalar reward (ReSim appendix B.2).

ReSim: "all video frames are first processed separately via the image-based
DINOv2 backbone. All image features are then passed to the prediction head,
which aggregates all features via two consecutive spatial-temporal attention
blocks and further predicts a scalar reward via an MLP." It is trained by
regression to each CARLA sample's Infraction Score.

Shapes (B batch, T = cfg.num_frames, S = cfg.image_size_px, N tokens per frame =
1 CLS + (S/patch)^2, D backbone width, d = cfg.head_dim):

    video     (B, T, 3, H, W) float in [0, 1]      any H, W: resized to S x S, ImageNet-normalised
    features  (B, T, N, D)   float32 (or float16)  DINOv2 last hidden state per frame (= dino.npy)
    head      [temporal_diff: (B, T, N, D) -> (B, T, N, 2D), features ++ change since the previous frame]
              (B, T, N, D or 2D) -> Linear -> (B, T, N, d) + temporal position embedding
              -> num_blocks x [spatial attention over N within each frame,
                               then temporal attention over T for each token position, then MLP]
              -> mean over T and N -> MLP -> sigmoid -> (B,)
    output    (B,) float32 predicted infraction score in (0, 1) (1 = clean, lower = infractions);
              output_activation "none" gives the raw, unbounded MLP output instead

The spatio-temporal blocks are *factorised*: spatial-then-temporal attention
(each block costs T*N^2 + N*T^2 instead of (T*N)^2). DINOv2's own position
embeddings already give each token its spatial position; the head adds a learned
temporal one.
"""
from __future__ import annotations

from typing import Any, Mapping

import torch
import torch.nn.functional as F
from torch import nn

from resim.models.reward.backbone import feature_id, load_backbone, num_tokens, preprocess_frames
from resim.models.reward.config import RewardModelConfig


class FeatureMismatchError(ValueError):
    """Stored features were made by another backbone / size / frame selection than this model's."""


class SpatioTemporalBlock(nn.Module):
    """Factorised spatio-temporal transformer block (pre-LN): spatial attn, temporal attn, MLP.

    x: (B, T, N, d) -> (B, T, N, d)
    """

    def __init__(self, dim: int, num_heads: int, mlp_ratio: float = 4.0, dropout: float = 0.0):
        super().__init__()
        self.norm_s = nn.LayerNorm(dim)
        self.attn_s = nn.MultiheadAttention(dim, num_heads, dropout=dropout, batch_first=True)
        self.norm_t = nn.LayerNorm(dim)
        self.attn_t = nn.MultiheadAttention(dim, num_heads, dropout=dropout, batch_first=True)
        self.norm_m = nn.LayerNorm(dim)
        hidden = int(dim * mlp_ratio)
        self.mlp = nn.Sequential(nn.Linear(dim, hidden), nn.GELU(), nn.Dropout(dropout), nn.Linear(hidden, dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, t, n, d = x.shape
        # spatial: tokens of one frame attend to each other
        h = self.norm_s(x).reshape(b * t, n, d)
        x = x + self.attn_s(h, h, h, need_weights=False)[0].reshape(b, t, n, d)
        # temporal: one token position attends across frames
        h = self.norm_t(x).permute(0, 2, 1, 3).reshape(b * n, t, d)
        x = x + self.attn_t(h, h, h, need_weights=False)[0].reshape(b, n, t, d).permute(0, 2, 1, 3)
        return x + self.mlp(self.norm_m(x))


class RewardHead(nn.Module):
    """(B, T, N, D) features -> (B,) scalar."""

    def __init__(self, in_dim: int, cfg: RewardModelConfig):
        super().__init__()
        self.temporal_diff = cfg.temporal_diff
        self.sigmoid = cfg.output_activation == "sigmoid"
        self.proj = nn.Linear(2 * in_dim if cfg.temporal_diff else in_dim, cfg.head_dim)
        self.time_pos = nn.Parameter(torch.zeros(1, cfg.num_frames, 1, cfg.head_dim))
        nn.init.normal_(self.time_pos, std=0.02)
        self.blocks = nn.ModuleList(
            SpatioTemporalBlock(cfg.head_dim, cfg.num_heads, dropout=cfg.dropout) for _ in range(cfg.num_blocks)
        )
        self.norm = nn.LayerNorm(cfg.head_dim)
        self.mlp = nn.Sequential(nn.Linear(cfg.head_dim, cfg.mlp_hidden_dim), nn.GELU(),
                                 nn.Linear(cfg.mlp_hidden_dim, 1))

    def forward(self, feats: torch.Tensor) -> torch.Tensor:
        if self.temporal_diff:  # (B, T, N, D) -> (B, T, N, 2D): features and their change since the last frame
            diff = torch.cat([torch.zeros_like(feats[:, :1]), feats[:, 1:] - feats[:, :-1]], dim=1)
            feats = torch.cat([feats, diff], dim=-1)
        x = self.proj(feats) + self.time_pos[:, : feats.shape[1]]
        for blk in self.blocks:
            x = blk(x)
        pooled = self.norm(x).mean(dim=(1, 2))
        out = self.mlp(pooled).squeeze(-1)
        return torch.sigmoid(out) if self.sigmoid else out


def _field(batch: Any, name: str) -> Any:
    """Read a field from a dict-like batch or a dataclass-like one (the Trainer's Batch)."""
    if isinstance(batch, Mapping):
        return batch.get(name)
    return getattr(batch, name, None)


class Video2Reward(nn.Module):
    """DINOv2 backbone (frozen by default) + factorised spatio-temporal head -> scalar."""

    def __init__(self, cfg: RewardModelConfig):
        super().__init__()
        self.cfg = cfg
        self.backbone, self.backbone_info = load_backbone(cfg.backbone_dir, cfg.backbone_init_seed)
        if cfg.freeze_backbone:
            self.backbone.requires_grad_(False)
        d = self.backbone_info["hidden_size"]
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(cfg.head_init_seed)
            self.head = RewardHead(d, cfg)

    # ---- identity of the features this model consumes -------------------------------------------
    @property
    def feature_id(self) -> str:
        """``meta.dino_id`` of features this model can reuse."""
        c = self.cfg
        return feature_id(self.backbone_info["id"], c.image_size_px, c.num_frames, c.frame_step)

    @property
    def feature_shape(self) -> tuple[int, int, int]:
        """(T, N_tokens, D) of one sample's features."""
        return (self.cfg.num_frames, num_tokens(self.cfg.image_size_px, self.backbone_info["patch_size"]),
                self.backbone_info["hidden_size"])

    def train(self, mode: bool = True):
        super().train(mode)
        if self.cfg.freeze_backbone:
            self.backbone.eval()  # a frozen backbone never runs in train mode (no dropout / drop-path)
        return self

    # ---- forward ----------------------------------------------------------------------------------
    def encode(self, video: torch.Tensor) -> torch.Tensor:
        """video (B, T, 3, H, W) float [0, 1] -> features (B, T, N, D) float32 (rounded to feature_dtype)."""
        if video.ndim != 5 or video.shape[2] != 3:
            raise ValueError(f"expected video (B, T, 3, H, W), got {tuple(video.shape)}")
        b, t = video.shape[:2]
        x = preprocess_frames(video.reshape(b * t, *video.shape[2:]), self.cfg.image_size_px,
                              self.backbone_info["image_mean"], self.backbone_info["image_std"])
        with torch.set_grad_enabled(torch.is_grad_enabled() and not self.cfg.freeze_backbone):
            feats = self.backbone(pixel_values=x).last_hidden_state
        if self.cfg.feature_dtype == "float16":
            feats = feats.to(torch.float16).to(torch.float32)  # identical to what dino.npy stores
        return feats.reshape(b, t, *feats.shape[1:])

    def forward(self, video: torch.Tensor | None = None, features: torch.Tensor | None = None) -> torch.Tensor:
        """Predicted infraction score (B,) from ``video`` (B, T, 3, H, W) or stored ``features`` (B, T, N, D)."""
        if (video is None) == (features is None):
            raise ValueError("pass exactly one of video or features")
        if features is None:
            if video.shape[1] != self.cfg.num_frames:
                raise ValueError(f"the model takes windows of {self.cfg.num_frames} frames, got {video.shape[1]} "
                                 "(use resim.sample.reward_score.score_videos for longer videos)")
            features = self.encode(video)
        else:
            features = features.to(torch.float32)
            if tuple(features.shape[1:]) != self.feature_shape:
                raise FeatureMismatchError(f"features of shape {tuple(features.shape[1:])} per sample, "
                                           f"this model expects {self.feature_shape}")
        return self.head(features)

    def loss(self, batch: Any) -> tuple[torch.Tensor, dict[str, float]]:
        """MSE regression to the infraction score.

        batch: ``infraction_score`` (B,) float; and ``dino`` (B, T, N, D) stored features (used when
        present, with ``dino_id`` equal to ``self.feature_id``), else ``video`` (B, T, 3, H, W) in [0, 1].
        Returns (loss, {"loss", "mae", "used_features"}).
        """
        target, feats, ids, video = self._inputs(batch)
        if feats is not None:
            bad = [i for i in ids if i != self.feature_id]
            if not ids or bad:
                raise FeatureMismatchError(f"stored features {bad[:1] or 'without dino_id'} do not match this "
                                           f"model's {self.feature_id!r}: recompute them (resim shards features)")
            pred = self(features=feats)
        else:
            pred = self(video=video)
        target = torch.as_tensor(target, dtype=torch.float32, device=pred.device)
        loss = F.mse_loss(pred, target)
        mae = (pred.detach() - target).abs().mean()
        return loss, {"loss": float(loss.detach()), "mae": float(mae), "used_features": float(feats is not None)}

    def _inputs(self, batch: Any):
        """(target (B,), dino or None, dino ids, video or None) from a reward batch (``collate``: keys
        infraction_score / dino / dino_id / video) or the common stream's ``resim.train.data.Batch``
        (``meta`` dicts carry infraction_score and dino_id; ``frames`` (B, T_clip, 3, H, W) uint8 is the
        whole clip, of which the model takes its last window)."""
        meta = _field(batch, "meta") or []
        target = _field(batch, "infraction_score")
        if target is None and meta:
            vals = [m.get("infraction_score") for m in meta]
            if any(v is None for v in vals):
                key = (_field(batch, "keys") or ["?"] * len(vals))[vals.index(None)]
                raise ValueError(f"sample {key} has no infraction_score: train Video2Reward on clips with outcomes "
                                 "(filter the stream to labelled sources)")
            target = vals
        if target is None:
            raise ValueError("batch has no infraction_score: Video2Reward trains only on clips with outcomes")
        feats = _field(batch, "dino")
        ids = _field(batch, "dino_id")
        if ids is None and meta:
            ids = [m.get("dino_id") for m in meta]
        ids = [ids] if isinstance(ids, str) else [i for i in (ids or []) if i is not None]
        video = _field(batch, "video")
        if feats is None and video is None:
            frames = _field(batch, "frames")
            if frames is None:
                raise ValueError("batch has neither dino, video nor frames")
            w = self.cfg.window_frames
            if frames.shape[1] < w:
                raise ValueError(f"clips of {frames.shape[1]} frames are shorter than the model's window of {w}")
            video = frames[:, frames.shape[1] - w::self.cfg.frame_step].float() / 255.0
        return target, feats, ids, video

    def metadata(self) -> dict:
        """What a checkpoint / score output records about the model."""
        return {"backbone_id": self.backbone_info["id"], "backbone_placeholder": self.backbone_info["placeholder"],
                "feature_id": self.feature_id, "window_frames": self.cfg.window_frames,
                "num_frames": self.cfg.num_frames, "frame_step": self.cfg.frame_step,
                "head": "factorised spatial-then-temporal attention x%d" % self.cfg.num_blocks}
