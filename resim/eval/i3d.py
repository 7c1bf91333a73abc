"""I3D (Carreira & Zisserman, 2017) video features for FVD.

Written out in the parameter layout of the widely used PyTorch port ``pytorch-i3d``
(``InceptionI3d``: ``Conv3d_1a_7x7.conv3d.weight``, ``Mixed_3b.b1b.bn.running_var``,
``logits.conv3d.bias`` ...), so its Kinetics-400 weights (``rgb_imagenet.pt``, a plain state
dict) load from a local file with ``torch.load(weights_only=True)``. TensorFlow's "SAME"
padding is reproduced exactly (asymmetric, computed from the input size).

FVD protocol (Unterthiner et al., 2018): clips resized to 224x224 (bilinear), scaled to
[-1, 1]; features are the 400-d logits (``feature_layer="logits"``, the original FVD) or the
1024-d pooled ``Mixed_5c`` output (``"pool"``). Numbers computed with this port are close to,
not identical with, the TF-Hub graph's; the report names the weights' sha256 so numbers are
only compared like for like.
"""
from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Literal

import torch
import torch.nn as nn
import torch.nn.functional as F

FVD_INPUT_PX = 224


def _same_pad(x: torch.Tensor, kernel: tuple[int, int, int], stride: tuple[int, int, int]) -> torch.Tensor:
    pads = []
    for size, k, s in zip(x.shape[2:], kernel, stride):
        total = max(k - s, 0) if size % s == 0 else max(k - size % s, 0)
        pads.append((total // 2, total - total // 2))
    (tf, tb), (hf, hb), (wf, wb) = pads
    return F.pad(x, (wf, wb, hf, hb, tf, tb))


class Unit3D(nn.Module):
    def __init__(self, cin: int, cout: int, kernel=(1, 1, 1), stride=(1, 1, 1), bn: bool = True,
                 bias: bool = False, relu: bool = True):
        super().__init__()
        self.kernel, self.stride, self.relu = tuple(kernel), tuple(stride), relu
        self.conv3d = nn.Conv3d(cin, cout, self.kernel, stride=self.stride, bias=bias)
        self.bn = nn.BatchNorm3d(cout, eps=0.001, momentum=0.01) if bn else None

    def forward(self, x):
        x = self.conv3d(_same_pad(x, self.kernel, self.stride))
        if self.bn is not None:
            x = self.bn(x)
        return F.relu(x) if self.relu else x


class MaxPoolSame(nn.Module):
    def __init__(self, kernel, stride):
        super().__init__()
        self.kernel, self.stride = tuple(kernel), tuple(stride)

    def forward(self, x):
        return F.max_pool3d(_same_pad(x, self.kernel, self.stride), self.kernel, self.stride)


class InceptionModule(nn.Module):
    def __init__(self, cin: int, out: list[int]):
        super().__init__()
        self.b0 = Unit3D(cin, out[0])
        self.b1a = Unit3D(cin, out[1])
        self.b1b = Unit3D(out[1], out[2], (3, 3, 3))
        self.b2a = Unit3D(cin, out[3])
        self.b2b = Unit3D(out[3], out[4], (3, 3, 3))
        self.b3a = MaxPoolSame((3, 3, 3), (1, 1, 1))
        self.b3b = Unit3D(cin, out[5])

    def forward(self, x):
        return torch.cat([self.b0(x), self.b1b(self.b1a(x)), self.b2b(self.b2a(x)), self.b3b(self.b3a(x))], 1)


_MIXED = [  # (name, in channels, branch widths) — InceptionV1 inflated
    ("Mixed_3b", 192, [64, 96, 128, 16, 32, 32]), ("Mixed_3c", 256, [128, 128, 192, 32, 96, 64]),
    ("MaxPool3d_4a_3x3", None, ((3, 3, 3), (2, 2, 2))),
    ("Mixed_4b", 480, [192, 96, 208, 16, 48, 64]), ("Mixed_4c", 512, [160, 112, 224, 24, 64, 64]),
    ("Mixed_4d", 512, [128, 128, 256, 24, 64, 64]), ("Mixed_4e", 512, [112, 144, 288, 32, 64, 64]),
    ("Mixed_4f", 528, [256, 160, 320, 32, 128, 128]),
    ("MaxPool3d_5a_2x2", None, ((2, 2, 2), (2, 2, 2))),
    ("Mixed_5b", 832, [256, 160, 320, 32, 128, 128]), ("Mixed_5c", 832, [384, 192, 384, 48, 128, 128]),
]


class I3D(nn.Module):
    """Clips ``(B, T, 3, H, W)`` float in [0, 1] (T >= 9) → features ``(B, 400)`` or ``(B, 1024)``."""

    def __init__(self, feature_layer: Literal["logits", "pool"] = "logits", num_classes: int = 400):
        super().__init__()
        if feature_layer not in ("logits", "pool"):
            raise ValueError(f"feature_layer must be 'logits' or 'pool', got {feature_layer!r}")
        self.feature_layer = feature_layer
        self.Conv3d_1a_7x7 = Unit3D(3, 64, (7, 7, 7), (2, 2, 2))
        self.MaxPool3d_2a_3x3 = MaxPoolSame((1, 3, 3), (1, 2, 2))
        self.Conv3d_2b_1x1 = Unit3D(64, 64)
        self.Conv3d_2c_3x3 = Unit3D(64, 192, (3, 3, 3))
        self.MaxPool3d_3a_3x3 = MaxPoolSame((1, 3, 3), (1, 2, 2))
        self.order = ["Conv3d_1a_7x7", "MaxPool3d_2a_3x3", "Conv3d_2b_1x1", "Conv3d_2c_3x3", "MaxPool3d_3a_3x3"]
        for name, cin, spec in _MIXED:
            mod = MaxPoolSame(*spec) if cin is None else InceptionModule(cin, spec)
            self.add_module(name, mod)
            self.order.append(name)
        self.logits = Unit3D(1024, num_classes, bn=False, bias=True, relu=False)
        self.weights_sha256 = "random-init"
        self.requires_grad_(False)
        self.eval()

    def train(self, mode: bool = True):
        return super().train(False)

    @classmethod
    def from_file(cls, path: str | Path, feature_layer: Literal["logits", "pool"] = "logits") -> "I3D":
        p = Path(path)
        if not p.is_file():
            raise FileNotFoundError(f"I3D weights {p} not found (see docs/eval.md)")
        net = cls(feature_layer)
        state = torch.load(p, map_location="cpu", weights_only=True)
        missing, unexpected = net.load_state_dict(state, strict=False)
        if missing or unexpected:
            raise ValueError(f"{p}: not a pytorch-i3d state dict (missing {missing[:3]}, unexpected {unexpected[:3]})")
        net.weights_sha256 = hashlib.sha256(p.read_bytes()).hexdigest()
        return net

    @torch.no_grad()
    def forward(self, clips: torch.Tensor) -> torch.Tensor:
        if clips.ndim != 5 or clips.shape[2] != 3:
            raise ValueError(f"expected clips (B, T, 3, H, W), got {tuple(clips.shape)}")
        b, t = clips.shape[:2]
        x = clips.float().flatten(0, 1)  # (B*T, 3, H, W)
        x = F.interpolate(x, size=(FVD_INPUT_PX, FVD_INPUT_PX), mode="bilinear", align_corners=False)
        x = (2 * x - 1).view(b, t, 3, FVD_INPUT_PX, FVD_INPUT_PX).transpose(1, 2)  # (B, 3, T, 224, 224)
        for name in self.order:
            x = getattr(self, name)(x)
        pooled = x.mean(dim=(2, 3, 4), keepdim=True)  # (B, 1024, 1, 1, 1)
        if self.feature_layer == "pool":
            return pooled.flatten(1)
        return self.logits(pooled).flatten(1)  # (B, 400)
