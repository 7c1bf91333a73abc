"""Long-horizon drift: does an autoregressive rollout stay a driving video for 30 s?

An autoregressive video model feeds its own frames back as history; small errors compound (Vid2World Sec. 4,
Diffusion Forcing's motivation). A model can score well at 4 s and dissolve into grey blur or saturate by 30 s.
There is no ground truth that far out (the recorded clips are 4.9 s), so drift is measured against the
*statistics of real frames* of the same world:

* per frame: ``sharpness`` (mean absolute intensity gradient, grey levels per pixel: blur lowers it),
  ``contrast`` (standard deviation of the intensity) and ``brightness`` (mean intensity), all on 0..255;
* the real reference: those statistics over every frame of the evaluation clips' recorded video;
* the **drift** at time ``t``: the mean over the statistics of ``|mean over rollouts at t - real mean| / real
  std``: 0 when generated frames look, on these statistics, like real ones; 1 when they are a real standard
  deviation away.

The rollout is the sampler's (:class:`resim.eval.worldeval.WorldRollouts`), chunk after chunk with the
history window sliding over its own output, under one command for the whole horizon.
"""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np
from PIL import Image

from resim.eval.command_following_report import _label
from resim.eval.worldeval import EvalClip, WorldRollouts
from resim.sample.rollout import rollout_num_future_frames

STATS = ("sharpness", "contrast", "brightness")


def frame_stats(video: np.ndarray) -> dict[str, np.ndarray]:
    """``video`` uint8 ``(T, H, W, 3)`` → each statistic of :data:`STATS` per frame, float64 ``(T,)``."""
    if video.ndim != 4 or video.shape[-1] != 3:
        raise ValueError(f"video must be (T, H, W, 3), got {video.shape}")
    g = video.astype(np.float32).mean(axis=-1)
    gx = np.abs(np.diff(g, axis=2)).mean(axis=(1, 2))
    gy = np.abs(np.diff(g, axis=1)).mean(axis=(1, 2))
    return {"sharpness": (gx + gy).astype(np.float64) / 2, "contrast": g.std(axis=(1, 2)).astype(np.float64),
            "brightness": g.mean(axis=(1, 2)).astype(np.float64)}


def real_reference(videos: Sequence[np.ndarray]) -> dict[str, dict[str, float]]:
    """Mean and standard deviation of each statistic over every frame of real ``videos``."""
    per = [frame_stats(v) for v in videos]
    return {s: {"mean": float(np.mean(np.concatenate([p[s] for p in per]))),
                "std": float(np.std(np.concatenate([p[s] for p in per])))} for s in STATS}


def drift_curve(videos: np.ndarray, first_frame: int, fps_hz: float, real: dict[str, dict[str, float]],
                bin_s: float = 1.0) -> list[dict[str, float]]:
    """Per ``bin_s`` of generated video (frames from ``first_frame`` on): each statistic's mean over rollouts
    and frames of the bin, its distance to the real mean in real standard deviations, and the drift."""
    stats = [frame_stats(v[first_frame:]) for v in videos]
    t = videos.shape[1] - first_frame
    per_bin = max(1, int(round(bin_s * fps_hz)))
    rows = []
    for start in range(0, t, per_bin):
        row: dict[str, float] = {"t_s": round((start + per_bin) / fps_hz, 3)}
        zs = []
        for s in STATS:
            m = float(np.mean([st[s][start:start + per_bin].mean() for st in stats]))
            z = abs(m - real[s]["mean"]) / max(real[s]["std"], 1e-6)
            row[s], row[f"z_{s}"] = m, z
            zs.append(z)
        row["drift"] = float(np.mean(zs))
        rows.append(row)
    return rows


def drift_eval(runner: WorldRollouts, clips: Sequence[EvalClip], *, seconds: float = 30.0,
               command: str | None = "Moving forward", bin_s: float = 1.0) -> dict[str, Any]:
    """Roll each clip's history out for ``seconds`` under ``command`` (None: the null prompt); the report
    (``_videos``: the decoded rollouts, history included)."""
    if not clips:
        raise ValueError("no clips to evaluate")
    nh, fps = clips[0].num_history_frames, clips[0].fps_hz
    n_lat = rollout_num_future_frames(seconds, fps)
    videos = runner.generate(clips, [None] * len(clips), [command] * len(clips), num_future_latents=n_lat)
    videos = videos[:, :nh + int(round(seconds * fps))]   # whole latent frames overshoot: keep exactly `seconds`
    real = real_reference([c.frames for c in clips])
    rows = drift_curve(videos, nh, fps, real, bin_s)
    at = {f"{h:g}s": next((r["drift"] for r in rows if r["t_s"] >= h), None) for h in (1, 4, 10, 20, 30)
          if h <= seconds + 1e-9}
    # the recorded future's own drift (its 4 s): what "looks real" reads on this scale
    recorded = drift_curve(np.stack([c.frames for c in clips]), nh, fps, real, bin_s)
    return {"per_second": rows, "drift_at": at, "recorded_future": recorded, "real_reference": real,
            "command": command or "null prompt", "seconds": float(seconds), "generated_frames": int(videos.shape[1] - nh),
            "_videos": videos}


def format_drift(rep: dict) -> str:
    at = "  ".join(f"{k} {v:.2f}" for k, v in rep["drift_at"].items() if v is not None)
    rec = max((r["drift"] for r in rep["recorded_future"]), default=float("nan"))
    lines = [f"drift (mean |stat - real mean| / real std over {', '.join(STATS)}; 0 = real-looking):",
             f"  generated, {rep['command']}: {at}",
             f"  recorded future (its 4 s, worst second): {rec:.2f}"]
    first, last = rep["per_second"][0], rep["per_second"][-1]
    real = rep["real_reference"]
    for s in STATS:
        lines.append(f"  {s:10s} real {real[s]['mean']:6.1f} +- {real[s]['std']:5.1f}   generated "
                     f"{first[s]:6.1f} at {first['t_s']:g} s -> {last[s]:6.1f} at {last['t_s']:g} s")
    return "\n".join(lines)


def plot_drift(rep: dict, path, title: str = ""):
    # matplotlib is slow to import and only the plot needs it
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows, real = rep["per_second"], rep["real_reference"]
    t = [r["t_s"] for r in rows]
    fig, axes = plt.subplots(1, len(STATS) + 1, figsize=(16, 3.6))
    for ax, s in zip(axes, STATS):
        m, sd = real[s]["mean"], real[s]["std"]
        ax.axhspan(m - sd, m + sd, color="tab:green", alpha=0.2, label="real frames (mean +- std)")
        ax.axhline(m, color="tab:green")
        ax.plot(t, [r[s] for r in rows], "o-", ms=3, label="rollout")
        ax.set_xlabel("time after the history (s)")
        ax.set_title(s)
        ax.legend(fontsize=7)
    ax = axes[-1]
    ax.plot(t, [r["drift"] for r in rows], "o-", ms=3, label="rollout")
    ax.plot([r["t_s"] for r in rep["recorded_future"]], [r["drift"] for r in rep["recorded_future"]], "s--",
            label="recorded future")
    ax.set_xlabel("time after the history (s)")
    ax.set_ylabel("real std")
    ax.set_title("drift")
    ax.legend(fontsize=7)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def drift_strip(videos: np.ndarray, first_frame: int, fps_hz: float, path, times_s=(0, 2, 5, 10, 20, 30),
                rows: int = 2):
    """Frames of the first ``rows`` rollouts at ``times_s`` after the last history frame, as one PNG."""
    out = []
    for v in videos[:rows]:
        tiles = []
        for s in times_s:
            f = first_frame - 1 + int(round(s * fps_hz))
            if f < v.shape[0]:
                tiles.append(_label(v[f], f"+{s:g}s"))
        out.append(np.concatenate(tiles, axis=1))
    Image.fromarray(np.concatenate(out, axis=0)).save(path)
    return path
