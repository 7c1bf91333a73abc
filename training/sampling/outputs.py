"""What a rollout leaves on disk: decoded video (MP4 + GIF), a contact sheet, the latents.

* :func:`decode_latents` – CogVideoX VAE decode of ``(B, T, C, h, w)`` latents (× scaling factor, as stored in
  shards) → ``(B, 1 + 4 (T - 1), H, W, 3)`` uint8 RGB; :func:`decode_rollout` does it round by round.
* :func:`draw_trajectory` – a bird's-eye panel of the 8 waypoints (x forward = up, y left = left).
* :func:`contact_sheet` – a grid of frames (last history frame + evenly spaced future frames), with the
  command and the trajectory drawn.
* :func:`write_rollout` – ``DIR/{name}.mp4``, ``.gif``, ``_sheet.png``, ``_latents.npy`` (float32, history +
  generated, exactly what the sampler produced, so runs can be compared bit for bit) and ``_meta.json``.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Sequence

import numpy as np

SHEET_BG = (24, 24, 24)
TEXT = (235, 235, 235)
HISTORY_EDGE = (90, 160, 255)
FUTURE_EDGE = (255, 170, 60)


def decode_latents(vae: Any, latents, scaling_factor: float | None = None, batch_size: int = 1) -> np.ndarray:
    """Latents ``(B, T, C, h, w)`` (torch or numpy, VAE latent × scaling factor) → uint8 ``(B, F, H, W, 3)``,
    ``F = 1 + 4 (T - 1)`` (frame 0 alone, then 4 pixel frames per latent frame, as the encoder made them).

    ``vae``: a ``pipelines.encoders.VideoVAE`` (uses its ``.model`` and ``.info.scaling_factor``) or a diffusers
    ``AutoencoderKLCogVideoX``. diffusers decodes in batches of 2 latent frames and only keeps frame 0 alone
    when ``T`` is odd (an even ``T`` gives ``4 T`` frames with no "first frame"); for an even ``T`` we append a
    copy of the last latent frame, decode ``T + 1`` and drop the last 4 pixel frames. The causal convolutions
    make earlier frames independent of the copy; only the last 2-frame batch's GroupNorm statistics see it.
    """
    import torch

    model = getattr(vae, "model", vae)
    if scaling_factor is None:
        info = getattr(vae, "info", None)
        scaling_factor = float(info.scaling_factor if info is not None else model.config.scaling_factor)
    z = torch.as_tensor(np.asarray(latents) if not isinstance(latents, torch.Tensor) else latents)
    if z.dim() != 5:
        raise ValueError(f"latents must be (B, T, C, h, w), got {tuple(z.shape)}")
    t = z.shape[1]
    if t % 2 == 0:
        z = torch.cat([z, z[:, -1:]], dim=1)
    p = next(model.parameters())
    out = []
    with torch.inference_mode():
        for i in range(0, z.shape[0], batch_size):
            zz = (z[i:i + batch_size].float() / scaling_factor).permute(0, 2, 1, 3, 4).to(p.device, p.dtype)
            x = model.decode(zz).sample                                  # (b, 3, F, H, W) in ~[-1, 1]
            x = ((x.float().clamp(-1, 1) + 1) * 127.5).round().to(torch.uint8)
            out.append(x.permute(0, 2, 3, 4, 1).cpu().numpy())
    frames = np.concatenate(out)
    want = 1 + 4 * (t - 1)
    if frames.shape[1] < want:  # our bug (or a VAE with another temporal layout)
        raise AssertionError(f"VAE decoded {frames.shape[1]} frames from {t} latent frames, expected >= {want}")
    return frames[:, :want]


def decode_rollout(vae: Any, latents, num_history: int, frames_per_round: int, history_frames: int) -> np.ndarray:
    """Decode a rollout round by round, each VAE call on one round's window (≤ history + round frames, the
    clip length the VAE/model work at), as ReSim decodes each 4-s prediction:

    round 0: latents ``[0, H0 + F0)`` → all its pixel frames; round r ≥ 1 (starting at latent ``s``): the window
    ``[s - history_frames, s + F_r)`` → its last ``4 F_r`` pixel frames. Returns ``(B, 1 + 4 (T - 1), H, W, 3)``.
    """
    t = int(latents.shape[1])
    first_end = min(t, num_history + frames_per_round)
    parts = [decode_latents(vae, latents[:, :first_end])]
    s = first_end
    while s < t:
        e = min(t, s + frames_per_round)
        win = decode_latents(vae, latents[:, max(0, s - history_frames):e])
        parts.append(win[:, -4 * (e - s):])
        s = e
    return np.concatenate(parts, axis=1)


def draw_trajectory(traj: np.ndarray | None, size_px: int = 96, label: str = "", score: float | None = None):
    """BEV panel (PIL image): ego at the bottom centre, x forward = up, y left = left; range fits the path."""
    from PIL import Image, ImageDraw

    img = Image.new("RGB", (size_px, size_px), (40, 40, 40))
    d = ImageDraw.Draw(img)
    cx, cy = size_px / 2, size_px - 10
    d.polygon([(cx, cy - 5), (cx - 4, cy + 4), (cx + 4, cy + 4)], fill=(255, 255, 255))
    if traj is not None:
        t = np.asarray(traj, dtype=np.float64).reshape(-1, 3)
        extent = max(10.0, float(np.abs(t[:, :2]).max()) * 1.1)
        s = (size_px - 16) / extent
        pts = [(cx, cy)] + [(cx - y * s, cy - x * s) for x, y, _ in t]
        d.line(pts, fill=FUTURE_EDGE, width=2)
        for p in pts[1:]:
            d.ellipse([p[0] - 2, p[1] - 2, p[0] + 2, p[1] + 2], fill=FUTURE_EDGE)
    else:
        d.text((4, size_px / 2 - 6), "no trajectory", fill=TEXT)
    if label:
        d.text((3, 2), label[:18], fill=TEXT)
    if score is not None:
        d.text((3, 13), f"score {score:.3f}", fill=(140, 255, 140))
    return img


def _pick(n_hist: int, n_total: int, count: int) -> list[int]:
    """Last history frame, then ``count - 1`` evenly spaced future frames ending at the last one."""
    fut = list(range(n_hist, n_total))
    if not fut:
        return [n_total - 1]
    k = max(1, min(count - 1, len(fut)))
    idx = [fut[round(i * (len(fut) - 1) / max(1, k - 1))] for i in range(k)] if k > 1 else [fut[-1]]
    return ([n_hist - 1] if n_hist > 0 else []) + idx


def contact_sheet(frames: np.ndarray, num_history_px: int, fps_hz: float, *, title: str = "",
                  trajectory: np.ndarray | None = None, count: int = 8, thumb_w: int = 160):
    """A one-row sheet (PIL image) of ``frames`` (T, H, W, 3) uint8: history frame (blue edge) + future (orange),
    time stamps, the ``title`` (command) and a BEV panel of ``trajectory``."""
    from PIL import Image, ImageDraw

    t, h, w, _ = frames.shape
    th = max(8, round(h * thumb_w / w))
    idx = _pick(num_history_px, t, count)
    pad, top = 4, 18
    panel = draw_trajectory(trajectory, size_px=max(th, 64))
    width = pad + len(idx) * (thumb_w + pad) + panel.width + pad
    height = top + max(th, panel.height) + 14 + pad
    sheet = Image.new("RGB", (width, height), SHEET_BG)
    d = ImageDraw.Draw(sheet)
    d.text((pad, 3), title, fill=TEXT)
    x = pad
    for i in idx:
        im = Image.fromarray(frames[i]).resize((thumb_w, th))
        sheet.paste(im, (x, top))
        edge = HISTORY_EDGE if i < num_history_px else FUTURE_EDGE
        d.rectangle([x - 1, top - 1, x + thumb_w, top + th], outline=edge)
        d.text((x + 2, top + th + 2), f"{(i - num_history_px + 1) / fps_hz:+.1f}s", fill=TEXT)
        x += thumb_w + pad
    sheet.paste(panel, (x, top))
    return sheet


def write_gif(frames: np.ndarray, path: Path, fps_hz: float, max_width: int = 320) -> Path:
    from PIL import Image

    h, w = frames.shape[1:3]
    size = (min(w, max_width), round(h * min(w, max_width) / w))
    ims = [Image.fromarray(f).resize(size) for f in frames]
    tmp = path.with_name(path.name + ".tmp")
    ims[0].save(tmp, format="GIF", save_all=True, append_images=ims[1:], duration=round(1000 / fps_hz), loop=0)
    tmp.replace(path)
    return path


def write_rollout(out_dir: str | Path, name: str, frames: np.ndarray, latents: np.ndarray, *,
                  num_history_px: int, fps_hz: float, title: str = "", trajectory: np.ndarray | None = None,
                  meta: dict | None = None) -> dict[str, Path]:
    """Write one rollout's files; returns their paths by kind (mp4, gif, sheet, latents, meta)."""
    from shards.video import encode_mp4

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"mp4": out / f"{name}.mp4", "gif": out / f"{name}.gif", "sheet": out / f"{name}_sheet.png",
             "latents": out / f"{name}_latents.npy", "meta": out / f"{name}_meta.json"}
    even = frames[:, : frames.shape[1] // 2 * 2, : frames.shape[2] // 2 * 2]   # mp4v needs even sizes
    tmp = paths["mp4"].with_name(paths["mp4"].name + ".tmp")
    tmp.write_bytes(encode_mp4(np.ascontiguousarray(even), fps_hz))
    tmp.replace(paths["mp4"])
    write_gif(frames, paths["gif"], fps_hz)
    contact_sheet(frames, num_history_px, fps_hz, title=title, trajectory=trajectory).save(paths["sheet"])
    np.save(paths["latents"], np.asarray(latents, dtype=np.float32))
    info = {"name": name, "num_frames": int(frames.shape[0]), "num_history_frames": int(num_history_px),
            "fps_hz": fps_hz, "frame_size_hw": [int(frames.shape[1]), int(frames.shape[2])],
            "latent_shape": list(np.asarray(latents).shape), "title": title,
            "trajectory": None if trajectory is None else np.asarray(trajectory).tolist(), **(meta or {})}
    paths["meta"].write_text(json.dumps(info, indent=2, default=str))
    return paths


def grid_with_scores(rows: Sequence[dict], fps_hz: float, count: int = 6, thumb_w: int = 128):
    """Planning grid (PIL): one row per candidate, best first: name + score, BEV path, future frames.

    Each row dict: ``name``, ``score``, ``rank``, ``frames`` (T, H, W, 3) uint8, ``num_history_px``, ``trajectory``.
    """
    from PIL import Image, ImageDraw

    sheets = [contact_sheet(r["frames"], r["num_history_px"], fps_hz, count=count, thumb_w=thumb_w,
                            title=f"#{r['rank']}  {r['name']}   reward {r['score']:.4f}",
                            trajectory=r.get("trajectory")) for r in rows]
    width = max(s.width for s in sheets)
    grid = Image.new("RGB", (width, sum(s.height for s in sheets)), SHEET_BG)
    y = 0
    for s in sheets:
        grid.paste(s, (0, y))
        ImageDraw.Draw(grid).line([(0, y), (width, y)], fill=(70, 70, 70))
        y += s.height
    return grid
