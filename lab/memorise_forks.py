"""A fitting test of the command path: train a world model on a few forks alone, then roll them out.

    python lab/memorise_forks.py --checkpoint synth-world --shards runs/fork/data_forks --histories 8 \
        --steps 400 --out runs/memorise8          # ~6 min of training + 2 x ~4.5 min of rollouts on 2 CPU cores

Forks (``resim synth --set fork_fraction=F``) record one history under left / forward / right; on a clip whose
history ends before the split only the command tells the futures apart. This script takes the first
``--histories`` three-way forks of ``--shards`` (one clip per branch), and

1. rolls them out with the model as it is (``resim eval commands``' protocol: each history under the three
   commands and the null prompt, guided DDIM, decoded by the VAE that encoded the shards, the flow labeler, and
   the counterfactual-branch score of ``resim/eval/branches.py``);
2. trains the model on those clips alone (v-loss on the future, history clean, the recorded command always
   given, no trajectory; AdamW, one noise level per clip as ``resim_cond_aug`` draws it);
3. measures the command's worth by the loss every 50 steps (``resim.eval.command_loss``) and rolls the clips
   out again.

It is not a training recipe (nothing is held out): it asks whether a model that *has* learnt the command on
these clips steers its rollouts, and whether the labeler can see it. A plain loop rather than ``resim train
world`` because the question needs clean histories, the command never dropped and a clip subset the loader has
no option for; the model, its loss and the evaluation are the library's. Writes OUT/model.pt and OUT/report.json.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from resim.config import from_dict
from resim.diffusion.guidance import guidance_preset
from resim.diffusion.schedule import add_noise, alphas_cumprod, v_target
from resim.eval.branches import counterfactual_groups, format_branches
from resim.eval.command_following import commands_eval
from resim.eval.command_loss import clip_losses, command_loss_report
from resim.eval.worldeval import WorldRollouts, eval_clips_from_dataset, flow_labeler_status
from resim.media.encoders import VideoVAE
from resim.sample.load import PromptSource, encoded_with, load_world_model, run_objective
from resim.sample.rollout import ROLLOUT_PRESETS, RolloutConfig
from resim.shards.schema import COMMANDS


def fork_clips(shards: str, histories: int) -> list:
    """One clip per branch of the first ``histories`` three-way forks of ``shards`` (dataset order)."""
    clips = [c for c in eval_clips_from_dataset(shards, need_trajectory=False) if c.command is not None]
    picked = []
    for g in counterfactual_groups(clips):
        by_cmd = {}
        for i in g:
            by_cmd.setdefault(clips[i].command, clips[i])
        if len(by_cmd) == 3:
            picked += [by_cmd[c] for c in COMMANDS]
        if len(picked) == 3 * histories:
            return picked
    raise SystemExit(f"{shards}: {len(picked) // 3} three-way forks, --histories asks for {histories}")


def rollouts(model, clips, vae, prompts, schedule, steps: int, group_ends: bool = False) -> dict:
    rc = {**ROLLOUT_PRESETS["resim"], "num_steps": steps, "guidance": guidance_preset("resim")}
    runner = WorldRollouts(model, vae, from_dict(RolloutConfig, rc), prompts, seed=0, batch_size=8, schedule=schedule)
    lab, _ = flow_labeler_status()
    rep = commands_eval(runner, clips, lab, group_ends=group_ends)
    fl = rep["flow_labeler"]
    out = {"labeler_commanded": fl["commanded"]["accuracy"], "labeler_matrix": fl["commanded"]["matrix"],
           "labeler_recorded_through_vae": fl["recorded_through_vae"]["accuracy"],
           "mean_heading_deg": fl["mean_yaw_deg"], "branches": rep["branches"]}
    if group_ends:
        ge = rep["flow_labeler_group_ends"]
        out["group_ends"] = {"labeler_commanded": ge["commanded"]["accuracy"], "matrix": ge["commanded"]["matrix"],
                             "recorded_through_vae": ge["recorded_through_vae"]["accuracy"],
                             "recorded_future": ge["recorded_future"]["accuracy"], "mean_heading_deg": ge["mean_yaw_deg"]}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", default="synth-world", help="world-model run folder or shipped name")
    ap.add_argument("--shards", required=True, help="a dataset with forks (resim synth --set fork_fraction=...)")
    ap.add_argument("--histories", type=int, default=8)
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--lr", type=float, default=5e-4)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--ddim-steps", type=int, default=25)
    ap.add_argument("--group-ends", action="store_true",
                    help="also the group-end reading of resim eval commands --set commands.group_ends=true "
                         "(diagnostic)")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(0)
    clips = fork_clips(args.shards, args.histories)
    model, _ = load_world_model(args.checkpoint, "cpu", torch.float32)
    schedule = run_objective(args.checkpoint).schedule
    ac = alphas_cumprod(schedule)
    prompts = PromptSource(Path(args.shards), None, max_tokens=model.cfg.max_text_seq_length)
    vae = VideoVAE(encoded_with(args.checkpoint, args.shards), device="cpu")
    recorded = [c.command for c in clips]
    h = 1 + (clips[0].num_history_frames - 1) // 4
    report = {"clips": [c.key for c in clips], "args": vars(args), "worth": []}

    def worth(step: int) -> None:
        rep = command_loss_report(clip_losses(model.eval(), clips, prompts, ac, seed=123), recorded, (950, 700, 400))
        row = {lv: {k: r[k] for k in ("accuracy", "turn_sign_accuracy", "worth_opposite", "worth_null")}
               for lv, r in rep["levels"].items()}
        report["worth"].append({"step": step, **row})
        print(f"step {step}: worth of the opposite turn at t = 950 / 700 / 400: "
              + " / ".join(f"{100 * r['worth_opposite']:+.1f} %" for r in row.values()), file=sys.stderr)

    print(f"{len(clips)} clips of {args.histories} forks; rolling out before training ...", file=sys.stderr)
    report["before"] = rollouts(model.eval(), clips, vae, prompts, schedule, args.ddim_steps, args.group_ends)
    worth(0)
    x_all = torch.from_numpy(np.stack([c.latents for c in clips])).float()
    text_all = torch.cat([prompts(c) for c in recorded])
    model.requires_grad_(True)
    opt = torch.optim.AdamW(model.parameters(), lr=args.lr, weight_decay=0.0)
    gen = torch.Generator().manual_seed(0)
    t0 = time.perf_counter()
    for step in range(1, args.steps + 1):
        model.train()
        b = torch.randint(len(clips), (args.batch,), generator=gen)
        x0 = x_all[b]
        noise = torch.randn(x0.shape, generator=gen)
        t = torch.zeros(args.batch, x0.shape[1], dtype=torch.long)
        t[:, h:] = torch.randint(0, len(ac), (args.batch, 1), generator=gen)     # one level for the future
        x_t = add_noise(x0, noise, t, ac)
        x_t[:, :h] = x0[:, :h]                                                      # history clean, as sampled
        loss = ((model(x_t, t, text_all[b], None, None) - v_target(x0, noise, t, ac))[:, h:] ** 2).mean()
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        if step % 50 == 0:
            print(f"  step {step}/{args.steps}  loss {loss.item():.4f}  {time.perf_counter() - t0:.0f} s", file=sys.stderr)
            worth(step)
    report["train_seconds"] = round(time.perf_counter() - t0, 1)
    torch.save(model.state_dict(), out / "model.pt")
    report["after"] = rollouts(model.eval().requires_grad_(False), clips, vae, prompts, schedule, args.ddim_steps,
                               args.group_ends)
    (out / "report.json").write_text(json.dumps(report, indent=1))
    for when in ("before", "after"):
        r = report[when]
        print(f"{when}: flow labeler {r['labeler_commanded']:.3f} (recorded through the VAE "
              f"{r['labeler_recorded_through_vae']:.3f}); {format_branches(r['branches'])}")
        if "group_ends" in r:
            g = r["group_ends"]
            print(f"  group-end reading: flow labeler {g['labeler_commanded']:.3f} (recorded through the VAE "
                  f"{g['recorded_through_vae']:.3f}, recorded {g['recorded_future']:.3f}); mean heading "
                  + " / ".join(f"{k} {v:+.1f}" for k, v in g["mean_heading_deg"].items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
