"""Fixtures: a tiny causal world model for sampler tests, with the world model's interface and KV-cache protocol.

``model(x, t, text, trajectory=None, actions=None, *, trajectory_keep=None, action_keep=None, kv_cache=None,
return_kv_cache=False)``: tokens = [text | frame 0 | frame 1 | …] (one token per latent pixel), per-frame
noise-level embedding + action added to the frame's tokens, trajectory embedding added to every video token,
block-causal attention (text sees text; frame f sees text and frames <= f). It is the sampler's independent
check of the protocol; the real ``resim.models.world.WorldModel`` is exercised by the same tests where present.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import nn
import torch.nn.functional as F


@dataclass
class TinyCache:
    keys: list = field(default_factory=list)
    values: list = field(default_factory=list)
    text_len: int = 0
    tokens_per_frame: int = 0
    num_frames: int = 0


class TinyCausalModel(nn.Module):
    def __init__(self, channels=4, dim=32, text_dim=8, layers=2, heads=2, action_dim=3, causal=True, seed=0):
        super().__init__()
        g = torch.Generator().manual_seed(seed)
        self.causal = causal
        self.dim, self.heads = dim, heads
        self.inp = nn.Linear(channels, dim)
        self.txt = nn.Linear(text_dim, dim)
        self.traj = nn.Linear(24, dim)
        self.act = nn.Linear(action_dim, dim)
        self.null_traj = nn.Parameter(torch.randn(dim, generator=g) * 0.1)
        self.null_act = nn.Parameter(torch.randn(dim, generator=g) * 0.1)
        self.qkv = nn.ModuleList([nn.Linear(dim, 3 * dim) for _ in range(layers)])
        self.proj = nn.ModuleList([nn.Linear(dim, dim) for _ in range(layers)])
        self.out = nn.Linear(dim, channels)
        for p in self.parameters():  # deterministic init independent of the global seed
            with torch.no_grad():
                p.copy_(torch.randn(p.shape, generator=g) * (0.3 / math.sqrt(p.shape[-1])))

    def _temb(self, t):
        freqs = torch.exp(-math.log(1000.0) * torch.arange(self.dim // 2) / (self.dim // 2))
        a = t.float()[..., None] * freqs
        return torch.cat([a.sin(), a.cos()], -1)

    def forward(self, x, t, text, trajectory=None, actions=None, *, trajectory_keep=None, action_keep=None,
                kv_cache=None, return_kv_cache=False):
        b, nf, c, h, w = x.shape
        n = h * w
        prefix = kv_cache.num_frames if kv_cache is not None else 0
        if kv_cache is not None and not self.causal:
            raise ValueError("kv_cache needs a causal model")
        tok = self.inp(x.permute(0, 1, 3, 4, 2).reshape(b, nf, n, c))
        frame_pos = torch.arange(prefix, prefix + nf, dtype=torch.float32)
        emb = self._temb(t) + self._temb(frame_pos * 37.0)[None]
        if actions is not None:
            a = self.act(actions.float())
            if action_keep is not None:
                a = torch.where(action_keep[..., None], a, self.null_act)
        else:
            a = self.null_act.expand(b, nf, -1)
        emb = emb + a
        if trajectory is not None:
            tr = self.traj(trajectory.reshape(b, -1).float())
            if trajectory_keep is not None:
                tr = torch.where(trajectory_keep[:, None], tr, self.null_traj)
        else:
            tr = self.null_traj.expand(b, -1)
        tok = (tok + emb[:, :, None] + tr[:, None, None]).reshape(b, nf * n, -1)
        if kv_cache is None:
            txt = self.txt(text.float())
            L = txt.shape[1]
            seq = torch.cat([txt, tok], 1)
        else:
            L = kv_cache.text_len
            seq = tok
        kf = torch.cat([torch.full((L,), -1), torch.arange(prefix + nf).repeat_interleave(n)])
        qf = torch.arange(prefix, prefix + nf).repeat_interleave(n)
        if kv_cache is None:
            qf = torch.cat([torch.full((L,), -1), qf])
        mask = (kf[None] <= qf[:, None]) if self.causal else None
        if self.causal and kv_cache is None:
            mask[:L] = (kf < 0)[None]
        keys, values = [], []
        hd = self.dim // self.heads
        for i, (qkv, proj) in enumerate(zip(self.qkv, self.proj)):
            q, k, v = qkv(seq).view(b, seq.shape[1], 3, self.heads, hd).permute(2, 0, 3, 1, 4)
            if kv_cache is not None:
                k = torch.cat([kv_cache.keys[i], k], 2)
                v = torch.cat([kv_cache.values[i], v], 2)
            keys.append(k)
            values.append(v)
            o = F.scaled_dot_product_attention(q, k, v, attn_mask=mask)
            seq = seq + proj(o.transpose(1, 2).reshape(b, seq.shape[1], -1))
        vid = seq[:, -nf * n:] if kv_cache is None else seq
        out = self.out(vid).reshape(b, nf, h, w, c).permute(0, 1, 4, 2, 3).to(x.dtype)
        if return_kv_cache:
            return out, TinyCache(keys, values, L, n, prefix + nf)
        return out


import pytest  # noqa: E402


@pytest.fixture
def tiny_model():
    """Factory: ``tiny_model(causal=True, seed=0)`` → an eval-mode TinyCausalModel (CPU, float32)."""
    torch.set_num_threads(1)

    def make(**kw):
        return TinyCausalModel(**kw).eval()
    return make
