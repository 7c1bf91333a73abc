"""LPIPS (Zhang et al., 2018) with a VGG-16 or AlexNet trunk, in the ``lpips`` package's layout.

torchvision is not available beside our CPU torch, so both trunks are written out with
torchvision's parameter names (``features.0.weight`` ...), and the linear heads with the
``lpips`` package's names (``lin0.model.1.weight`` ...). Real weights load from two local
files: the torchvision ImageNet trunk (``vgg16-397923af.pth`` / ``alexnet-owt-7be5be79.pth``)
and the LPIPS heads (``lpips/weights/v0.1/{vgg,alex}.pth``). Tests use random weights.

Distance for frames x, y in [0, 1]: both scaled to [-1, 1], shifted/scaled by the
ScalingLayer constants, passed through the trunk; at each of 5 layers features are
unit-normalised over channels, the squared difference is weighted by a 1x1 conv (the
"lin" layer), averaged over space, and the 5 layer values are summed.
"""
from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Literal

import torch
import torch.nn as nn

Net = Literal["vgg", "alex"]

# layer configs: torchvision `features` Sequential, and the slice boundaries LPIPS taps
_VGG16 = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M"]
_SLICES = {"vgg": (4, 9, 16, 23, 30), "alex": (2, 5, 8, 10, 12)}
_CHANNELS = {"vgg": (64, 128, 256, 512, 512), "alex": (64, 192, 384, 256, 256)}
_SHIFT = torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1)
_SCALE = torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1)


def _vgg16_features() -> nn.Sequential:
    layers: list[nn.Module] = []
    cin = 3
    for v in _VGG16:
        if v == "M":
            layers.append(nn.MaxPool2d(2, 2))
        else:
            layers += [nn.Conv2d(cin, v, 3, padding=1), nn.ReLU(inplace=False)]
            cin = v
    return nn.Sequential(*layers)


def _alexnet_features() -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(3, 64, 11, stride=4, padding=2), nn.ReLU(),
        nn.MaxPool2d(3, 2),
        nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(),
        nn.MaxPool2d(3, 2),
        nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(),
        nn.Conv2d(384, 256, 3, padding=1), nn.ReLU(),
        nn.Conv2d(256, 256, 3, padding=1), nn.ReLU(),
        nn.MaxPool2d(3, 2),
    )


class _Lin(nn.Module):
    def __init__(self, cin: int):
        super().__init__()
        self.model = nn.Sequential(nn.Dropout(), nn.Conv2d(cin, 1, 1, bias=False))


class LPIPS(nn.Module):
    """Frames ``(N, 3, H, W)`` in [0, 1] (two of them) → distance ``(N,)``; 0 for identical frames."""

    def __init__(self, net: Net = "vgg"):
        super().__init__()
        if net not in _SLICES:
            raise ValueError(f"net must be 'vgg' or 'alex', got {net!r}")
        self.net_name = net
        self.features = _vgg16_features() if net == "vgg" else _alexnet_features()
        for i, c in enumerate(_CHANNELS[net]):
            setattr(self, f"lin{i}", _Lin(c))
            # trained LPIPS heads are non-negative (the lpips package clamps them), so a distance is >= 0;
            # keep the random-init placeholder in that family too
            lin = getattr(self, f"lin{i}").model[1]
            lin.weight.data.abs_()
        self.weights_sha256 = "random-init"
        self.requires_grad_(False)
        self.eval()

    def train(self, mode: bool = True):  # dropout in the heads must never be active at evaluation
        return super().train(False)

    @classmethod
    def from_files(cls, net: Net, trunk_path: str | Path, lin_path: str | Path) -> "LPIPS":
        m = cls(net)
        h = hashlib.sha256()
        for p in (Path(trunk_path), Path(lin_path)):
            if not p.is_file():
                raise FileNotFoundError(f"LPIPS weights {p} not found (see docs/eval.md)")
            h.update(p.read_bytes())
        trunk = torch.load(trunk_path, map_location="cpu", weights_only=True)
        trunk = {k[len("features."):]: v for k, v in trunk.items() if k.startswith("features.")}
        m.features.load_state_dict(trunk, strict=True)
        lin = torch.load(lin_path, map_location="cpu", weights_only=True)
        own = {k: v for k, v in m.state_dict().items() if k.startswith("lin")}
        missing = set(own) - set(lin)
        if missing:
            raise ValueError(f"{lin_path}: not an LPIPS head file (missing {sorted(missing)[:3]})")
        m.load_state_dict({**m.state_dict(), **{k: lin[k] for k in own}})
        m.weights_sha256 = h.hexdigest()
        return m

    def _taps(self, x: torch.Tensor) -> list[torch.Tensor]:
        outs, start = [], 0
        for end in _SLICES[self.net_name]:
            for layer in self.features[start:end]:
                x = layer(x)
            outs.append(x)
            start = end
        return outs

    @torch.no_grad()
    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        if x.shape != y.shape or x.ndim != 4 or x.shape[1] != 3:
            raise ValueError(f"expected two (N, 3, H, W) batches, got {tuple(x.shape)} and {tuple(y.shape)}")
        sx = ((2 * x.float() - 1) - _SHIFT.to(x.device)) / _SCALE.to(x.device)
        sy = ((2 * y.float() - 1) - _SHIFT.to(y.device)) / _SCALE.to(y.device)
        total = torch.zeros(x.shape[0], device=x.device)
        for i, (fx, fy) in enumerate(zip(self._taps(sx), self._taps(sy))):
            nx = fx / (fx.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            ny = fy / (fy.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            d = getattr(self, f"lin{i}").model((nx - ny) ** 2)  # (N, 1, h, w)
            total = total + d.mean(dim=(1, 2, 3))
        return total
