"""The closed loop inside a world model (resim/sample/simulate.py), on the tiny causal model and the tiny
placeholder VAE: each decision's plan is what the world model is conditioned on, the policy sees the frames the
world model made, and the loop grows the video by one decision's frames at a time."""
from pathlib import Path

import numpy as np
import pytest
import torch

from resim.media.encoders import VideoVAE
from resim.sample.rollout import RolloutConfig
from resim.sample.simulate import NULL_PROMPT_GUIDANCE_START, WorldModelLoop, loop_guidance_start
from resim.synthworld.closed_loop import PolicyError

pytestmark = pytest.mark.usefixtures("one_torch_thread")
VAE_DIR = Path(__file__).resolve().parents[2] / "configs/models/placeholder-cogvideox-vae-tiny"


class Spy(torch.nn.Module):
    """The tiny model, recording the trajectory of every call's conditional half."""

    def __init__(self, model):
        super().__init__()
        self.model, self.cfg, self.seen = model, model, []
        self.causal = model.causal

    def forward(self, x, t, text, trajectory=None, actions=None, **kw):
        self.seen.append(None if trajectory is None else trajectory[:1].clone())
        return self.model(x, t, text, trajectory, actions, **kw)


def test_each_plan_conditions_the_world_model_and_the_policy_sees_its_frames(tiny_model):
    vae = VideoVAE(VAE_DIR, device="cpu")
    model = Spy(tiny_model(channels=16, text_dim=8))
    text = {None: torch.zeros(1, 3, 8), "Moving forward": torch.ones(1, 3, 8)}
    loop = WorldModelLoop(model, vae, lambda c: text[c], RolloutConfig(num_steps=3), latents_per_decision=1)
    frames = np.random.default_rng(0).integers(0, 255, (9, 16, 24, 3), dtype=np.uint8)
    hist = torch.from_numpy(np.asarray(vae.encode(frames[None], seeds=[0]), np.float32))
    seen_obs = []

    def policy(obs):
        seen_obs.append(obs)
        k = len(seen_obs)
        return np.c_[np.arange(1, 9) * 2.0, np.full(8, 0.1 * k), np.zeros(8)]   # decision k: lateral 0.1 k m

    res = loop.run(hist, frames, 6.0, policy, 1.2, command_at=lambda t: "Moving forward", t0_s=0.8, seed=3)
    assert len(res.plans) == 3 and [round(t, 3) for t, _ in res.plans] == [0.8, 1.2, 1.6]
    assert res.latents.shape[1] == 3 + 3 and res.frames.shape == (9 + 3 * 4, 16, 24, 3)
    # every model call of decision k carried decision k's plan (history cache, 3 DDIM steps)
    per = len(model.seen) // 3
    for k in range(3):
        for traj in model.seen[k * per:(k + 1) * per]:
            assert traj is not None and torch.allclose(traj[0, :, 1], torch.full((8,), 0.1 * (k + 1)))
    # the policy saw the recorded history first, then the generated frames; the speedometer is its own plan's
    assert np.array_equal(seen_obs[0].frames, frames) and seen_obs[0].speed_mps == 6.0
    assert np.array_equal(seen_obs[1].frames[-4:], res.frames[9:13])
    assert seen_obs[1].speed_mps == pytest.approx(np.hypot(2.0, 0.1) / 0.5)
    assert seen_obs[2].command == "Moving forward" and seen_obs[2].pose is None
    with pytest.raises(PolicyError, match="policy bad: plan has shape"):
        loop.run(hist, frames, 6.0, lambda obs: np.zeros(3), 0.4, name="bad")


def test_a_batch_of_policies_drives_as_each_would_alone(tiny_model):
    vae = VideoVAE(VAE_DIR, device="cpu")
    model = tiny_model(channels=16, text_dim=8)
    loop = WorldModelLoop(model, vae, lambda c: torch.zeros(1, 3, 8), RolloutConfig(num_steps=2))
    frames = np.random.default_rng(1).integers(0, 255, (9, 16, 24, 3), dtype=np.uint8)
    hist = torch.from_numpy(np.asarray(vae.encode(frames[None], seeds=[0]), np.float32))
    pols = [lambda obs, y=y: np.c_[np.arange(1, 9) * 2.0, np.full(8, y), np.zeros(8)] for y in (-1.0, 1.0)]
    both = loop.run_batch(hist, frames, 5.0, pols, 0.8, seeds=[7, 9])
    alone = [loop.run(hist, frames, 5.0, p, 0.8, seed=s) for p, s in zip(pols, (7, 9))]
    for b, a in zip(both, alone):
        assert torch.allclose(b.latents, a.latents, atol=1e-4)
        assert np.abs(b.frames.astype(int) - a.frames).max() <= 1
    assert not torch.allclose(both[0].latents, both[1].latents)


def test_the_world_model_can_be_left_without_the_command_the_policy_is_told(tiny_model):
    """command_to_world=False: the prompt is the null one at every decision, the policy still gets the command."""
    vae = VideoVAE(VAE_DIR, device="cpu")
    asked = []

    def text_for(c):
        asked.append(c)
        return torch.zeros(1, 3, 8)

    loop = WorldModelLoop(tiny_model(channels=16, text_dim=8), vae, text_for, RolloutConfig(num_steps=1),
                          command_to_world=False)
    frames = np.random.default_rng(2).integers(0, 255, (9, 16, 24, 3), dtype=np.uint8)
    hist = torch.from_numpy(np.asarray(vae.encode(frames[None], seeds=[0]), np.float32))
    told = []

    def policy(obs):
        told.append(obs.command)
        return np.c_[np.arange(1, 9) * 2.0, np.zeros(8), np.zeros(8)]

    res = loop.run(hist, frames, 5.0, policy, 0.8, command_at=lambda t: "Turning left", t0_s=0.8)
    assert told == ["Turning left"] * 2 and res.commands == ["Turning left"] * 2
    assert asked and set(asked) == {None}


def test_the_null_prompt_loop_starts_its_trajectory_guidance_higher():
    # null prompt: the measured closed-loop default; anything the user or the checkpoint decided is kept
    assert loop_guidance_start(None, "resim", False, False, False) == NULL_PROMPT_GUIDANCE_START == 15.0
    assert loop_guidance_start(3.0, "resim", False, False, False) == 3.0
    assert loop_guidance_start(None, "resim", False, True, False) is None      # command in the prompt: the preset's 7.5
    assert loop_guidance_start(None, "vid2world", False, False, False) is None  # its own action guidance (2.5)
    assert loop_guidance_start(None, "resim", True, False, False) is None      # --no-guidance
    assert loop_guidance_start(None, "resim", False, False, True) is None      # a distilled student samples unguided
