"""Run observability, rank 0 only: metrics.jsonl, TensorBoard, a tqdm bar, a loss-curve PNG.

``metrics.jsonl`` gets one JSON object per optimizer step (``step``, ``loss``, ``lr``,
``grad_norm``, ``samples_per_s`` and, on GPU, ``tokens_per_s`` and ``mfu``, plus the model's
own logs). On resume, lines for steps after the checkpoint are dropped first, so the file
reads as one uninterrupted run.
"""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any

import yaml
from tqdm import tqdm

from resim.config import safe_yaml

METRICS = "metrics.jsonl"


def read_metrics(run_dir: str | Path) -> list[dict]:
    p = Path(run_dir) / METRICS
    if not p.is_file():
        return []
    out = []
    for line in p.read_text().splitlines():
        line = line.strip()
        if line:
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:
                continue  # a line cut by a kill mid-write
    return out


def truncate_after(run_dir: str | Path, step: int) -> None:
    """Keep only records with ``step <= step`` (called when resuming from a checkpoint at ``step``)."""
    p = Path(run_dir) / METRICS
    if not p.is_file():
        return
    keep = [r for r in read_metrics(run_dir) if r.get("step", 0) <= step]
    tmp = p.with_name(p.name + ".part")
    tmp.write_text("".join(json.dumps(r) + "\n" for r in keep))
    tmp.replace(p)


class MetricsLogger:
    def __init__(self, run_dir: str | Path, *, enabled: bool, total_steps: int, start_step: int,
                 tensorboard: bool = True, progress_bar: bool = True, log_every: int = 1):
        self.run_dir = Path(run_dir)
        self.enabled = enabled
        self.log_every = log_every
        self._tb = None
        self._bar = None
        self._f = None
        if not enabled:
            return
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self._f = open(self.run_dir / METRICS, "a", buffering=1)
        if tensorboard:
            try:
                from torch.utils.tensorboard import SummaryWriter
            except ImportError as e:  # tensorboard is in the train extra; say so instead of failing the run
                print(f"[resim] TensorBoard disabled ({e}); pip install 'resim[train]'", file=sys.stderr)
            else:
                self._tb = SummaryWriter(log_dir=str(self.run_dir / "tensorboard"), purge_step=start_step + 1)
        if progress_bar:
            self._bar = tqdm(total=total_steps, initial=start_step, desc="train", unit="step",
                             dynamic_ncols=True, file=sys.stderr)

    def log(self, record: dict[str, Any]) -> None:
        if not self.enabled:
            return
        self._f.write(json.dumps(record) + "\n")
        step = record["step"]
        if self._tb is not None and step % self.log_every == 0:
            for k, v in record.items():
                if k != "step" and isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
                    self._tb.add_scalar(f"train/{k}", v, step)
        if self._bar is not None:
            self._bar.update(1)
            if step % self.log_every == 0:
                post = {"loss": f"{record['loss']:.4g}", "lr": f"{record['lr']:.2e}"}
                if "samples_per_s" in record:
                    post["samp/s"] = f"{record['samples_per_s']:.1f}"
                if record.get("mfu") is not None:
                    post["mfu"] = f"{record['mfu']:.1%}"
                self._bar.set_postfix(post, refresh=False)

    def message(self, text: str) -> None:
        if not self.enabled:
            return
        if self._bar is not None:
            self._bar.write(text, file=sys.stderr)
        else:
            print(text, file=sys.stderr, flush=True)

    def close(self, loss_curve: bool = True) -> Path | None:
        if not self.enabled:
            return None
        if self._bar is not None:
            self._bar.close()
        if self._tb is not None:
            self._tb.close()
        self._f.close()
        return plot_loss_curve(self.run_dir) if loss_curve else None


def _run_title(run_dir: Path) -> str:
    """"<model> loss (<folder>)" from the run's config.yaml: a folder name alone ("trainer", "final") says little."""
    try:
        name = (safe_yaml((run_dir / "config.yaml").read_text()) or {}).get("model_name")
    except (OSError, yaml.YAMLError, AttributeError):
        name = None
    return f"{name} loss ({run_dir.name})" if isinstance(name, str) and name else run_dir.name


def plot_loss_curve(run_dir: str | Path) -> Path | None:
    """RUN_DIR/loss_curve.png from metrics.jsonl (loss, and a moving average, vs step)."""
    recs = [r for r in read_metrics(run_dir) if isinstance(r.get("loss"), (int, float))]
    if not recs:
        return None
    import matplotlib   # slow to import: only for the loss-curve PNG
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = [r["step"] for r in recs]
    loss = [r["loss"] for r in recs]
    w = max(1, len(loss) // 20)
    smooth = [sum(loss[max(0, i - w + 1): i + 1]) / len(loss[max(0, i - w + 1): i + 1]) for i in range(len(loss))]
    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=100)
    ax.plot(steps, loss, lw=0.8, alpha=0.5, label="loss")
    ax.plot(steps, smooth, lw=1.5, label=f"moving avg ({w})")
    ax.set_xlabel("optimizer step")
    ax.set_ylabel("loss")
    ax.set_title(_run_title(Path(run_dir)))
    if all(v > 0 for v in loss) and max(loss) / max(min(loss), 1e-12) > 50:
        ax.set_yscale("log")
    ax.legend()
    fig.tight_layout()
    out = Path(run_dir) / "loss_curve.png"
    fig.savefig(out)
    plt.close(fig)
    return out


def plot_bars(groups: dict[str, dict[str, float | None]], path: str | Path, title: str = "",
              ylabel: str = "m") -> Path:
    """Grouped bars: ``{"ADE": {"IDM": 0.4, "constant velocity": 1.2}, "FDE": {...}}``."""
    # matplotlib is slow to import and only the plot needs it
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(dict.fromkeys(k for g in groups.values() for k in g))
    fig, ax = plt.subplots(figsize=(1.6 + 1.4 * len(groups) * max(len(names), 1) / 2, 3.2), dpi=110)
    width = 0.8 / max(len(names), 1)
    for j, name in enumerate(names):
        xs = [i + j * width for i in range(len(groups))]
        vals = [g.get(name) for g in groups.values()]
        bars = ax.bar(xs, [v if v is not None else 0 for v in vals], width, label=name)
        for b, v in zip(bars, vals):
            ax.annotate("n/a" if v is None else f"{v:.3g}", (b.get_x() + b.get_width() / 2, b.get_height()),
                        ha="center", va="bottom", fontsize=7)
    ax.set_xticks([i + width * (len(names) - 1) / 2 for i in range(len(groups))], list(groups))
    ax.set_ylabel(ylabel)
    ax.legend(fontsize=7)
    ax.set_title(title, fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return Path(path)
