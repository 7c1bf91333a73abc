"""How much the command is worth to the world model, read off its denoising loss (no sampling, no labeler).

`resim eval commands` reads the command off *decoded rollouts*, so its answer is capped by the VAE (a
reconstruction that loses the motion reads "forward") and blurred by undertrained sampling. This reads the
model directly: each held-out clip's future, noised to a fixed level with one noise draw, is denoised with
the history clean under each prompt (left / forward / right and the null prompt), and the v-prediction
losses are compared. Two numbers per noise level:

* **command accuracy by the loss** (a diffusion classifier, as in Li et al. 2023, "Your Diffusion Model is
  Secretly a Zero-Shot Classifier"): the share of clips whose recorded command gives the lowest loss of
  the three. Chance is 1/3 and a model that ignores the text sits there.
* **worth**: ``loss(prompt) / loss(recorded command) − 1``, averaged over clips, for the opposite turn (turning
  clips) and for the null prompt: how much worse the model predicts the future when told the wrong thing.

Reported again on the **counterfactual clips** where a dataset has them: clips with the same history (byte-identical
history frames) and different recorded commands, as the synthetic world's forks make them
(``resim synth --set fork_fraction=...``). There the history cannot tell the futures apart, only the command can.

Reads clips with a recorded command; the model is an argument, as in ``training_losses``.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch

from resim.diffusion.schedule import add_noise, alphas_cumprod, v_target
from resim.eval.branches import counterfactual_clips
from resim.eval.command_following import balanced_clips
from resim.eval.report import format_protocol
from resim.eval.worldeval import EvalClip, eval_clips_from_dataset
from resim.sample.load import PromptSource, SamplingInputError, load_world_model, run_objective
from resim.shards.reader import ShardReadError
from resim.shards.schema import COMMANDS

OPPOSITE = {"Turning left": "Turning right", "Turning right": "Turning left"}
DEFAULT_LEVELS = (950, 700, 400)


class CommandLossInputError(ValueError):
    """A checkpoint, dataset or level that cannot be evaluated (one line, for the CLI)."""


def _history_latents(clip: EvalClip) -> int:
    return clip.num_history_latents


@torch.no_grad()
def clip_losses(model: Any, clips: Sequence[EvalClip], text_for: Callable[[str | None], torch.Tensor],
                alphas_cumprod: torch.Tensor, levels: Sequence[int] = DEFAULT_LEVELS, seed: int = 0,
                batch_size: int = 8, device: str = "cpu") -> np.ndarray:
    """v-MSE over each clip's future latent frames, ``(N clips, len(levels), 4 prompts)`` float64; prompts in the
    order ``COMMANDS`` + null. History frames are clean (t = 0, as at inference); the future is noised to the level
    with one noise draw per clip and level (the same under every prompt), so the prompts are compared paired."""
    if not clips:
        raise ValueError("no clips")
    h, t_lat = _history_latents(clips[0]), clips[0].latents.shape[0]
    if any(_history_latents(c) != h or c.latents.shape[0] != t_lat for c in clips):
        raise ValueError("clips must share their geometry (history and latent frames)")
    n_levels = int(alphas_cumprod.shape[0])
    if any(not 0 <= lv < n_levels for lv in levels):
        raise ValueError(f"noise levels must be in [0, {n_levels - 1}], got {list(levels)}")
    texts = [text_for(c).to(device) for c in COMMANDS] + [text_for(None).to(device)]
    ac = alphas_cumprod.to(device)
    gen = torch.Generator().manual_seed(seed)
    out = np.zeros((len(clips), len(levels), len(texts)))
    for i in range(0, len(clips), batch_size):
        part = clips[i:i + batch_size]
        x0 = torch.from_numpy(np.stack([c.latents for c in part])).float().to(device)   # (B, T, C, h, w)
        b = x0.shape[0]
        for j, level in enumerate(levels):
            noise = torch.randn(x0.shape, generator=gen).to(device)
            t = torch.zeros(b, t_lat, dtype=torch.long, device=device)
            t[:, h:] = int(level)
            x_t = add_noise(x0, noise, t, ac)
            x_t[:, :h] = x0[:, :h]     # the history as the sampler feeds it: clean, at t = 0
            target = v_target(x0, noise, t, ac)
            for k, emb in enumerate(texts):
                pred = model(x_t, t, emb.expand(b, *emb.shape[1:]), None, None)
                err = ((pred.float() - target.float())[:, h:] ** 2).mean(dim=(1, 2, 3, 4))
                out[i:i + b, j, k] = err.double().cpu().numpy()
    return out


def command_loss_report(losses: np.ndarray, recorded: Sequence[str], levels: Sequence[int]) -> dict:
    """Accuracy by the loss and worth per level (see the module docstring), overall and per recorded command."""
    rec = np.array([COMMANDS.index(c) for c in recorded])
    turning = np.array([c in OPPOSITE for c in recorded])
    opp = np.array([COMMANDS.index(OPPOSITE[c]) if c in OPPOSITE else -1 for c in recorded])
    rows = {}
    for j, level in enumerate(levels):
        L = losses[:, j]                                     # (N, 4)
        own = L[np.arange(len(L)), rec]
        picked = L[:, :3].argmin(1)
        row = {"accuracy": float((picked == rec).mean()),
               "worth_null": float((L[:, 3] / own - 1).mean()),
               "per_command": {c: {"clips": int((rec == k).sum()),
                                   "accuracy": float((picked[rec == k] == k).mean()) if (rec == k).any() else None}
                               for k, c in enumerate(COMMANDS)},
               "confusion": [[int(((rec == a) & (picked == p)).sum()) for p in range(3)] for a in range(3)]}
        if turning.any():
            row["worth_opposite"] = float((L[turning, opp[turning]] / own[turning] - 1).mean())
            row["turn_sign_accuracy"] = float((L[turning, opp[turning]] > own[turning]).mean())
        rows[str(int(level))] = row
    return {"levels": rows, "clips": len(recorded), "chance_accuracy": 1 / 3}


def format_command_loss(rep: dict) -> str:
    lines = [f"command read by the model's own loss ({rep['clips']} clips; accuracy: lowest loss of the three "
             "commands = the recorded one, chance 0.33)",
             f"{'noise level':>11}  {'accuracy':>8}  {'left/fwd/right':>16}  {'turn sign':>9}  "
             f"{'worth opposite':>14}  {'worth null':>10}"]
    for level, r in rep["levels"].items():
        per = "/".join("-" if v["accuracy"] is None else f"{v['accuracy']:.2f}" for v in r["per_command"].values())
        sign = f"{r['turn_sign_accuracy']:.2f}" if "turn_sign_accuracy" in r else "-"
        opp = f"{100 * r['worth_opposite']:+.1f} %" if "worth_opposite" in r else "-"
        lines.append(f"{level:>11}  {r['accuracy']:>8.2f}  {per:>16}  {sign:>9}  {opp:>14}  "
                     f"{100 * r['worth_null']:+9.1f} %")
    return "\n".join(lines)


def run_command_loss(checkpoint: str, shards: str | Path, items: Sequence[str] | None, *, limit: int | None = None,
                     levels: Sequence[int] = DEFAULT_LEVELS, seed: int = 0, batch_size: int = 8,
                     text_encoder: str | Path | None = None, device: str = "cpu",
                     split: dict | None = None) -> tuple[dict, str]:
    """``resim eval command-loss`` without the printing: the clips of ``shards`` with a recorded command (of the
    episodes ``items``; ``None``: all; ``split``: which side of the dataset's split they are, for the protocol), at
    most ``limit`` with the commands in turn; the report and its text."""
    try:
        clips = eval_clips_from_dataset(shards, items=items, need_trajectory=False)
    except (FileNotFoundError, ShardReadError) as e:
        raise CommandLossInputError(f"--shards: {e}") from None
    clips = [c for c in clips if c.command is not None]
    if limit is not None:
        clips = balanced_clips(clips, limit)
    if not clips:
        raise CommandLossInputError(f"no clips with a command in {shards}")
    try:
        model, info = load_world_model(checkpoint, device, torch.float32)
        ac = alphas_cumprod(run_objective(checkpoint).schedule)
        prompts = PromptSource(Path(shards), text_encoder, device=device, max_tokens=model.cfg.max_text_seq_length)
    except SamplingInputError as e:
        raise CommandLossInputError(str(e)) from None
    bad = [lv for lv in levels if not 0 <= lv < len(ac)]
    if bad:
        raise CommandLossInputError(f"--levels {bad[0]} is outside 0..{len(ac) - 1} (the run's schedule)")
    print(f"[resim eval command-loss] {len(clips)} clips x {len(levels)} noise levels x 4 prompts ...", file=sys.stderr)
    t0 = time.perf_counter()
    losses = clip_losses(model, clips, prompts, ac, levels=levels, seed=seed, batch_size=batch_size, device=device)
    recorded = [c.command for c in clips]
    rep = command_loss_report(losses, recorded, levels)
    idx, n_hist = counterfactual_clips(clips)
    if idx:
        rep["counterfactual"] = {"histories": n_hist,
                                 **command_loss_report(losses[idx], [recorded[i] for i in idx], levels)}
    rep["per_clip"] = [{"key": c.key, "recorded": c.command, "loss": losses[i].round(6).tolist()}
                       for i, c in enumerate(clips)]
    rep["protocol"] = {"clips": len(clips), "episodes": len({c.item_id for c in clips}),
                       "recorded_commands": {c: recorded.count(c) for c in sorted(set(recorded))},
                       "shards": str(shards), "split": split, "world_model": {**info, "device": device},
                       "conditions": "future noised to each level (one draw per clip and level, shared by the "
                                     "prompts), history clean, no trajectory; prompts left/forward/right/null",
                       "seconds": round(time.perf_counter() - t0, 2)}
    text = [format_protocol(rep["protocol"]), format_command_loss(rep)]
    if "counterfactual" in rep:
        cf = rep["counterfactual"]
        text += [f"counterfactual clips: {cf['clips']} clips of {cf['histories']} histories shared by clips of another "
                 "command (only the command tells their futures apart)", format_command_loss(cf)]
    return rep, "\n".join(text)


def plot_command_loss(rep: dict, path, title: str = ""):
    """Accuracy by the loss per noise level (against chance) and the worth of the opposite / null prompt."""
    # matplotlib is slow to import and only the plot needs it
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    levels = list(rep["levels"])
    rows = [rep["levels"][k] for k in levels]
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    ax = axes[0]
    x = np.arange(len(levels))
    cf = rep.get("counterfactual")
    w = 0.4 if cf else 0.8
    ax.bar(x - (w / 2 if cf else 0), [r["accuracy"] for r in rows], w, color="tab:blue", label=f"all {rep['clips']} clips")
    if cf:
        ax.bar(x + w / 2, [cf["levels"][k]["accuracy"] for k in levels], w, color="tab:green",
               label=f"{cf['clips']} counterfactual clips")
    ax.axhline(rep["chance_accuracy"], color="k", ls="--", lw=1, label="chance")
    ax.set_xticks(x, levels)
    ax.set_ylim(0, 1)
    ax.set_xlabel("noise level of the future (t)")
    ax.set_ylabel("lowest loss = recorded command")
    ax.legend(fontsize=8)
    ax = axes[1]
    ax.bar(x - 0.2, [100 * r.get("worth_opposite", np.nan) for r in rows], 0.4, label="opposite turn")
    ax.bar(x + 0.2, [100 * r["worth_null"] for r in rows], 0.4, label="null prompt")
    ax.axhline(0, color="k", lw=0.8)
    ax.set_xticks(x, levels)
    ax.set_xlabel("noise level of the future (t)")
    ax.set_ylabel("loss increase (%)")
    ax.set_title("loss over the recorded command's, all clips", fontsize=10)
    ax.legend()
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
