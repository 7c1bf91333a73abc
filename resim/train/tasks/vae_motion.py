"""The motion term of ``resim train vae``: reconstruction errors that move with the scene.

Why: the world model's command accuracy is read off decoded video by the optical-flow labeler, and through the
synthetic world's VAE it reads much less of the originals' turn (docs/models/synth-vae.md, "Limitations"). Measured
per frame pair, the reconstructions' yaw rate falls short of the originals' inside each 4-frame latent group, while
frames 4 apart are shifted as in the originals: inside a group the decoded texture barely moves and then catches
up, so the frame-to-frame flow has little motion to read.

Pixel losses do not see this. MSE, L1 and the spatial-gradient term score each frame alone; the temporal-difference
term tried before (``|Δt x̂ − Δt x|``, the same pixel in two frames) asks the reconstruction error to *stay put*,
which is the wrong thing for a camera that moves, and it did not help. This term asks the error to move with the
scene instead: with ``W`` the warp of frame t onto frame t+1 along the *original's* optical flow,

    motion L1 = mean | (x̂_{t+1} − W x̂_t) − (x_{t+1} − W x_t) |  =  mean | e_{t+1} − W e_t |,   e = x̂ − x.

It is zero for a perfect reconstruction whatever the flow's own errors (occlusions and flow mistakes appear in
both brackets), so it does not move the optimum of the pixel losses; it penalises texture that stays where the
scene moves on, and ghosting inside a latent group. This is the short-term temporal loss of video style transfer
and video super-resolution (Ruder et al. 2016, "Artistic style transfer for videos"; Lai et al. 2018, "Learning
blind video temporal consistency"), written on the error so that the original's own occlusions cancel.

The flow is OpenCV's DIS (the labeler's estimator) on the originals, computed on the CPU per batch: the originals
are uint8 frames, the flow carries no gradient, and at 64 x 96 it costs ~1 ms per pair.

**Measured: it does not keep the heading** (docs/lab/2026-11-26-synth-vae-4x.md, 2026-12-01). The synthetic world's
decoder fine-tuned with it at weight 1 for 300 steps, against the same run without it, on 48 fresh clips: heading
kept −0.008 [−0.025, +0.008], PSNR −0.55 dB. The term is small for errors of low spatial frequency (they barely
change under a warp of a pixel), so it pays a decoder to blur the texture it cannot place. Blur is not what costs
the labeler the turn, though (a 2-px Gaussian blur of the originals keeps 0.91 of the heading); a cross-fade between
the group ends is (0.06), and this term did not remove it (resim/eval/group_frames.py). No shipped model uses it; it
stays an option (``model.motion_weight``, default 0) with that measurement.
"""
from __future__ import annotations

import cv2
import numpy as np
import torch
import torch.nn.functional as F

FLOW_UPSCALE = 2   # flow is estimated on frames upsampled 2x: the ego motion is ~0.5-2 px per frame at 64 x 96


def backward_flow(frames: torch.Tensor) -> torch.Tensor:
    """uint8 ``(B, T, 3, H, W)`` 0..255 → float32 ``(B, T-1, 2, H, W)`` (dx, dy) px: for pair ``t``, frame
    ``t+1`` at pixel p looks like frame ``t`` at ``p + flow`` (DIS on the grey frames, medium preset)."""
    if frames.dtype != torch.uint8 or frames.dim() != 5 or frames.shape[2] != 3:
        raise ValueError(f"backward_flow needs uint8 (B, T, 3, H, W) frames, got {frames.dtype} {tuple(frames.shape)}")
    b, t, _, h, w = frames.shape
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    s = FLOW_UPSCALE
    rgb = frames.permute(0, 1, 3, 4, 2).cpu().numpy()
    out = np.zeros((b, t - 1, 2, h, w), np.float32)
    for i in range(b):
        greys = [cv2.resize(cv2.cvtColor(np.ascontiguousarray(f), cv2.COLOR_RGB2GRAY), (w * s, h * s),
                            interpolation=cv2.INTER_CUBIC) for f in rgb[i]]
        for k in range(t - 1):
            fl = dis.calc(greys[k + 1], greys[k], None)            # greys[k+1](p) ≈ greys[k](p + fl(p))
            out[i, k] = cv2.resize(fl, (w, h), interpolation=cv2.INTER_AREA).transpose(2, 0, 1) / s
    return torch.from_numpy(out)


def warp(video: torch.Tensor, flow: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Frames ``0..T-2`` of ``video`` ``(B, C, T, H, W)`` warped onto frames ``1..T-1`` along ``flow``
    (:func:`backward_flow`'s ``(B, T-1, 2, H, W)``) → (warped ``(B, C, T-1, H, W)``, valid mask ``(B, 1, T-1, H, W)``:
    1 where the source point lies inside the frame). Bilinear, differentiable in ``video``."""
    b, c, t, h, w = video.shape
    fl = flow.to(video.device, video.dtype)
    ys, xs = torch.meshgrid(torch.arange(h, device=video.device, dtype=video.dtype),
                            torch.arange(w, device=video.device, dtype=video.dtype), indexing="ij")
    sx, sy = xs + fl[:, :, 0], ys + fl[:, :, 1]                       # (B, T-1, H, W) source points
    grid = torch.stack([2 * sx / (w - 1) - 1, 2 * sy / (h - 1) - 1], dim=-1).reshape(b * (t - 1), h, w, 2)
    src = video[:, :, :-1].permute(0, 2, 1, 3, 4).reshape(b * (t - 1), c, h, w)
    out = F.grid_sample(src, grid, mode="bilinear", padding_mode="border", align_corners=True)
    out = out.reshape(b, t - 1, c, h, w).permute(0, 2, 1, 3, 4)
    valid = ((sx >= 0) & (sx <= w - 1) & (sy >= 0) & (sy <= h - 1)).to(video.dtype).unsqueeze(1)
    return out, valid


def motion_l1(rec: torch.Tensor, x: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
    """mean |e_{t+1} − W e_t| over valid pixels, ``e = rec − x`` (both ``(B, C, T, H, W)`` in [-1, 1]) and ``W`` the
    warp along the original's ``flow`` (:func:`backward_flow`)."""
    err = rec - x
    moved, valid = warp(err, flow)
    d = (err[:, :, 1:] - moved).abs() * valid
    return d.sum() / (valid.sum() * err.shape[1]).clamp_min(1.0)
