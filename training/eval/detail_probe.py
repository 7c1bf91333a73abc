"""Where is a turn lost? The world model's one-step prediction of a recorded future, read by the flow labeler.

`resim eval commands` reads the command off decoded rollouts, and on the synthetic world every rollout so far read
"forward" while in latent space it landed on the commanded branch (``training.eval.branches``). This probe asks
which noise levels lose the turn, without sampling. For each held-out clip:

* its recorded future latents ``x0`` are noised to level ``t`` (one noise draw per clip, the same at every level),
  the history kept clean, as the sampler feeds it;
* the model predicts ``x0_hat`` in one step under the clip's recorded command (no guidance);
* history + ``x0_hat`` is decoded as a rollout is, and the flow labeler reads its heading change.

The reference is the recorded future itself through the VAE (the ceiling of any world model through this VAE).
Per level the probe reports the **heading kept**: the least-squares slope, through the origin, of the prediction's
heading on the reference's over the clips (1: the turn survives whole; 0: it is gone), with a bootstrap interval
over clips, and the prediction's latent error. Turning clips dominate the slope (it weighs each clip by its
reference heading squared), so clips driving straight need not be removed.

Why it matters: DDIM's last step returns the model's one-step prediction at the last level of its list
(``t = 49`` of 1,000 with 20 trailing steps, SNR 6.4 under CogVideoX's shifted schedule). If the turn is lost in
one step from the *true* noisy future at that level, no sampler setting can bring it back: the model's low-noise
denoising is what must improve. Measured on the shipped model in docs/models/synth-world.md ("Where the turn is
lost").

The model is an argument (as in ``training_losses``); the decoder and prompts come in through a
``training.eval.worldeval.WorldRollouts`` (its ``decode`` and ``text_for``), so the decoding is the rollouts' own.
"""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np
import torch

from training.diffusion.schedule import add_noise, alphas_cumprod
from training.eval.commands import flow_commands
from training.eval.heading_kept import kept_slope, paired_slope_difference
from training.eval.worldeval import EvalClip
from training.sampling.ddim import v_to_x0_eps

DEFAULT_LEVELS = (0, 49, 99, 199, 499)


@torch.no_grad()
def one_step_predictions(model: Any, latents: torch.Tensor, num_history: int, text: torch.Tensor, level: int,
                         noise: torch.Tensor, schedule: Any = None, batch_size: int = 8) -> torch.Tensor:
    """``latents`` (B, T, C, h, w) float32, the first ``num_history`` frames history (fed clean, level 0), the rest
    the future noised to ``level`` with ``noise`` (B, T - num_history, C, h, w); ``text`` (B, L, D) prompt
    embeddings. Returns the model's one-step clean estimate of the future, (B, T - num_history, C, h, w) float32."""
    ac = alphas_cumprod(schedule)
    if not 0 <= level < len(ac):
        raise ValueError(f"level {level} not in [0, {len(ac)})")
    params = list(model.parameters())
    dev, dtype = (params[0].device, params[0].dtype) if params else (latents.device, torch.float32)
    out = []
    for i in range(0, latents.shape[0], batch_size):
        lat, eps = latents[i:i + batch_size].to(dev), noise[i:i + batch_size].to(dev)
        b, t_all = lat.shape[:2]
        fut = lat[:, num_history:]
        x_t = add_noise(fut, eps, torch.full((b,), level), ac.to(dev))
        x = torch.cat([lat[:, :num_history], x_t], dim=1)
        t = torch.zeros(b, t_all, dtype=torch.long, device=dev)
        t[:, num_history:] = level
        v = model(x.to(dtype), t, text[i:i + batch_size].to(dev, dtype))[:, num_history:].float()
        out.append(v_to_x0_eps(x_t, v, float(ac[level]))[0].cpu())
    return torch.cat(out)


def detail_probe(runner: Any, clips: Sequence[EvalClip], labeler: Any, levels: Sequence[int] = DEFAULT_LEVELS,
                 seed: int = 0, log: Any = None) -> dict:
    """The probe of the module docstring on ``clips`` (one geometry) with ``runner.model``. Returns a JSON-able
    report: per level the headings, the heading kept (slope and interval), the labeler's accuracy against the
    recorded commands, and the latent error; the same for the recorded future through the VAE and the originals."""
    if not clips:
        raise ValueError("detail_probe needs at least one clip")
    h = runner.history_latents(clips[0])
    nh, fps = clips[0].num_history_frames, clips[0].fps_hz
    lat = torch.from_numpy(np.stack([c.latents for c in clips])).float()
    cmds = [c.command for c in clips]
    text = torch.cat([runner.text_for(c) for c in cmds])
    noise = torch.randn(lat[:, h:].shape, generator=torch.Generator().manual_seed(seed))

    def read(videos):
        got, yaws = flow_commands(videos, nh, fps, labeler)
        return yaws, float(np.mean([g == c for g, c in zip(got, cmds)]))

    orig_yaw, orig_acc = read(np.stack([c.frames for c in clips]))
    ref_yaw, ref_acc = read(runner.decode_recorded(clips))
    rep: dict = {"clips": len(clips), "levels": list(levels), "commands": cmds,
                 "original": {"yaw_deg": orig_yaw, "labeler_accuracy": orig_acc},
                 "recorded_through_vae": {"yaw_deg": ref_yaw, "labeler_accuracy": ref_acc,
                                          "kept": kept_slope(ref_yaw, orig_yaw, seed=seed)},
                 "per_level": []}
    ac = alphas_cumprod(runner.schedule)
    for lvl in levels:
        x0 = one_step_predictions(runner.model, lat, h, text, int(lvl), noise, runner.schedule,
                                  batch_size=runner.batch_size)
        yaw, acc = read(runner.decode(clips, torch.cat([lat[:, :h], x0], dim=1)))
        a = float(ac[int(lvl)])
        rep["per_level"].append({
            "level": int(lvl), "snr": a / (1 - a) if a < 1 else float("inf"),
            "yaw_deg": yaw, "labeler_accuracy": acc, "kept": kept_slope(yaw, ref_yaw, seed=seed),
            "latent_mse": float(((x0 - lat[:, h:]) ** 2).mean()),
        })
        if log is not None:
            k = rep["per_level"][-1]["kept"]
            log(f"level {lvl}: heading kept {k['slope']:.2f} [{k['ci95'][0]:.2f}, {k['ci95'][1]:.2f}], "
                f"labeler {acc:.2f}")
    return rep


def paired_kept_difference(rep: dict, other: dict, n_boot: int = 2000, seed: int = 0) -> list[dict]:
    """Heading kept of ``rep`` minus ``other`` per level both have, with a 95 % paired bootstrap interval over
    clips (the same clips and noise: each resample takes the same clips from both). Raises ``ValueError`` when the
    two reports were not read on the same clips (their recorded futures through the VAE differ)."""
    ref, ref_o = np.asarray(rep["recorded_through_vae"]["yaw_deg"]), np.asarray(other["recorded_through_vae"]["yaw_deg"])
    if ref.shape != ref_o.shape or not np.allclose(ref, ref_o) or rep["commands"] != other["commands"]:
        raise ValueError("the two detail reports were not read on the same clips")
    theirs = {r["level"]: r["yaw_deg"] for r in other["per_level"]}
    return [{"level": r["level"], **paired_slope_difference(r["yaw_deg"], theirs[r["level"]], ref, n_boot, seed)}
            for r in rep["per_level"] if r["level"] in theirs]


def format_probe(rep: dict) -> str:
    ref, org = rep["recorded_through_vae"], rep["original"]
    lines = [f"{rep['clips']} clips; heading kept = slope of the prediction's heading on the recorded future's "
             "through the VAE (1 = the turn survives, 0 = gone), 95 % bootstrap over clips",
             f"{'':>28} {'SNR':>7} {'heading kept':>22} {'labeler':>8} {'latent MSE':>11}",
             f"{'originals':>28} {'':>7} {'':>22} {org['labeler_accuracy']:>8.3f} {'':>11}",
             f"{'recorded through the VAE':>28} {'':>7} "
             f"{_kept(ref['kept']) + ' (of originals)':>22} {ref['labeler_accuracy']:>8.3f} {0.0:>11.4f}"]
    for r in rep["per_level"]:
        lines.append(f"{'one step from level ' + str(r['level']):>28} {r['snr']:>7.2f} {_kept(r['kept']):>22} "
                     f"{r['labeler_accuracy']:>8.3f} {r['latent_mse']:>11.4f}")
    return "\n".join(lines)


def _kept(k: dict) -> str:
    return f"{k['slope']:.2f} [{k['ci95'][0]:.2f}, {k['ci95'][1]:.2f}]"


def plot_probe(rep: dict, path, title: str = "", others: Sequence[tuple[str, dict]] = (), name: str = "") -> None:
    """Heading kept against the level's SNR (log axis), one line per report: ``rep`` (labelled ``name``) and each
    ``(label, report)`` of ``others``."""
    import matplotlib                                   # heavy, and only the CLI draws
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    for label, r in [(name, rep), *others]:
        rows = [x for x in r["per_level"] if np.isfinite(x["snr"])]
        s = [x["snr"] for x in rows]
        k = np.array([x["kept"]["slope"] for x in rows])
        lo = np.array([x["kept"]["ci95"][0] for x in rows])
        hi = np.array([x["kept"]["ci95"][1] for x in rows])
        line, = ax.semilogx(s, k, "o-", label=label or "one-step prediction")
        ax.fill_between(s, lo, hi, color=line.get_color(), alpha=0.15)
    ax.axhline(1.0, color="k", lw=0.8, ls="--", label="the recorded future through the VAE")
    ax.axhline(0.0, color="grey", lw=0.8)
    ax.set_xlabel("SNR of the noisy future the model sees (its noise level's)")
    ax.set_ylabel("heading kept (flow labeler)")
    ax.set_title(title or f"{rep['clips']} clips: how much of the turn one denoising step keeps", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
