"""A distilled student against its teacher, in the same process, on the same histories and starting noise: the
teacher's guided 50-step DDIM (ReSim's sampler: CFG batched, KV cache) is the baseline; beside it the student at
its own steps without guidance, and the teacher itself cut to the student's step count (with and without CFG),
which is what a few steps cost without distillation.

For each sampler: seconds per 4-s rollout (10 latent frames, one chunk) and the distance of its future latents to
the baseline's, as RMS / the baseline's standard deviation (0 = the teacher's output). Only the world model is
timed (no VAE). Histories: the first clips of ``--shards`` (a held-out world), each with its recorded command.
Run: PYTHONPATH=. python bench/distill_speed.py --student runs/distill/student [--teacher synth-world]
     [--shards runs/synth/heldout] [--clips 8] [--threads 2]
"""
from __future__ import annotations

import argparse
import time

import torch

from resim.diffusion.guidance import guidance_preset
from resim.eval.worldeval import eval_clips_from_dataset
from resim.sample.load import PromptSource, load_world_model, run_objective, sampling_defaults
from resim.sample.rollout import Condition, RolloutConfig, rollout


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--student", required=True, help="a `resim train distill` run")
    ap.add_argument("--teacher", default=None, help="default: the student's teacher (its config)")
    ap.add_argument("--shards", default="runs/synth/heldout")
    ap.add_argument("--clips", type=int, default=8)
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--teacher-steps", type=int, default=50)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    d = sampling_defaults(args.student)
    if not d:
        raise SystemExit(f"{args.student}: not a distilled student (no sampling section in its config)")
    teacher_path = args.teacher or d["distilled_from"]
    teacher, _ = load_world_model(teacher_path)
    student, _ = load_world_model(args.student)
    schedule = run_objective(args.student).schedule
    clips = eval_clips_from_dataset(args.shards, limit=args.clips, need_trajectory=False)
    prompts = PromptSource(args.shards, max_tokens=teacher.cfg.max_text_seq_length)
    h = 1 + (clips[0].num_history_frames - 1) // 4
    f = clips[0].latents.shape[0] - h

    def run(model, steps: int, guidance: str) -> tuple[float, torch.Tensor]:
        rc = RolloutConfig(num_steps=steps, history_frames=h, frames_per_round=f, chunk_frames=f,
                           guidance=guidance_preset(guidance))
        out, secs = [], 0.0
        for i in range(0, len(clips), args.batch):
            part = clips[i:i + args.batch]
            hist = torch.stack([torch.from_numpy(c.latents[:h]) for c in part]).float()
            cond = Condition(text=torch.cat([prompts(c.command) for c in part]),
                             null_text=torch.cat([prompts(None) for _ in part]))
            t0 = time.perf_counter()
            res = rollout(model, hist, cond, f, rc, seeds=[1000 + i + j for j in range(len(part))], schedule=schedule)
            secs += time.perf_counter() - t0
            out.append(res.future)
        return secs / len(clips), torch.cat(out)

    run(student, 1, "none")   # warm-up
    t_base, base = run(teacher, args.teacher_steps, "resim")
    ref = float(base.std())
    rows = [(f"teacher, {args.teacher_steps} steps, CFG (baseline)", t_base, 0.0)]
    n = int(d["num_steps"])
    for name, model, steps, g in ((f"student, {n} steps, no CFG", student, n, "none"),
                                  (f"teacher, {n} steps, CFG", teacher, n, "resim"),
                                  (f"teacher, {n} steps, no CFG", teacher, n, "none")):
        t, x = run(model, steps, g)
        rows.append((name, t, float(((x - base) ** 2).mean().sqrt()) / ref))
    print(f"{len(clips)} held-out histories of {args.shards}, {f} latent frames each (one 4-s chunk), batches of "
          f"{args.batch}, {args.threads} torch thread(s); distance = RMS to the baseline's latents / their std")
    for name, t, dist in rows:
        print(f"  {name:<34} {t:7.2f} s per rollout   x{t_base / t:5.1f}   distance {dist:.3f}")


if __name__ == "__main__":
    main()
