"""Named run configs per trainable model: ``PRESETS[model_name][preset] -> RunConfig dict``.

World model stages follow ReSim's Table S.1 (appendix of arXiv 2506.09981): 40 A100s, ~14 days.

| stage | DiT | LoRA | traj. enc. | data | resolution | batch | LR | steps |
|---|---|---|---|---|---|---|---|---|
| 1 | trainable | - | - | OpenDV | 512x896 | 80 | 1e-5 | 20K |
| 2 | frozen | trainable | trainable | OpenDV, NAVSIM, CARLA | 256x448 | 160 | 5e-5 | 80K |
| 3 | trainable | trainable | trainable | OpenDV, NAVSIM, CARLA | 512x896 | 80 | 5e-5 | 50K |

Values the paper does not give are ours and marked ``# ours``: LoRA rank 64, warmup 500 steps, equal
source weights in stages 2-3, batch 2 or 4 per GPU (80 = 2 x 40 GPUs, 160 = 4 x 40), bf16 + FSDP2 +
activation checkpointing. Resolution is the pixel size the latents were encoded at (the VAE makes
512x896 -> 64x112 latents); the data should have been encoded at it (mixed shapes train, one shape per batch).
Stage 2/3 start from the previous stage: ``--set model.init_weights=RUN1/final/model.safetensors``;
stage 1 from CogVideoX-2B: ``--set model.pretrained=/path/to/CogVideoX-2b/transformer``.
"""
from __future__ import annotations

import copy

_OBJECTIVE = {"noise_mode": "resim_cond_aug", "num_history_frames": 3}  # 9 history frames -> 3 latent frames

_STAGE_COMMON = {
    "model_name": "world",
    "optim": {"warmup_steps": 500, "schedule": "constant", "weight_decay": 0.0, "grad_clip_norm": 1.0},  # ours
    "trainer": {"precision": "bf16", "parallel": "fsdp", "activation_checkpointing": True,
                "checkpoint_every_steps": 1000, "keep_checkpoints": 3, "log_every_steps": 10},
    "data": {"num_workers": 4},
}


def _stage(n: int, *, trainable: str, lora: int, hw: tuple[int, int], bs: int, gbs: int, lr: float, steps: int,
           weights: dict, paper: dict) -> dict:
    d = copy.deepcopy(_STAGE_COMMON)
    d["preset"] = f"stage{n}"
    d["model"] = {"preset": "cogvideox-2b", "trainable": trainable, "lora_rank": lora, "objective": dict(_OBJECTIVE),
                  "latent_hw": [hw[0] // 8, hw[1] // 8], "latent_frames": 13}
    d["data"].update({"batch_size_per_gpu": bs, "source_weights": weights})
    d["optim"]["lr"] = lr
    d["trainer"].update({"steps": steps, "global_batch_size": gbs})
    d["reference"] = {"source": "ReSim Table S.1", "gpus": 40, **paper}
    return d


# the synthetic world's model reads the command also through a pooled text vector in AdaLN
# (training/models/config.py: TextPoolConfig): through joint attention alone it learnt to ignore it
_SYNTH_TEXT_POOL = {"text_pool": {"enabled": True}}

WORLD_PRESETS: dict[str, dict] = {
    # seconds on a laptop CPU: the tiny DiT (2 layers, width 32) on dummy/synthetic shards
    "tiny": {
        "model_name": "world", "preset": "tiny",
        "model": {"preset": "tiny", "trainable": "all", "objective": dict(_OBJECTIVE), "latent_hw": [8, 12]},
        "data": {"batch_size_per_gpu": 2, "num_workers": 0},
        "optim": {"lr": 1e-3, "warmup_steps": 2},
        "trainer": {"steps": 20, "checkpoint_every_steps": 10, "precision": "fp32", "tensorboard": True},
    },
    # the synthetic world on a CPU (configs/models/synth-world, docs/models/synth-world.md): shards of
    # configs/pipeline/synthetic.yaml encoded by configs/models/synth-vae. History noise up to t = 200 (not the
    # whole range as ReSim at scale: a 5 M model in half an hour learns little from near-pure-noise histories).
    # Every source may drop its trajectory (ReSim keeps CARLA's, whose hazards the history cannot show; the
    # synthetic explorer's commands come from its trajectory, so the command still says where it goes): the
    # command alone must steer, which is what `resim eval commands` measures.
    "synth": {
        "model_name": "world", "preset": "synth",
        "model": {"preset": "synth", "trainable": "all", "latent_hw": [8, 12],
                  "objective": {**_OBJECTIVE, "cond_aug_max_t": 200, "text_drop_prob": 0.3,
                                "trajectory_keep_sources": []}},
        "data": {"batch_size_per_gpu": 8, "num_workers": 1},
        "optim": {"lr": 5e-4, "warmup_steps": 100, "schedule": "cosine", "min_lr_ratio": 0.1, "grad_clip_norm": 1.0},
        "trainer": {"steps": 4000, "checkpoint_every_steps": 500, "precision": "fp32", "ema_decay": 0.999,
                    "log_every_steps": 20},
    },
    # second stage of the synthetic world model: from "synth"'s EMA weights, ReSim's full-range history noise
    # (t_aug ~ U[0, N)): with its history often unreadable, the model must take the motion from the command.
    # After "synth" alone the command changed the prediction by 0.4 % (left vs right, held-out clips): the clean
    # history already says where the car goes on most training clips, and the model had learnt to read it alone.
    # --set model.init_weights=RUN_SYNTH/final/ema.safetensors
    "synth-control": {
        "model_name": "world", "preset": "synth-control",
        "model": {"preset": "synth", "trainable": "all", "latent_hw": [8, 12],
                  "objective": {**_OBJECTIVE, "cond_aug_max_t": None, "text_drop_prob": 0.3,
                                "trajectory_keep_sources": []}},
        "data": {"batch_size_per_gpu": 8, "num_workers": 1},
        "optim": {"lr": 5e-4, "warmup_steps": 50, "schedule": "cosine", "min_lr_ratio": 0.1, "grad_clip_norm": 1.0},
        "trainer": {"steps": 2500, "checkpoint_every_steps": 500, "precision": "fp32", "ema_decay": 0.999,
                    "log_every_steps": 20},
    },
    "stage1": _stage(1, trainable="dit", lora=0, hw=(512, 896), bs=2, gbs=80, lr=1e-5, steps=20_000,
                     weights={"opendv": 1.0},
                     paper={"dit": "trainable", "lora": "-", "traj_enc": "-", "data": "OpenDV",
                            "resolution": "512x896", "batch": 80, "lr": 1e-5, "steps": 20_000}),
    "stage2": _stage(2, trainable="lora+new", lora=64, hw=(256, 448), bs=4, gbs=160, lr=5e-5, steps=80_000,
                     weights={"opendv": 1.0, "navsim": 1.0, "carla": 1.0},
                     paper={"dit": "frozen", "lora": "trainable", "traj_enc": "trainable",
                            "data": "OpenDV, NAVSIM, CARLA", "resolution": "256x448", "batch": 160, "lr": 5e-5,
                            "steps": 80_000}),
    "stage3": _stage(3, trainable="all", lora=64, hw=(512, 896), bs=2, gbs=80, lr=5e-5, steps=50_000,
                     weights={"opendv": 1.0, "navsim": 1.0, "carla": 1.0},
                     paper={"dit": "trainable", "lora": "trainable", "traj_enc": "trainable",
                            "data": "OpenDV, NAVSIM, CARLA", "resolution": "512x896", "batch": 80, "lr": 5e-5,
                            "steps": 50_000}),
}

# third stage (an experiment, not the shipped model): from "synth-control"'s EMA weights, the command also
# through a pooled text vector in AdaLN (training/models/config.py: TextPoolConfig, zero-initialised so
# training starts from the earlier model); otherwise "synth-control". After "synth-control" the command was
# worth ~1 % of the loss; 7,300 steps with this path raised that to ~18 % but did not make rollouts turn
# (docs/models/synth-world.md, "The pooled-text experiment"). --set model.init_weights=RUN_CONTROL/final/ema.safetensors
WORLD_PRESETS["synth-command"] = copy.deepcopy(WORLD_PRESETS["synth-control"])
WORLD_PRESETS["synth-command"].update(preset="synth-command")
WORLD_PRESETS["synth-command"]["model"]["overrides"] = dict(_SYNTH_TEXT_POOL)
WORLD_PRESETS["synth-command"]["trainer"]["steps"] = 9000

# fourth stage of the shipped synthetic world model (docs/models/synth-world.md, stage 4): from "synth-control"'s
# weights, on counterfactual forks (`resim synth --set fork_fraction=1.0`: one history, three recorded futures) with
# the command as the only condition. Histories stay readable (t_aug <= 200, as at sampling) and the trajectory and
# actions are always dropped, so on a fork clip nothing but the command tells the futures apart; with the full-range
# history noise and the trajectory of "synth-command", 1,500 steps on forks did not move held-out rollouts.
# The command is dropped 10 % of the time: enough null-prompt training for CFG.
# --set model.init_weights=RUN_CONTROL/final/ema.safetensors
WORLD_PRESETS["synth-fork"] = copy.deepcopy(WORLD_PRESETS["synth-control"])
WORLD_PRESETS["synth-fork"].update(preset="synth-fork")
WORLD_PRESETS["synth-fork"]["model"]["objective"].update(cond_aug_max_t=200, text_drop_prob=0.1,
                                                         trajectory_drop_prob=1.0, action_drop_prob=1.0)
WORLD_PRESETS["synth-fork"]["optim"]["lr"] = 3e-4
WORLD_PRESETS["synth-fork"]["trainer"]["steps"] = 2000

# fifth stage of the shipped synthetic world model (docs/models/synth-world.md, "Stage 5"): "synth-fork" with ReSim's
# trajectory given half the time and the command half the time, independently, so on a CARLA-layout fork clip a
# quarter of the steps have only the trajectory to tell the branches apart (OpenDV-layout clips carry none).
# Per-frame actions stay dropped: ReSim conditions through the trajectory encoder alone, and `resim eval` and
# `resim sample` pass no actions unless asked (--actions-from-trajectory), so the rollouts see what training saw.
# --set model.init_weights=STAGE_4C/final/ema.safetensors
WORLD_PRESETS["synth-fork-traj"] = copy.deepcopy(WORLD_PRESETS["synth-fork"])
WORLD_PRESETS["synth-fork-traj"].update(preset="synth-fork-traj")
WORLD_PRESETS["synth-fork-traj"]["model"]["objective"].update(text_drop_prob=0.5, trajectory_drop_prob=0.5)

# stage 8b of the shipped synthetic world model (docs/models/synth-world.md, "Stages 8 and 8b"): the plan nearly
# always given. In closed loop (docs/closed_loop.md) the world model is driven by a plan alone (null prompt,
# trajectory guidance), and under the true loop's own plans stage 6's video moved the car 5-8 m from where the true
# world does: "synth-fork-traj" gave the trajectory on a quarter of the clips. Here it is kept on 90 % of the clips
# that carry one (10 % dropped: the unconditional branch of the guidance), hazardous explorers included, so the
# plan decides on most steps.
# The command is still dropped half the time. What mattered was the share of clips with a plan: on a world that is
# half OpenDV layout (no trajectory) the plan reached 40 % of the clips and the closed loop did not change (stage 8);
# on a CARLA-layout world (every clip has one; 8b) it reached 90 % and the model follows the plan.
# --set model.init_weights=RUN_STAGE6/final/ema.safetensors
# Stage 9 (shipped) is this preset again, from 8b's weights, on a world with pace forks (synthworld/pace.py), where
# only the trajectory's speed tells the futures apart.
WORLD_PRESETS["synth-fork-plan"] = copy.deepcopy(WORLD_PRESETS["synth-fork-traj"])
WORLD_PRESETS["synth-fork-plan"].update(preset="synth-fork-plan")
WORLD_PRESETS["synth-fork-plan"]["model"]["objective"].update(trajectory_drop_prob=0.1)
WORLD_PRESETS["synth-fork-plan"]["trainer"]["steps"] = 1500

# The synthetic world model from scratch, one run (docs/lab/2026-12-07-world-recipe.md; scripts/train_synth_world.sh).
# Data: configs/pipeline/synth-world.yaml, 5-Hz clips of 3 + 20 frames through the per-frame VAE (a turn
# stays a turn frame by frame: docs/lab/2026-12-07-representation.md), forks + experts + hazardous explorers.
# The command reaches the model through the T5 tokens and a pooled text vector in AdaLN; the trajectory is dropped
# on half of the clips of every source, so the command alone must steer there; ReSim's history noise over the full
# range (App. B.2). Constant learning rate after warm-up: the run is trained in budgeted segments across sessions
# (trainer.max_wall_s, --resume), and a constant rate makes the segmented run the same run as an unbroken one.
WORLD_PRESETS["synth-world"] = {
    "model_name": "world", "preset": "synth-world",
    "model": {"preset": "synth", "trainable": "all", "latent_hw": [32, 48], "latent_frames": 23,
              # the per-frame VAE's 4 x 32 x 48 latents in 8 x 8 patches: 24 tokens per frame, as 8x latents in 2 x 2
              "overrides": {**_SYNTH_TEXT_POOL, "in_channels": 4, "out_channels": 4, "patch_size": 8},
              "objective": {**_OBJECTIVE, "cond_aug_max_t": None, "text_drop_prob": 0.2, "trajectory_drop_prob": 0.5,
                            "trajectory_keep_sources": [], "action_drop_prob": 1.0, "latent_frame_dt_s": 0.2}},
    "data": {"batch_size_per_gpu": 8, "num_workers": 1},
    "optim": {"lr": 3e-4, "warmup_steps": 200, "schedule": "constant", "grad_clip_norm": 1.0},
    "trainer": {"steps": 100_000, "checkpoint_every_steps": 500, "keep_checkpoints": 2, "precision": "fp32",
                "ema_decay": 0.999, "log_every_steps": 20},
}

VAE_PRESETS: dict[str, dict] = {
    # the synthetic world's VAE (configs/models/synth-vae, docs/models/synth-vae.md): 64x96 clips of
    # configs/pipeline/synthetic.yaml, 17-frame crops; wider at the low-resolution levels, where width is cheap
    "synth": {
        "model_name": "vae", "preset": "synth",
        "model": {"block_out_channels": [16, 32, 64, 64], "norm_num_groups": 8, "clip_frames": 17},
        "data": {"batch_size_per_gpu": 2, "num_workers": 0, "load_frames": True},
        "optim": {"lr": 5e-4, "warmup_steps": 100, "schedule": "cosine", "min_lr_ratio": 0.1},
        "trainer": {"steps": 2000, "checkpoint_every_steps": 200, "precision": "fp32", "log_every_steps": 20},
    },
    # seconds on a CPU (tests)
    "tiny": {
        "model_name": "vae", "preset": "tiny",
        "model": {"block_out_channels": [8, 8, 8, 8], "norm_num_groups": 2, "clip_frames": 9},
        "data": {"batch_size_per_gpu": 1, "num_workers": 0, "load_frames": True},
        "optim": {"lr": 1e-3, "warmup_steps": 1},
        "trainer": {"steps": 4, "checkpoint_every_steps": 2, "precision": "fp32"},
    },
}

# the synthetic world's per-frame VAE (its candidate: lab/runs/synth-vae-frame; docs/lab/2026-12-07-representation.md): ratio
# 1, so a turn is drawn frame by frame (no latent group to cross-fade), and 2x spatial (2 levels) with 4 channels:
# at 8x and 4x the frames came back too smooth for the flow labeler to follow the asphalt and the lane dashes
# (0.50 and 0.85-0.88 of the heading kept, whatever the loss). 9-frame clips of the 5-Hz clips of
# configs/pipeline/synth-world.yaml, cropped to 32 x 48 (the network is convolutional; CogVideoX trains its VAE on
# crops too): the full-resolution first level costs 4x less a step.
VAE_PRESETS["synth-frame"] = copy.deepcopy(VAE_PRESETS["synth"])
VAE_PRESETS["synth-frame"].update(preset="synth-frame")
VAE_PRESETS["synth-frame"]["model"].update(block_out_channels=[32, 64], latent_channels=4, crop_hw=[32, 48],
                                           temporal_compression_ratio=1, clip_frames=9, gradient_weight=1.0)
VAE_PRESETS["synth-frame"]["data"]["batch_size_per_gpu"] = 4
VAE_PRESETS["synth-frame"]["trainer"]["steps"] = 1200

# stage 1b of the shipped synthetic-world VAE (docs/models/synth-vae.md, "Stage 1b"): "synth"'s weights fine-tuned
# with detail terms and a spatio-temporal patch adversary (training/vae_gan.py), the first loss that kept the ego
# motion through the VAE; EMA weights exported. Constant learning rate: on a leased GPU the run is stopped by
# trainer.max_wall_s (scripts/gpu_synth_round.sh), and the shipped weights are its step 1,568.
# --set model.init_weights=RUN_SYNTH/final/vae/diffusion_pytorch_model.safetensors
VAE_PRESETS["synth-adv"] = copy.deepcopy(VAE_PRESETS["synth"])
VAE_PRESETS["synth-adv"].update(preset="synth-adv")
VAE_PRESETS["synth-adv"]["model"].update(l1_weight=1.0, gradient_weight=2.0, adversarial_weight=0.1,
                                         discriminator_width=32)
VAE_PRESETS["synth-adv"]["data"]["batch_size_per_gpu"] = 16
VAE_PRESETS["synth-adv"]["optim"].update(lr=2e-4, warmup_steps=50, schedule="constant")
VAE_PRESETS["synth-adv"]["trainer"].update(steps=1568, ema_decay=0.998, checkpoint_every_steps=100)

# stage 1c (docs/models/synth-vae.md, "Stage 1c"): stage 1b's decoder alone, fine-tuned with MSE (the objective
# the PSNR target measures) at a decaying learning rate. The encoder is frozen, so the latents, and the world
# model trained on them, stay exactly as they were: the decoder can be replaced without retraining synth-world.
# --set model.init_weights=STAGE_1B_FOLDER/diffusion_pytorch_model.safetensors
VAE_PRESETS["synth-dec"] = copy.deepcopy(VAE_PRESETS["synth"])
VAE_PRESETS["synth-dec"].update(preset="synth-dec")
VAE_PRESETS["synth-dec"]["model"].update(trainable="decoder")
VAE_PRESETS["synth-dec"]["data"]["batch_size_per_gpu"] = 4
VAE_PRESETS["synth-dec"]["optim"].update(lr=1e-4, warmup_steps=50, schedule="cosine", min_lr_ratio=0.1)
VAE_PRESETS["synth-dec"]["trainer"].update(steps=3000, ema_decay=0.998, checkpoint_every_steps=250)
# stage 1c' (shipped): "synth-dec"'s decoder + 500 steps with the spatial-gradient L1 as well. MSE alone returned the
# mean where the latent leaves the detail open and cost the flow labeler 3 of 48 fresh clips; the gradient term
# gives the edges back (docs/models/synth-vae.md, "Stage 1c"). --set model.init_weights=SYNTH_DEC_FOLDER/...
VAE_PRESETS["synth-dec-detail"] = copy.deepcopy(VAE_PRESETS["synth-dec"])
VAE_PRESETS["synth-dec-detail"].update(preset="synth-dec-detail")
VAE_PRESETS["synth-dec-detail"]["model"].update(gradient_weight=1.0)
VAE_PRESETS["synth-dec-detail"]["optim"].update(lr=5e-5, warmup_steps=20, schedule="constant")
VAE_PRESETS["synth-dec-detail"]["trainer"].update(steps=500)

# guidance + step distillation of a world model into a few-step student (training/distill.py: CausVid's ODE
# regression); --set model.teacher=RUN (default: the shipped synthetic world model)
DISTILL_PRESETS: dict[str, dict] = {
    # the shipped synthetic world model -> 4 steps without CFG, on clips of its own data pipeline; the first epoch
    # rolls every clip out with the teacher (50 guided steps), later ones reuse those trajectories. The teacher is
    # guided at 15 -> 1, twice ReSim's 7.5: the regression passes on only part of the guidance's effect, and from
    # the harder-guided teacher the student keeps the 7.5-guided teacher's command-following (docs/distill.md:
    # within 2.4 points on two fresh fork worlds, from two training sets; distilled from 7.5, 11.6-13 points short)
    "synth": {
        "model_name": "distill", "preset": "synth",
        "model": {"teacher": "synth-world", "student_steps": 4, "teacher_steps": 50, "guidance": "resim",
                  "guidance_scale": 15.0},
        "data": {"batch_size_per_gpu": 8, "num_workers": 1},
        "optim": {"lr": 1e-4, "warmup_steps": 50, "schedule": "cosine", "min_lr_ratio": 0.1, "grad_clip_norm": 1.0},
        "trainer": {"steps": 2000, "checkpoint_every_steps": 250, "precision": "fp32", "ema_decay": 0.999,
                    "log_every_steps": 20},
    },
    # seconds on a CPU (tests): --set model.teacher=A_TINY_WORLD_RUN
    "tiny": {
        "model_name": "distill", "preset": "tiny",
        "model": {"teacher": "synth-world", "student_steps": 2, "teacher_steps": 8, "guidance": "resim"},
        "data": {"batch_size_per_gpu": 2, "num_workers": 0},
        "optim": {"lr": 1e-3, "warmup_steps": 2},
        "trainer": {"steps": 20, "checkpoint_every_steps": 10, "precision": "fp32"},
    },
}

# model name -> its presets; `resim train NAME` exists for every name here (the reward model adds "reward")
PRESETS: dict[str, dict[str, dict]] = {"world": WORLD_PRESETS, "vae": VAE_PRESETS, "distill": DISTILL_PRESETS}


def get_preset(model_name: str, preset: str) -> dict:
    if model_name not in PRESETS:
        raise KeyError(f"no presets for model {model_name!r}; known: {sorted(PRESETS)}")
    table = PRESETS[model_name]
    if preset not in table:
        raise KeyError(f"unknown preset {preset!r} for {model_name}; known: {', '.join(table)}")
    return copy.deepcopy(table[preset])
