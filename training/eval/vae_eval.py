"""Reconstruction quality of a VAE on held-out clips (``resim eval vae``): PSNR / SSIM per frame of the clip,
and a picture of originals beside reconstructions.

Each clip's recorded frames (``frames.mp4``, at the resolution the pipeline encoded) go through the VAE as the
pipeline runs it (``media.encoders.VideoVAE.encode``: one posterior sample x scaling factor) and back
through the sampler's decode (``training.sampling.outputs.decode_latents``), i.e. exactly the round trip a
world-model rollout's frames take. Frame ``k``'s metrics average over clips, so the causal VAE's first
frame (encoded alone) and the frames at its 4-frame chunk boundaries show up separately.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from training.eval.fidelity import psnr, ssim


def reconstruct(vae: Any, frames: np.ndarray, seeds: Sequence[int]) -> np.ndarray:
    """uint8 ``(B, T, H, W, 3)`` → the VAE's reconstruction, same shape and dtype."""
    from training.sampling.outputs import decode_latents

    lat = vae.encode(frames, seeds=list(seeds))
    return decode_latents(vae, torch.from_numpy(lat))


def vae_eval(vae: Any, clips: Sequence[Any], batch_size: int = 2) -> dict:
    """Per-frame PSNR/SSIM over ``clips`` (``EvalClip``: ``.frames`` uint8 (T, H, W, 3)); ``_examples`` holds
    the first batch's originals and reconstructions for the picture."""
    per_psnr, per_ssim, examples = [], [], None
    for i in range(0, len(clips), batch_size):
        part = clips[i:i + batch_size]
        frames = np.stack([c.frames for c in part])
        rec = reconstruct(vae, frames, seeds=range(i, i + len(part)))
        g = torch.from_numpy(rec).permute(0, 1, 4, 2, 3)
        r = torch.from_numpy(frames).permute(0, 1, 4, 2, 3)
        per_psnr.append(psnr(g, r, "uint8"))
        per_ssim.append(ssim(g, r, "uint8"))
        if examples is None:
            examples = (frames, rec)
    p, s = torch.cat(per_psnr), torch.cat(per_ssim)                  # (N, T)
    return {"psnr_db": {"mean": float(p.mean()), "per_clip_min": float(p.mean(1).min()),
                        "per_frame": p.mean(0).tolist()},
            "ssim": {"mean": float(s.mean()), "per_frame": s.mean(0).tolist()},
            "clips": len(clips), "frames_per_clip": int(p.shape[1]), "_examples": examples}


def plot_vae_eval(rep: dict, path: str | Path, fps_hz: float, title: str = "") -> Path:
    """Per-frame PSNR/SSIM curves above originals (top row) vs reconstructions (bottom row) of one clip."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    frames, rec = rep["_examples"]
    t = frames.shape[1]
    cols = list(range(0, t, max(1, t // 6)))[:7]
    fig = plt.figure(figsize=(14, 6.2))
    ax = fig.add_subplot(3, 1, 1)
    x = np.arange(len(rep["psnr_db"]["per_frame"])) / fps_hz
    ax.plot(x, rep["psnr_db"]["per_frame"], label=f"PSNR (mean {rep['psnr_db']['mean']:.2f} dB)")
    ax.set_ylabel("PSNR (dB)")
    ax2 = ax.twinx()
    ax2.plot(x, rep["ssim"]["per_frame"], color="tab:orange", label=f"SSIM (mean {rep['ssim']['mean']:.3f})")
    ax2.set_ylabel("SSIM")
    ax.set_xlabel("time in clip (s)")
    ax.legend(loc="lower left")
    ax2.legend(loc="lower right")
    ax.set_title(title or f"VAE reconstruction, {rep['clips']} held-out clips")
    top = np.concatenate([frames[0, k] for k in cols], axis=1)
    bottom = np.concatenate([rec[0, k] for k in cols], axis=1)
    for row, (img, name) in enumerate(((top, "original"), (bottom, "reconstruction"))):
        a = fig.add_subplot(3, 1, 2 + row)
        a.imshow(img)
        a.set_axis_off()
        a.set_title(f"{name}, frames {cols}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path)
