"""Causalising pretrained non-causal video layers (Vid2World Sec. 4.1 and App. A).

Temporal convolutions with symmetric kernels (size k odd, zero padding k//2, output[t] = Σ_o w[o] x[t+o],
o ∈ {-k//2 … k//2}) become causal convolutions (offsets o ≤ 0 only, zero left padding) by one of three
*weight transfers*, all pure functions of the pretrained kernel:

* ``shift`` – the whole kernel moved k//2 steps into the past: w'[o] = w[o + k//2] (no weight lost, but the
  kernel is temporally misaligned: tap o now reads frame t + o - k//2);
* ``masked`` – future taps zeroed: w'[o] = w[o] for o ≤ 0 (causal, loses the future taps' information);
* ``extrapolative`` (the paper's choice) – each future frame x[t+j] is replaced by its least-squares linear
  extrapolation from the m most recent frames x[t-m+1 … t]:
  x̂[t+j] = Σ_i c_i(j) x[t-i] with c_i(j) = 1/m + (j - τ̄)(τ_i - τ̄) / Σ_l (τ_l - τ̄)², τ_i = -i,
  so w'[-i] = w[-i] + Σ_{j=1}^{k//2} w[j] c_i(j). On inputs linear in time (away from the start, where the
  zero padding breaks linearity) the causal layer reproduces the original output exactly. The new kernel has
  max(k//2 + 1, m) taps.

``causalize(module, method, m=2)`` returns a *new* module (the input is not modified): a ``Conv1d`` (time is
its only axis) or a ``Conv3d`` with a temporal kernel (time = kernel dim 0, input ``(B, C, T, H, W)``) becomes
a :class:`CausalConv`; a temporal ``nn.MultiheadAttention`` becomes :class:`CausalTemporalAttention` (a causal
mask, no weight change – attention adapts to the shorter context); any other module is copied with its
temporal layers replaced (``select(name, module)`` decides which; by default all Conv1d and all Conv3d with a
temporal kernel > 1; attention only if ``select`` says so, since temporal and spatial attention modules
look alike). CogVideoX's DiT has no temporal convolutions: it needs only the mask (see ``attention.py``).
"""
from __future__ import annotations

import copy
from typing import Callable, Literal

import torch
import torch.nn.functional as F
from torch import nn

Method = Literal["shift", "masked", "extrapolative"]


def extrapolation_coefficients(m: int, j: int, dtype=torch.float64) -> torch.Tensor:
    """OLS linear-extrapolation weights ``c`` (m,): x̂[t+j] = Σ_i c[i] x[t-i], exact for x linear in t."""
    if m < 2:
        raise ValueError("extrapolation needs a window of m >= 2 past frames")
    tau = -torch.arange(m, dtype=dtype)
    tb = tau.mean()
    return 1.0 / m + (j - tb) * (tau - tb) / ((tau - tb) ** 2).sum()


def causal_kernel(weight: torch.Tensor, method: Method, time_dim: int = 2, m: int = 2) -> torch.Tensor:
    """Weight transfer on a conv weight ``(out, in, …, k, …)`` with the temporal taps on ``time_dim``.

    Returns the causal kernel whose last temporal tap is offset 0 (the current frame) and whose tap ``i``
    is offset ``i - (K - 1)``; use it with ``K - 1`` zero frames of left padding.
    """
    k = weight.shape[time_dim]
    if k % 2 == 0:
        raise ValueError(f"temporal kernel size {k} is even: not a symmetric ('same') kernel")
    r = k // 2
    w = weight.movedim(time_dim, -1)                               # (..., k), index r = offset 0
    if method == "shift":
        out = w.clone()
    elif method == "masked":
        out = w[..., : r + 1].clone()
    elif method == "extrapolative":
        kk = max(r + 1, m)
        out = torch.zeros(*w.shape[:-1], kk, dtype=w.dtype, device=w.device)
        out[..., kk - (r + 1):] = w[..., : r + 1]                  # past and present taps stay
        for j in range(1, r + 1):                                  # fold each future tap onto the window
            c = extrapolation_coefficients(m, j).to(w.dtype).to(w.device)   # c[i] multiplies x[t-i]
            for i in range(m):
                out[..., kk - 1 - i] += w[..., r + j] * c[i]
    else:
        raise ValueError(f"unknown weight transfer {method!r}; use shift, masked or extrapolative")
    return out.movedim(-1, time_dim)


class CausalConv(nn.Module):
    """A conv whose temporal axis is causal: zero left padding of ``K - 1`` frames, none on the right."""

    def __init__(self, conv: nn.Conv1d | nn.Conv3d, time_dim: int):
        super().__init__()
        self.conv = conv
        self.time_dim = time_dim  # kernel dim of time (2 in the weight); the input's time axis is the same index
        self.left = conv.weight.shape[time_dim] - 1

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        pad = [0, 0] * (x.dim() - 1 - self.time_dim) + [self.left, 0]   # F.pad lists dims from the last
        return self.conv(F.pad(x, pad))


def _causal_conv(conv: nn.Module, method: Method, m: int) -> nn.Module:
    if isinstance(conv, nn.Conv3d):
        td = 0
    elif isinstance(conv, nn.Conv1d):
        td = 0
    else:
        raise TypeError(f"not a Conv1d/Conv3d: {type(conv).__name__}")
    k = conv.kernel_size[td]
    if k == 1:
        return copy.deepcopy(conv)
    if conv.stride[td] != 1 or conv.dilation[td] != 1:
        raise ValueError(f"{type(conv).__name__}: temporal stride/dilation must be 1 to causalise")
    if isinstance(conv.padding, str) and conv.padding != "same" or (
            not isinstance(conv.padding, str) and conv.padding[td] != k // 2):
        raise ValueError(f"{type(conv).__name__}: temporal padding must be k//2 ('same'), got {conv.padding}")
    if conv.padding_mode != "zeros":
        raise ValueError(f"{type(conv).__name__}: padding_mode {conv.padding_mode!r} not supported (zeros only)")
    with torch.no_grad():
        w = causal_kernel(conv.weight.detach(), method, time_dim=2 + td, m=m)
    kernel = (w.shape[2],) + tuple(conv.kernel_size[1:])
    padding = (0,) + (tuple(conv.padding[1:]) if not isinstance(conv.padding, str)
                      else tuple(ks // 2 for ks in conv.kernel_size[1:]))
    cls = type(conv)
    new = cls(conv.in_channels, conv.out_channels, kernel, stride=conv.stride, padding=padding,
              dilation=conv.dilation, groups=conv.groups, bias=conv.bias is not None,
              device=w.device, dtype=w.dtype)
    with torch.no_grad():
        new.weight.copy_(w)
        if conv.bias is not None:
            new.bias.copy_(conv.bias)
    return CausalConv(new, time_dim=2 + td)


class CausalTemporalAttention(nn.Module):
    """``nn.MultiheadAttention`` over time with a causal mask (query t sees keys ≤ t)."""

    def __init__(self, attn: nn.MultiheadAttention):
        super().__init__()
        self.attn = attn

    def forward(self, query, key, value, **kwargs):
        tdim = 1 if self.attn.batch_first else 0
        lq, lk = query.shape[tdim], key.shape[tdim]
        mask = torch.ones(lq, lk, dtype=torch.bool, device=query.device).triu(1 + lk - lq)  # True = blocked
        if kwargs.get("attn_mask") is not None:
            raise ValueError("CausalTemporalAttention builds its own mask")
        kwargs["attn_mask"] = mask
        return self.attn(query, key, value, **kwargs)


def _default_select(name: str, module: nn.Module) -> bool:
    if isinstance(module, nn.Conv3d):
        return module.kernel_size[0] > 1
    return isinstance(module, nn.Conv1d)


def causalize(module: nn.Module, method: Method = "extrapolative", m: int = 2,
              select: Callable[[str, nn.Module], bool] | None = None) -> nn.Module:
    """A causal copy of ``module`` (see the module docstring); ``module`` itself is left unchanged."""
    if isinstance(module, (nn.Conv1d, nn.Conv3d)):
        return _causal_conv(module, method, m)
    if isinstance(module, nn.MultiheadAttention):
        return CausalTemporalAttention(copy.deepcopy(module))
    select = select or _default_select
    root = copy.deepcopy(module)
    todo = [(n, mod) for n, mod in root.named_modules() if n and select(n, mod)]
    done: set[str] = set()
    for name, mod in todo:
        if any(name.startswith(d + ".") for d in done):
            continue
        parent_name, _, attr = name.rpartition(".")
        parent = root.get_submodule(parent_name) if parent_name else root
        setattr(parent, attr, causalize(mod, method, m))
        done.add(name)
    return root
