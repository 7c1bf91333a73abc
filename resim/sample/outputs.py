"""What a rollout leaves on disk: decoded video (MP4 + GIF), a contact sheet, the latents.

* :func:`decode_latents` – CogVideoX VAE decode of ``(B, T, C, h, w)`` latents (× scaling factor, as stored in
  shards) → ``(B, 1 + r (T - 1), H, W, 3)`` uint8 RGB (r: the VAE's temporal ratio); :func:`decode_rollout` does
  it round by round.
* :func:`draw_trajectory` – a bird's-eye panel of the 8 waypoints (x forward = up, y left = left).
* :func:`contact_sheet` – a grid of frames (last history frame + evenly spaced future frames), with the
  command and the trajectory drawn.
* :func:`write_rollout` – ``DIR/{name}.mp4``, ``.gif``, ``_sheet.png``, ``_latents.npy`` (float32, history +
  generated, exactly what the sampler produced, so runs can be compared bit for bit) and ``_meta.json``.
"""
from __future__ import annotations

import json
from contextlib import contextmanager, nullcontext
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from PIL import Image, ImageDraw

from resim.shards.video import encode_mp4

SHEET_BG = (24, 24, 24)
TEXT = (235, 235, 235)
HISTORY_EDGE = (90, 160, 255)
FUTURE_EDGE = (255, 170, 60)


def temporal_compression(vae: Any) -> int:
    """Pixel frames per latent frame after the first of ``vae`` (a ``VideoVAE`` or a diffusers VAE): 4 for
    CogVideoX's, 1 for a per-frame VAE."""
    info = getattr(vae, "info", None)
    if info is not None:
        return int(info.temporal_compression)
    return int(getattr(getattr(vae, "model", vae).config, "temporal_compression_ratio", 4))


def decode_latents(vae: Any, latents, scaling_factor: float | None = None, batch_size: int = 1) -> np.ndarray:
    """Latents ``(B, T, C, h, w)`` (torch or numpy, VAE latent × scaling factor) → uint8 ``(B, F, H, W, 3)``,
    ``F = 1 + r (T - 1)`` (frame 0 alone, then ``r`` pixel frames per latent frame, as the encoder made them; ``r``
    the VAE's temporal ratio, 4 for CogVideoX's, 1 for a per-frame VAE).

    ``batch_size``: samples decoded in one VAE call (it bounds the memory). diffusers' slicing, which
    ``resim.media.encoders.VideoVAE`` turns on to bound the encoder's memory, would split each call into one decode per
    sample again; it is off during the call. One call for 4 clips of the synthetic world (64 x 96) takes 1/4.2 of
    4 single-clip calls on a 2-core CPU (docs/benchmarks.md, "The VAE in batches": PyTorch's CPU convolution
    skips oneDNN for small batches of one); the uint8 frames agree with single-clip decoding up to 1 level in
    ~2e-5 of the values (floating-point summation order).

    ``vae``: a ``resim.media.encoders.VideoVAE`` (uses its ``.model`` and ``.info.scaling_factor``) or a diffusers
    ``AutoencoderKLCogVideoX``. diffusers decodes in batches of 2 latent frames (the first batch takes 3 when ``T``
    is odd, so frame 0 is upsampled alone) and each batch's GroupNorms normalise over (group channels, time, H, W)
    of that batch; an even ``T`` would give ``4 T`` frames with no "first frame". For an even ``T`` we append a
    padding latent frame (a copy of the last), decode ``T + 1`` as diffusers does and drop the padding's 4 pixel
    frames. The padding shares the last decode batch with the last real latent frame: the causal convolutions
    and the nearest-neighbour temporal upsampling never carry it into earlier frames, and
    :func:`_group_norm_without_padding` computes that batch's GroupNorm statistics over the real frames only, so
    the decoded frames do not depend on the padding at all. Every other batch (and any odd ``T``) is diffusers'
    decode unchanged.
    """
    import torch   # only to decode latents: writing videos and sheets needs numpy and PIL alone

    model = getattr(vae, "model", vae)
    if scaling_factor is None:
        info = getattr(vae, "info", None)
        scaling_factor = float(info.scaling_factor if info is not None else model.config.scaling_factor)
    z = torch.as_tensor(np.asarray(latents) if not isinstance(latents, torch.Tensor) else latents)
    if z.dim() != 5 or z.shape[1] < 1:
        raise ValueError(f"latents must be (B, T, C, h, w) with T >= 1, got {tuple(z.shape)}")
    t = z.shape[1]
    tc = temporal_compression(vae)
    want = 1 + tc * (t - 1)
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    padded = tc > 1 and t % 2 == 0      # a per-frame VAE (ratio 1) upsamples no time: every T decodes to T frames
    if padded:
        z = torch.cat([z, z[:, -1:]], dim=1)
    p = next(model.parameters())
    out = []
    with torch.inference_mode(), _without_slicing(model):
        for i in range(0, z.shape[0], batch_size):
            zz = (z[i:i + batch_size].float() / scaling_factor).permute(0, 2, 1, 3, 4).to(p.device, p.dtype)
            with _group_norm_without_padding(model, zz.shape[2]) if padded else nullcontext():
                x = model.decode(zz).sample                              # (b, 3, F', H, W) in ~[-1, 1]
            if x.shape[2] < want:  # our bug (or a VAE with another temporal layout)
                raise AssertionError(f"VAE decoded {x.shape[2]} frames from {t} latent frames, expected >= {want}")
            x = x[:, :, :want]                                           # the padding's frames never reach uint8
            x = ((x.float().clamp(-1, 1) + 1) * 127.5).round().to(torch.uint8)
            out.append(x.permute(0, 2, 3, 4, 1).cpu().numpy())
    return np.concatenate(out)


@contextmanager
def _without_slicing(model: Any):
    """diffusers' ``use_slicing`` off for the block (a plain attribute of its autoencoders), restored after."""
    had = getattr(model, "use_slicing", None)
    if had:
        model.use_slicing = False
    try:
        yield
    finally:
        if had:
            model.use_slicing = had


@contextmanager
def _group_norm_without_padding(model: Any, num_frames: int):
    """While ``model`` (a diffusers ``AutoencoderKLCogVideoX``) decodes ``num_frames`` latent frames whose last one
    is padding, the GroupNorms of the decoder batch holding the padding take their statistics from the real
    frames only (the padding's own frames are normalised with them too, and dropped by the caller).

    diffusers' ``_decode`` and ``tiled_decode`` call ``model.decoder`` once per frame batch, in order, with
    ``[2 + r, 2, …, 2]`` latent frames (``r = num_frames % 2``), for every batch slice and spatial tile; the
    padding is the last frame of each such run's last batch. In that batch of ``L`` latent frames (2, or 3 when it
    is also the first) a decoder tensor of ``T'`` frames holds the padding in its last
    ``(T' - L % 2) / (L - L % 2)`` frames: frame 0 of an odd batch is upsampled alone, the others 2× in time
    (nearest) per temporal upsampling. A batching other than this is refused (AssertionError), never guessed.
    """
    import torch   # see decode_latents
    import torch.nn.functional as F

    decoder = getattr(model, "decoder", None)
    fb = getattr(model, "num_latent_frames_batch_size", None)
    if not isinstance(decoder, torch.nn.Module) or fb != 2:
        raise ValueError("decoding an even number of latent frames needs a diffusers AutoencoderKLCogVideoX "
                         f"(a .decoder and 2-frame decode batches); got {type(model).__name__} with "
                         f"num_latent_frames_batch_size={fb!r}")
    nb = max(num_frames // fb, 1)
    lengths = [fb + num_frames % fb] + [fb] * (nb - 1)
    state = {"calls": 0, "padding_batch": 0}     # padding_batch: L while the batch with the padding runs, else 0

    def before_decoder(module, args, kwargs):
        sample = args[0] if args else kwargs["sample"]                 # (b, C, L, h, w)
        k = state["calls"] % nb
        if sample.shape[2] != lengths[k]:
            raise AssertionError(f"diffusers decoded batch {k} with {sample.shape[2]} latent frames, expected "
                                 f"{lengths[k]} (batches {lengths}): its decode batching changed")
        state["calls"] += 1
        state["padding_batch"] = lengths[k] if k == nb - 1 else 0

    def group_norm(module, args, out):
        n_lat = state["padding_batch"]
        x = args[0]
        if not n_lat or x.dim() != 5:
            return None
        first, tl = n_lat % 2, x.shape[2]
        if (tl - first) % (n_lat - first):
            raise AssertionError(f"a decoder tensor of {tl} frames in a batch of {n_lat} latent frames")
        keep = tl - (tl - first) // (n_lat - first)
        real = F.group_norm(x[:, :, :keep], module.num_groups, module.weight, module.bias, module.eps)
        return torch.cat([real, out[:, :, keep:]], dim=2)

    handles = [decoder.register_forward_pre_hook(before_decoder, with_kwargs=True)]
    handles += [m.register_forward_hook(group_norm) for m in decoder.modules() if isinstance(m, torch.nn.GroupNorm)]
    try:
        yield
    finally:
        for h in handles:
            h.remove()
    if state["calls"] == 0 or state["calls"] % nb:
        raise AssertionError(f"diffusers called the decoder {state['calls']} times for batches of {lengths}")


def decode_rollout(vae: Any, latents, num_history: int, frames_per_round: int, history_frames: int,
                   batch_size: int = 1) -> np.ndarray:
    """Decode a rollout round by round, each VAE call on one round's window (≤ history + round frames, the
    clip length the VAE/model work at), as ReSim decodes each 4-s prediction:

    round 0: latents ``[0, H0 + F0)`` → all its pixel frames; round r ≥ 1 (starting at latent ``s``): the window
    ``[s - history_frames, s + F_r)`` → its last ``r F_r`` pixel frames (``r``: the VAE's temporal ratio).
    Returns ``(B, 1 + r (T - 1), H, W, 3)``.
    ``batch_size``: rollouts per VAE call (:func:`decode_latents`).
    """
    t, tc = int(latents.shape[1]), temporal_compression(vae)
    first_end = min(t, num_history + frames_per_round)
    parts = [decode_latents(vae, latents[:, :first_end], batch_size=batch_size)]
    s = first_end
    while s < t:
        e = min(t, s + frames_per_round)
        win = decode_latents(vae, latents[:, max(0, s - history_frames):e], batch_size=batch_size)
        parts.append(win[:, -tc * (e - s):])
        s = e
    return np.concatenate(parts, axis=1)


def draw_trajectory(traj: np.ndarray | None, size_px: int = 96, label: str = "", score: float | None = None):
    """BEV panel (PIL image): ego at the bottom centre, x forward = up, y left = left; range fits the path."""
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
