"""The DINOv2 backbone of Video2Reward: loading, frame preprocessing, feature ids.

ReSim (appendix B.2) runs every frame separately through a pretrained DINOv2.
We load ``transformers.Dinov2Model`` from a local folder with ``from_pretrained``
(no downloads at run time). A folder that holds only ``config.json`` is a
placeholder (``configs/models/placeholder-dinov2-tiny``): its weights are built
deterministically from a seed, and its id says ``placeholder``.
"""
from __future__ import annotations

import json
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
WEIGHT_FILES = ("model.safetensors", "pytorch_model.bin", "model.safetensors.index.json")


class BackboneError(ValueError):
    """The backbone folder is missing or unusable."""


def _resolve_dir(backbone_dir: str | Path) -> Path:
    p = Path(backbone_dir)
    if not p.is_absolute() and not p.exists():
        # relative paths in configs are relative to the repository root
        repo = Path(__file__).resolve().parents[3]
        if (repo / p).exists():
            p = repo / p
    if not (p / "config.json").is_file():
        raise BackboneError(f"DINOv2 backbone folder {p} has no config.json "
                            "(expected a local folder readable by Dinov2Model.from_pretrained)")
    return p


def has_weights(backbone_dir: str | Path) -> bool:
    p = _resolve_dir(backbone_dir)
    return any((p / f).is_file() for f in WEIGHT_FILES)


def load_backbone(backbone_dir: str | Path, init_seed: int = 0) -> tuple[nn.Module, dict]:
    """Load a ``Dinov2Model`` from a local folder.

    Returns ``(model, info)`` with ``info = {"id", "placeholder", "hidden_size", "patch_size",
    "image_mean", "image_std"}``. Without a weights file the model is randomly initialised
    from ``init_seed`` (same seed -> bit-identical weights) and marked a placeholder.
    """
    from safetensors import SafetensorError
    from transformers import Dinov2Config, Dinov2Model

    p = _resolve_dir(backbone_dir)
    try:
        raw = json.loads((p / "config.json").read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise BackboneError(f"{p}/config.json: not valid JSON ({e})") from None
    if not isinstance(raw, dict) or raw.get("model_type") not in (None, "dinov2"):
        got = raw.get("model_type") if isinstance(raw, dict) else type(raw).__name__
        raise BackboneError(f"{p}/config.json: model_type is {got!r}, expected 'dinov2'")
    if has_weights(p):
        try:
            model = Dinov2Model.from_pretrained(str(p))
        except (SafetensorError, OSError) as e:  # truncated / corrupt weight file: a user's folder, not our bug
            raise BackboneError(f"DINOv2 backbone folder {p}: weights cannot be read ({e})") from None
        placeholder = bool(raw.get("resim_placeholder", False))
        ident = p.name
    else:
        config = Dinov2Config.from_pretrained(str(p))
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(init_seed)
            model = Dinov2Model(config)
        placeholder = True
        ident = f"{p.name}-random-seed{init_seed}"
    mean, std = IMAGENET_MEAN, IMAGENET_STD
    pre = p / "preprocessor_config.json"
    if pre.is_file():
        d = json.loads(pre.read_text())
        mean = tuple(d.get("image_mean", mean))
        std = tuple(d.get("image_std", std))
    model.eval()
    info = {
        "id": ident,
        "placeholder": placeholder,
        "hidden_size": int(model.config.hidden_size),
        "patch_size": int(model.config.patch_size),
        "image_mean": mean,
        "image_std": std,
    }
    return model, info


def num_tokens(image_size_px: int, patch_size: int) -> int:
    """Tokens per frame of DINOv2's last hidden state: CLS + (H/p)*(W/p) patches."""
    return 1 + (image_size_px // patch_size) ** 2


def preprocess_frames(frames: torch.Tensor, image_size_px: int, mean=IMAGENET_MEAN, std=IMAGENET_STD) -> torch.Tensor:
    """Resize and normalise frames for DINOv2.

    frames: (N, C=3, H, W) float in [0, 1]. Returns (N, 3, S, S) float32, ImageNet-normalised,
    S = image_size_px (bilinear with antialiasing; aspect ratio is not kept, as in ReSim's 224x224).
    """
    if frames.ndim != 4 or frames.shape[1] != 3:
        raise ValueError(f"expected frames (N, 3, H, W), got {tuple(frames.shape)}")
    x = frames.float()
    if x.shape[-2:] != (image_size_px, image_size_px):
        x = F.interpolate(x, size=(image_size_px, image_size_px), mode="bilinear", align_corners=False,
                          antialias=True)
    m = torch.tensor(mean, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
    s = torch.tensor(std, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
    return (x - m) / s


def feature_id(backbone_id: str, image_size_px: int, num_frames: int, frame_step: int) -> str:
    """The string stored as ``meta.dino_id``: backbone + everything that changes the stored features.

    Stored features are only reused when this id equals the model's own (see model.Video2Reward).
    """
    return f"{backbone_id}|{image_size_px}px|T{num_frames}s{frame_step}"
