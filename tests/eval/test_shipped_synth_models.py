"""The shipped synthetic-world models still work (docs/models/): if these fail, VAE loading, training or
sampling broke.

* the VAE (configs/models/synth-vae) reconstructs held-out clips (frames of a world seed it never saw), and decodes
  each latent group's end frame where the turn has taken the original (the flow labeler reads the turns there);
* the world model (configs/models/synth-world) rolls held-out histories out into futures that resemble the
  recorded ones (PSNR at 2 and 4 s well above what a broken VAE or sampler gives);
* from the shared history of a fork (a world seed it never saw), its rollouts under each command land on the future
  recorded under that command (in latent space, where the VAE cannot hide a turn), and the null prompt's do not;
* (expected to fail until a model that turns clearly is shipped, see the card) on held-out histories, its
  rollouts under "Turning left" and "Turning right" are read as left / right turns by the optical-flow labeler.

Held-out clips: tests/data/synth-heldout, a pipeline dataset of world seed 2000, and tests/data/synth-forks, two
three-way forks of world seed 2001 (no shipped model saw either seed; the commands that made them are in
tests/data/README.md)."""
from pathlib import Path

import numpy as np
import pytest
import torch

from resim.shipped import PLACEHOLDER_T5, SYNTH_VAE, SYNTH_WORLD, shipped_dir

REPO = Path(__file__).resolve().parents[2]
HELDOUT = REPO / "tests" / "data" / "synth-heldout"
FORKS = REPO / "tests" / "data" / "synth-forks"

pytestmark = pytest.mark.slow


@pytest.fixture(autouse=True)
def _threads():
    n = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(n)


def _clips():
    from resim.eval.worldeval import eval_clips_from_dataset

    return eval_clips_from_dataset(HELDOUT, need_trajectory=False)


def test_vae_reconstructs_heldout_clips():
    from resim.media.encoders import VideoVAE
    from resim.eval.fidelity import psnr
    from resim.sample.outputs import decode_latents

    vae = VideoVAE(shipped_dir(SYNTH_VAE), device="cpu")
    assert not vae.info.placeholder
    clips = _clips()[:3]
    frames = np.stack([c.frames for c in clips])                       # (N, 49, 64, 96, 3)
    lat = vae.encode(frames, seeds=list(range(len(clips))))
    rec = decode_latents(vae, torch.from_numpy(lat))
    p = psnr(torch.from_numpy(rec).permute(0, 1, 4, 2, 3), torch.from_numpy(frames).permute(0, 1, 4, 2, 3), "uint8")
    # the model card's held-out mean is 2-3 dB above this floor; a broken load or decode gives ~10 dB
    assert float(p.mean()) > 25.0, p.mean(dim=1)


def test_vae_puts_each_latent_group_where_the_turn_took_the_original():
    """The flow labeler on the fork clips' reconstructions with the frames inside each latent group redrawn from
    the group ends (resim/eval/group_frames.py). The shipped decoder draws those inside frames as a cross-fade,
    so as decoded it keeps only part of a turn; its group ends must carry all of it."""
    from resim.media.encoders import VideoVAE
    from resim.eval.branches import counterfactual_groups
    from resim.eval.vae_eval import vae_eval
    from resim.eval.worldeval import eval_clips_from_dataset, flow_labeler_status

    every = eval_clips_from_dataset(FORKS, need_trajectory=False)
    clips = [every[i] for g in counterfactual_groups(every) for i in g]      # the two forks: 2 left, 2 right, 2 ahead
    labeler, reason = flow_labeler_status()
    assert labeler is not None, reason
    m = vae_eval(VideoVAE(shipped_dir(SYNTH_VAE), device="cpu"), clips, labeler=labeler, group_ends=True)["motion"]
    g = m["group_ends"]
    # measured 2026-12-02 (stage 1e, these 6 clips, 4 turning by 34-79 deg): heading kept 1.00 at the group ends
    # (0.51 as decoded), every clip labelled right there (0.67 as decoded); a decoder whose frames stood still or
    # drifted would keep ~0 at the group ends too (docs/models/synth-vae.md, "Limitations")
    assert m["turning_clips"] >= 4 and g["heading_kept"] > 0.8, (m["heading_kept"], g)
    assert g["labeler_on_reconstructions"]["accuracy"] >= 0.9, g["labeler_on_reconstructions"]


def _runner(data: Path = HELDOUT):
    from resim.media.encoders import VideoVAE
    from resim.config import from_dict
    from resim.eval.worldeval import WorldRollouts
    from resim.diffusion.guidance import guidance_preset
    from resim.sample.load import PromptSource, encoded_with, load_world_model, run_objective
    from resim.sample.rollout import ROLLOUT_PRESETS, RolloutConfig

    ckpt = shipped_dir(SYNTH_WORLD)
    model, _ = load_world_model(ckpt, "cpu", torch.float32)
    vae = VideoVAE(encoded_with(ckpt), device="cpu")
    assert not vae.info.placeholder
    cfg = from_dict(RolloutConfig, {**ROLLOUT_PRESETS["resim"], "num_steps": 20, "guidance": guidance_preset("resim")})
    prompts = PromptSource(data, shipped_dir(PLACEHOLDER_T5), device="cpu", max_tokens=model.cfg.max_text_seq_length)
    return WorldRollouts(model, vae, cfg, prompts, seed=0, batch_size=3, schedule=run_objective(ckpt).schedule)


def test_world_model_rollouts_look_like_the_heldout_future():
    from resim.eval.command_following import fidelity_per_horizon

    clips = _clips()
    videos = _runner().generate(clips, [None] * len(clips), [c.command for c in clips])
    gt = np.stack([c.frames for c in clips])
    rows = fidelity_per_horizon(videos, gt, clips[0].num_history_frames, clips[0].fps_hz, (2.0, 4.0))["per_horizon"]
    # measured for stage 4b with the stage-1b VAE (2026-11-28): 20.5 / 20.2 dB at 2 / 4 s on these clips (stages 4c
    # and 5, shipped after it, passed this test when shipped; on 12 seed-1000 histories they are within 0.9 dB of 4b)
    # (copy-last-frame 23.2 / 22.0: these 6 clips are slow drives); a random VAE or a broken sampler gives 10-13 dB
    for r in rows:
        assert r["psnr_model"] > 17.0, rows


def test_world_model_rolls_a_fork_out_to_the_commanded_branch():
    """ReSim's controllability where only the command decides: the two forks' shared histories rolled out under
    left / forward / right (and the null prompt), each rollout scored by the sibling recorded future it lands
    nearest to (resim.eval.branches). A model or sampler that ignores the command lands at chance, 1/3."""
    from resim.shards.schema import COMMANDS
    from resim.eval.branches import branch_matching, counterfactual_groups
    from resim.eval.worldeval import eval_clips_from_dataset

    every = eval_clips_from_dataset(FORKS, need_trajectory=False)
    clips = [every[i] for g in counterfactual_groups(every) for i in g]
    groups = counterfactual_groups(clips)
    assert len(groups) == 2 and len(clips) == 6, [len(g) for g in groups]
    runner = _runner(FORKS)
    h = runner.history_latents(clips[0])
    n = len(clips)
    gen = {c: runner.generate_latents(clips, [None] * n, [c] * n)[:, h:].numpy() for c in COMMANDS}
    gen["null"] = runner.generate_latents(clips, [None] * n, [None] * n)[:, h:].numpy()
    rep = branch_matching(gen, np.stack([c.latents[h:] for c in clips]), [c.command for c in clips], groups,
                          null_key="null")
    # measured 2026-11-30 (stage 9, 20 DDIM steps): commanded 0.72 (13 of 18), null prompt 0.33, swap test 1.00
    # (18 pairs; stage 8b: 0.83 / 0.33 / 1.00); on held-out fork worlds: docs/models/synth-world.md, "Held-out
    # numbers"; a command-blind model: ~0.33 / 0.33 / 0.5
    assert rep["commanded"]["accuracy"] >= 0.66, rep["commanded"]
    assert rep["null_prompt"]["accuracy"] <= 0.5, rep["null_prompt"]
    assert rep["swap_test"]["accuracy"] >= 0.8, rep["swap_test"]


@pytest.mark.xfail(strict=True, reason="the shipped synth-world turns the commanded way too weakly for the flow "
                                       "labeler (docs/models/synth-world.md, 'Limitations': a few degrees where "
                                       "a turn is 15.5 deg); strict: an XPASS means a new model turns clearly, so "
                                       "this mark and the card must be updated")
def test_world_model_turns_where_it_is_told():
    from resim.eval.command_following import flow_commands
    from resim.eval.worldeval import flow_labeler_status

    runner = _runner()
    clips = _clips()[:3]
    labeler, reason = flow_labeler_status()
    assert labeler is not None, reason
    nh, fps = clips[0].num_history_frames, clips[0].fps_hz
    read = {}
    for cmd in ("Turning left", "Turning right"):
        videos = runner.generate(clips, [None] * len(clips), [cmd] * len(clips))
        read[cmd] = flow_commands(videos, nh, fps, labeler)
    left_ok = sum(c == "Turning left" for c in read["Turning left"][0])
    right_ok = sum(c == "Turning right" for c in read["Turning right"][0])
    # every left rollout must turn further left than the right rollout of the same history
    assert all(yl > yr for yl, yr in zip(read["Turning left"][1], read["Turning right"][1])), read
    assert left_ok + right_ok >= 5, read
