"""`resim eval closed-loop`'s report: what each reading is called, the text table, the scatter plot and the strip
of frames (the evaluation itself: ``resim.eval.policy_ranking``)."""
from __future__ import annotations

import numpy as np
from PIL import Image

from resim.eval.command_following_report import _label

READINGS = {   # report key: (label, short label for tables, the score array it ranks by)
    "proxy_vs_true_on_true_frames": ("IDM proxy on the true frames", "proxy, true frames", "true_proxy"),
    "world_model_vs_true": ("world model (IDM proxy on its video)", "proxy, world model", "wm_proxy"),
    "reward_vs_true_on_true_frames": ("Video2Reward x100 on the true frames", "V2R, true frames", "true_reward"),
    "world_model_reward_vs_true": ("world model (Video2Reward x100 on its video)", "V2R, world model", "wm_reward"),
    "replay_vs_true": ("world model replaying the true loop's plans (IDM proxy)", "proxy, WM replay", "replay_proxy"),
}


GAPS = {   # per-drive distances from the true loop (``rep["gaps"]``): column label, what it measures
    "plan_gap_m": ("plan gap", "how far the policy's plans inside the world model land from its plans at the same "
                               "decisions in the true world (last waypoint, each in its own ego frame)"),
    "path_gap_m": ("replay gap", "how far the path the IDM reads off the world model's replay of the true plans "
                                 "lies from the path it reads off the true frames"),
}


def format_closed_loop(rep: dict) -> str:
    readings = [(key, label) for key, (label, *_) in READINGS.items() if key in rep]
    names = rep["policies"]
    gaps = rep.get("gaps", {})
    gap_cols = [k for k in GAPS if any(k in g for g in gaps.values())]
    head = (f"{'policy':34s} {'true score':>10s}" + "".join(f" {READINGS[key][1]:>22s}" for key, _ in readings)
            + "".join(f" {GAPS[k][0]:>14s}" for k in gap_cols))
    lines = [f"closed loop: {len(names)} policies x {len(rep['states'])} starting states "
             "(mean composed score, 100 = the expert; rank in brackets)", head]
    for n in names:
        t = rep[readings[0][0]]["per_policy"][n]
        row = f"{n:34s} {t['true']:6.1f} [{t['true_rank']}]"
        for key, _ in readings:
            m = rep[key]["per_policy"][n]
            row += f" {m['model']:18.1f} [{m['model_rank']}]"
        row += "".join(f" {gaps.get(n, {}).get(k, float('nan')):12.2f} m" for k in gap_cols)
        lines.append(row)
    for k in gap_cols:
        lines.append(f"{GAPS[k][0]}: {GAPS[k][1]} (mean over states)")
    for key, label in readings:
        a = rep[key]
        ci = f"[{a['ci95'][0]:.2f}, {a['ci95'][1]:.2f}]" if a["ci95"] else "n/a"
        lines.append(f"Spearman, {label} vs true: {a['spearman']:.2f} (95% bootstrap over states {ci})"
                     + (f"; largest disagreements: {', '.join(a['largest_disagreements'])}"
                        if a["largest_disagreements"] else ""))
    return "\n".join(lines)


def plot_closed_loop(rep: dict, path):
    # matplotlib is slow to import and only the plot needs it
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [k for k in READINGS if k in rep]
    fig, axes = plt.subplots(1, len(keys), figsize=(5.0 * len(keys), 4.4), squeeze=False)
    for ax, key in zip(axes[0], keys):
        a = rep[key]
        for n, v in a["per_policy"].items():   # one colour per policy, the same in every panel
            ax.scatter(v["true"], v["model"], s=40, label=n)
        ax.plot([0, 100], [0, 100], color="0.7", lw=0.8)
        ax.set_xlabel("true score (simulator)")
        ax.set_ylabel("Video2Reward x 100" if "reward" in key else "IDM proxy score")
        ax.set_title(f"{READINGS[key][0]}:\nSpearman {a['spearman']:.2f}", fontsize=9)
    axes[0][0].legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def closed_loop_strip(rep: dict, path, first_frame: int, fps_hz: float = 10.0, times_s=(0, 2, 4, 6, 8)):
    """The first starting state, one row per (policy, loop): frames at ``times_s`` after the last history frame,
    the true world's row, then the world model's, then (with the replay) the world model's under the true plans.
    A PNG; None when there are no videos."""
    videos = rep.get("_videos") or {}
    rows = []
    for name in rep["policies"]:
        for loop in ("true", "world model", "replay"):
            v = videos.get((loop, name))
            if v is None:
                continue
            tiles = [_label(v[first_frame + int(round(t * fps_hz))], f"{loop}: {name[:22]}" if i == 0 else f"+{t:g}s")
                     for i, t in enumerate(times_s) if first_frame + int(round(t * fps_hz)) < len(v)]
            rows.append(np.concatenate(tiles, axis=1))
    if not rows:
        return None
    w = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 0), (0, w - r.shape[1]), (0, 0))) for r in rows]
    Image.fromarray(np.concatenate(rows, axis=0)).save(path)
    return path
