"""Does a world model anchor on its history and use its conditions? A cheap reading off its own loss.

At a high noise level the future is nearly pure noise, so what the model predicts there comes from the history and
the conditions alone (zero-terminal-SNR schedule: at t = 999 the v-target is −x0). On turning clips with a
trajectory this reads, with the same noise draw for every variant:

* the per-future-frame v-loss at each level, beside the loss of copying the last history frame (at t = 999 the two
  are the same measure): a model that anchors on its history beats copy-last on the first future frames, and its
  loss grows with the horizon; one that draws a blurred scene has a flat curve;
* the worth of the history: loss with another clip's history / with its own (> 1 when the model draws from it);
* the worth of the command: loss under the opposite turn / under the recorded one (> 1 when used);
* the worth of the trajectory: loss with the recorded trajectory / without it (< 1 when used), and with the
  mirrored trajectory (y and yaw negated) / with the recorded one (> 1 when used).

Usage:
  python lab/anchor_reading.py --checkpoint RUN [RUN ...] --shards DEV [--clips 32] [--levels 999 950 800]

Prints one block per checkpoint and appends one JSON row each to ``--out`` (default: none).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from resim.diffusion.schedule import add_noise, alphas_cumprod, v_target
from resim.eval.command_loss import OPPOSITE
from resim.sample.load import PromptSource, load_world_model, run_objective
from x0_reading import one_per_episode   # lab/, run as a script: its folder is on sys.path


def _mse(pred: torch.Tensor, target: torch.Tensor, h: int) -> torch.Tensor:
    """Per future frame, ``(T_future,)``."""
    return ((pred.float() - target.float())[:, h:] ** 2).mean(dim=(0, 2, 3, 4))


def _weights_step(final: Path) -> int | None:
    """The step of the weights in ``final/``: that of the newest complete checkpoint saved with them (a run in
    progress logs later steps than its ``final/`` holds); None for a folder without checkpoints (a shipped bundle)."""
    ckpts = final.parent / "checkpoints"
    weights = next((final / n for n in ("ema.safetensors", "model.safetensors") if (final / n).is_file()), None)
    if weights is None or not ckpts.is_dir():
        return None
    saved = [json.loads((d / "meta.json").read_text()) for d in ckpts.iterdir() if (d / "meta.json").is_file()]
    steps = [m["step"] for m in saved if m.get("saved_unix_s", 0) <= weights.stat().st_mtime + 5]
    return max(steps) if steps else None


@torch.no_grad()
def read(checkpoint: str, shards: Path, clips: int, levels: list[int], seed: int = 0) -> dict:
    cs = one_per_episode(shards, clips, keep=lambda c: c.command in OPPOSITE, need_trajectory=True)
    if not cs:
        raise SystemExit(f"{shards}: no turning clips with a trajectory")
    model, info = load_world_model(checkpoint, "cpu", torch.float32)
    ac = alphas_cumprod(run_objective(checkpoint).schedule)
    prompts = PromptSource(shards, None, device="cpu", max_tokens=model.cfg.max_text_seq_length)
    x0 = torch.from_numpy(np.stack([c.latents for c in cs])).float()
    traj = torch.from_numpy(np.stack([c.trajectory for c in cs])).float()
    mirrored = traj * torch.tensor([1.0, -1.0, -1.0])
    own = torch.cat([prompts(c.command) for c in cs])
    opposite = torch.cat([prompts(OPPOSITE[c.command]) for c in cs])
    h, b = cs[0].num_history_latents, len(cs)
    gen = torch.Generator().manual_seed(seed)
    copy_last = ((x0[:, h:] - x0[:, h - 1:h]) ** 2).mean(dim=(0, 2, 3, 4))
    row = {"checkpoint": str(checkpoint), "step": _weights_step(Path(info["checkpoint"])), "clips": b,
           "episodes": len({c.item_id for c in cs}),
           "copy_last_per_frame": copy_last.numpy().round(4).tolist(), "levels": {}}
    for level in levels:
        noise = torch.randn(x0.shape, generator=gen)
        t = torch.zeros(b, x0.shape[1], dtype=torch.long)
        t[:, h:] = level
        x_t = add_noise(x0, noise, t, ac)
        x_t[:, :h] = x0[:, :h]          # the history as the sampler gives it: clean, t = 0
        target = v_target(x0, noise, t, ac)

        def loss(text, tr, x=x_t):
            return _mse(model(x, t, text, tr, None), target, h)

        swapped = x_t.clone()
        swapped[:, :h] = x0.roll(b // 2, dims=0)[:, :h]   # each clip's future beside the history of a clip half the list away (not its fork sibling)
        base = loss(own, None)
        row["levels"][str(level)] = {
            "per_frame": base.numpy().round(4).tolist(),
            "loss": float(base.mean()),
            "history_worth": float(loss(own, None, swapped).mean() / base.mean()),
            "command_worth": float(loss(opposite, None).mean() / base.mean()),
            "trajectory_worth": float(loss(own, traj).mean() / base.mean()),
            "mirrored_over_true": float(loss(own, mirrored).mean() / loss(own, traj).mean())}
    return row


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", nargs="+", required=True, help="world-model run folders (or their final/)")
    p.add_argument("--shards", type=Path, required=True, help="dev dataset folder (never the held-out one)")
    p.add_argument("--clips", type=int, default=32, help="turning clips with a trajectory, one episode after another")
    p.add_argument("--levels", type=int, nargs="+", default=[999, 950, 800])
    p.add_argument("--out", type=Path, help="append one JSON row per checkpoint here")
    a = p.parse_args()
    for ck in a.checkpoint:
        row = read(ck, a.shards, a.clips, a.levels)
        print(f"{ck} (step {row['step']}, {row['clips']} clips of {row['episodes']} episodes)")
        print(f"  copy-last per frame: {' '.join(f'{v:.3f}' for v in row['copy_last_per_frame'][:8])} ...")
        for lv, r in row["levels"].items():
            print(f"  t={lv}: per frame {' '.join(f'{v:.3f}' for v in r['per_frame'][:8])} ... | history worth "
                  f"{r['history_worth']:.3f}, command worth "
                  f"{r['command_worth']:.4f}, with/without trajectory {r['trajectory_worth']:.4f}, mirrored/true "
                  f"{r['mirrored_over_true']:.4f}")
        if a.out:
            with open(a.out, "a") as f:
                f.write(json.dumps(row) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
