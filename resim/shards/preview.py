"""PNG contact sheet of one sample: frames (history framed blue, future orange), command, heading change,
and the future trajectory drawn top-down (forward up, left to the left).

Needs matplotlib and OpenCV (``pip install 'resim[pipeline]'``); imported inside the functions.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from resim.shards.video import decode_mp4

HISTORY_COLOR = "#1f77b4"
FUTURE_COLOR = "#ff7f0e"


def pick_frames(num_frames: int, num_history: int, max_frames: int = 12) -> list[int]:
    """Evenly spread frame indices that always include the first, last-history and last frames."""
    if num_frames <= max_frames:
        return list(range(num_frames))
    must = {0, num_history - 1, num_frames - 1}
    rest = np.linspace(0, num_frames - 1, max_frames - len(must) + 2).round().astype(int).tolist()
    picks = sorted(must | set(rest))
    while len(picks) > max_frames:  # drop interior picks that are not required
        for i in picks[1:-1]:
            if i not in must:
                picks.remove(i)
                break
    return picks


def render_preview(sample: dict, out_png, max_frames: int = 12, cols: int = 6) -> Path:
    """Write the contact sheet of a decoded ``sample`` (frames decoded on demand) to ``out_png``."""
    # matplotlib is slow to import and only the contact sheet needs it (the light install may lack it)
    try:
        import matplotlib
    except ImportError as e:
        raise RuntimeError("preview needs matplotlib: pip install 'resim[pipeline]'") from e
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    meta = sample["meta.json"]
    frames = sample.get("frames")
    if frames is None:
        frames = decode_mp4(sample["frames.mp4"])
    nh, fps = meta["num_history_frames"], meta["fps_hz"]
    picks = pick_frames(len(frames), min(nh, len(frames)), max_frames)
    rows = math.ceil(len(picks) / cols)
    h, w = frames.shape[1:3]
    fig_w = cols * 2.2 + 3.2
    fig = plt.figure(figsize=(fig_w, rows * 2.2 * h / w + 1.6), dpi=100)
    grid = fig.add_gridspec(rows, cols + 2, left=0.02, right=0.98, top=0.80, bottom=0.10, wspace=0.08, hspace=0.25)
    for n, i in enumerate(picks):
        ax = fig.add_subplot(grid[n // cols, n % cols])
        ax.imshow(frames[i])
        hist = i < nh
        color = HISTORY_COLOR if hist else FUTURE_COLOR
        ax.add_patch(Rectangle((0, 0), w - 1, h - 1, fill=False, lw=3, ec=color))
        ax.set_title(f"#{i} {(i - (nh - 1)) / fps:+.1f}s", fontsize=8, color=color)
        ax.set_xticks([])
        ax.set_yticks([])
    ax = fig.add_subplot(grid[:, cols:])
    traj = sample.get("traj.npy")
    if traj is not None:
        t = np.asarray(traj, np.float32)
        xs, ys = -t[:, 1], t[:, 0]  # top-down: lateral (left = -x on the plot), forward up
        ax.plot(np.r_[0, xs], np.r_[0, ys], "-o", color=FUTURE_COLOR, ms=3)
        for x, y, yaw in zip(xs, ys, t[:, 2]):
            ax.arrow(x, y, -math.sin(yaw) * 0.8, math.cos(yaw) * 0.8, head_width=0.4, color="k", lw=0.5)
        ax.plot([0], [0], "s", color=HISTORY_COLOR, ms=8, label="ego at last history frame")
        span = max(np.abs(np.r_[xs, ys]).max(), 5.0) * 1.15
        half = max(span / 2, np.abs(xs).max() * 1.2)
        ax.set_xlim(-half, half)
        ax.set_ylim(-1, span)
        ax.set_aspect("equal")
        ax.set_title(f"trajectory ({len(t)} wp)", fontsize=9)
        ax.set_xlabel("left  <-  y (m)  ->  right", fontsize=7)
        ax.set_ylabel("x forward (m)", fontsize=7)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    else:
        ax.axis("off")
        ax.text(0.5, 0.5, "no trajectory\n(source has no poses)", ha="center", va="center", fontsize=9)
    haz = meta.get("hazard")
    haz_s = "" if haz is None else f" | hazard {haz} (score {meta.get('infraction_score')})"
    flow = meta.get("command_flow")
    trj = meta.get("command_trajectory")
    fig.suptitle(
        f"{sample['__key__']}\n"
        f"{meta['command']}  (from {meta['command_source']}, conf {meta['confidence']:.2f})   "
        f"heading change {meta['yaw_deg']:+.1f} deg over {meta['num_future_frames'] / fps:.1f} s\n"
        f"{meta['source']} {meta['item_id']} @ {meta['start_s']:.1f}s | flow: {flow} | trajectory: {trj}{haz_s}",
        fontsize=9, x=0.02, ha="left")
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png)
    plt.close(fig)
    return out_png
