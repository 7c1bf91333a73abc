"""Pictures and text of ``resim eval commands``: confusion matrices, fidelity vs horizon, and one history
rolled out under the three commands beside the recorded future (image strip + animated GIF)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from resim.eval.branches import format_branches
from resim.sample.outputs import write_gif
from resim.shards.schema import COMMANDS

SHORT = {"Turning left": "left", "Moving forward": "forward", "Turning right": "right"}


def _confusion_line(name: str, c: dict) -> str:
    """One row of a confusion table: accuracy, count and recall per command."""
    per = "  ".join(f"{SHORT[k]} {v:.2f}" if v is not None else f"{SHORT[k]} n/a" for k, v in c["per_command"].items())
    return f"  {name:<24} {c['accuracy']:.3f}  (n={c['n']}; {per})"


def format_commands(rep: dict) -> str:
    fl = rep["flow_labeler"]
    lines = ["command accuracy (flow labeler on the generated future; 1/3 = ignores the command):"]
    for name in ("commanded", "null_prompt", "null_prompt_vs_recorded", "recorded_future", "recorded_through_vae"):
        c = fl.get(name)
        if c is None:                                  # reports written before the VAE row existed
            continue
        lines.append(_confusion_line(name, c))
    if isinstance(rep.get("idm"), dict):
        lines.append("command accuracy (IDM trajectory → command):")
        for name, c in rep["idm"].items():
            lines.append(f"  {name:<24} {c['accuracy']:.3f}  (n={c['n']})")
    lines.append("mean heading change of the future (deg, left +): " + "  ".join(
        f"{SHORT.get(k, k)} {v:+.1f}" for k, v in fl["mean_yaw_deg"].items()))
    if "mirror_check_deg" in fl:                      # reports written before the check have none
        lines.append("  the labeler's own lean on these videos, (heading + heading mirrored) / 2 (deg; ~0: a lean "
                     "above is the videos'): " + "  ".join(f"{SHORT.get(k, k)} {v:+.1f}"
                                                            for k, v in fl["mirror_check_deg"].items()))
    ge = rep.get("flow_labeler_group_ends")
    if ge:
        lines.append("group-end reading (diagnostic: frames inside each latent group redrawn from the group ends):")
        lines += [_confusion_line(name, ge[name]) for name in ("commanded", "recorded_future", "recorded_through_vae")]
        lines.append("  mean heading (deg, left +): " + "  ".join(f"{SHORT.get(k, k)} {v:+.1f}"
                                                               for k, v in ge["mean_yaw_deg"].items()))
    if "branches" in rep:                             # reports written before forks were scored have none
        lines.append(format_branches(rep["branches"]))
    if "trajectory_branches" in rep:
        lines.append(format_branches(rep["trajectory_branches"], title="trajectory branches (null prompt + a "
                                     "sibling's recorded trajectory)", given="trajectory given"))
    lines.append("fidelity under the recorded command (PSNR dB / SSIM; copy-last-frame baseline):")
    for r in rep["fidelity"]["per_horizon"]:
        lines.append(f"  {r['horizon_s']:>4g} s  model {r['psnr_model']:.2f} / {r['ssim_model']:.3f}   "
                     f"copy-last {r['psnr_copy_last_frame']:.2f} / {r['ssim_copy_last_frame']:.3f}")
    return "\n".join(lines)


def plot_commands(rep: dict, path: str | Path, title: str = "") -> Path:
    # matplotlib is slow to import and only the plot needs it
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fl = rep["flow_labeler"]
    panels = [("commanded", "commanded"), ("null_prompt", "null prompt"), ("recorded_future", "recorded future"),
              ("recorded_through_vae", "recorded, through the VAE")]
    panels = [p for p in panels if p[0] in fl]
    fig, axes = plt.subplots(1, len(panels) + 1, figsize=(4 * (len(panels) + 1), 3.8))
    for ax, (key, name) in zip(axes, panels):
        m = np.asarray(fl[key]["matrix"], float)
        rows = m / np.maximum(m.sum(1, keepdims=True), 1)
        ax.imshow(rows, vmin=0, vmax=1, cmap="Blues")
        for i in range(3):
            for j in range(3):
                ax.text(j, i, f"{int(m[i, j])}", ha="center", va="center",
                        color="white" if rows[i, j] > 0.6 else "black")
        ax.set_xticks(range(3), [SHORT[c] for c in COMMANDS])
        ax.set_yticks(range(3), [SHORT[c] for c in COMMANDS])
        ax.set_xlabel("flow labeler reads")
        ax.set_ylabel("recorded" if key.startswith("recorded") else "conditioned on")
        ax.set_title(f"{name}: acc {fl[key]['accuracy']:.2f}")
    ax = axes[len(panels)]
    rows = rep["fidelity"]["per_horizon"]
    hs = [r["horizon_s"] for r in rows]
    ax.plot(hs, [r["psnr_model"] for r in rows], "o-", label="world model")
    ax.plot(hs, [r["psnr_copy_last_frame"] for r in rows], "s--", label="copy last frame")
    ax.set_xlabel("horizon (s)")
    ax.set_ylabel("PSNR (dB)")
    ax.set_title("fidelity vs horizon")
    ax.legend()
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return Path(path)


def _label(img: np.ndarray, text: str) -> np.ndarray:
    im = Image.fromarray(img)
    ImageDraw.Draw(im).text((2, 1), text, fill=(255, 255, 255))
    return np.asarray(im)


def command_strip(videos: dict[str, np.ndarray], index: int, num_history_frames: int, fps_hz: float,
                  path: str | Path, every_s: float = 0.8) -> Path:
    """Rows: recorded future, then the rollouts under left / forward / right (and the null prompt); columns:
    the last history frame, then every ``every_s`` seconds. ``videos[name]`` is ``(N, T, H, W, 3)`` uint8."""
    names = ["recorded", *COMMANDS, *(["null prompt"] if "null prompt" in videos else [])]
    t = videos["recorded"].shape[1]
    step = max(1, int(round(every_s * fps_hz)))
    cols = list(range(num_history_frames - 1, t, step))
    rows = []
    for name in names:
        v = videos[name][index]
        tiles = [_label(v[f], f"{SHORT.get(name, name)} {(f - num_history_frames + 1) / fps_hz:+.1f}s") for f in cols]
        rows.append(np.concatenate(tiles, axis=1))
    Image.fromarray(np.concatenate(rows, axis=0)).save(path)
    return Path(path)


def command_gif(videos: dict[str, np.ndarray], index: int, fps_hz: float, path: str | Path) -> Path:
    """The recorded future and the three commanded rollouts side by side, as an animated GIF."""
    names = ["recorded", *COMMANDS]
    frames = np.concatenate([np.stack([_label(f, SHORT.get(n, n)) for f in videos[n][index]]) for n in names], axis=2)
    return write_gif(frames, Path(path), fps_hz, max_width=frames.shape[2])
