"""resim.diffusion: schedule vs diffusers, v closed forms, noise-level modes, dropout, the loss."""
import dataclasses
import math

import pytest
import torch

from resim.config import ConfigError
from resim.diffusion import ObjectiveConfig, training_losses
from resim.diffusion.ddim import v_to_x0_eps
from resim.diffusion.noise_levels import sample_noise_levels
from resim.diffusion.schedule import add_noise, alphas_cumprod, v_target


def test_schedule_equals_diffusers_cogvideox_ddim():
    from diffusers import CogVideoXDDIMScheduler
    ref = CogVideoXDDIMScheduler(beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear",
                                 rescale_betas_zero_snr=True, snr_shift_scale=3.0, prediction_type="v_prediction",
                                 timestep_spacing="trailing", clip_sample=False).alphas_cumprod
    ours = alphas_cumprod()
    assert ours.shape == (1000,)
    assert torch.allclose(ours, ref.to(ours.dtype), rtol=0, atol=1e-12)
    assert ours[-1] == 0 and ours[0] < 1 and bool((ours[1:] < ours[:-1]).all())


def test_schedule_closed_form_first_step():
    # without rescale, step 0: ᾱ0 = 1 - β_start, then SNR / 3: ᾱ0 / (3 - 2 ᾱ0)
    from resim.diffusion.config import ScheduleConfig
    ac = alphas_cumprod(ScheduleConfig(rescale_zero_terminal_snr=False))
    a0 = 1 - 0.00085
    assert math.isclose(float(ac[0]), a0 / (3 - 2 * a0), rel_tol=1e-12)
    # the rescale keeps ᾱ0
    assert math.isclose(float(alphas_cumprod()[0]), float(ac[0]), rel_tol=1e-12)


def test_v_closed_form_and_inverses():
    ac = alphas_cumprod()
    g = torch.Generator().manual_seed(0)
    x0, eps = torch.randn(2, 3, 4, 2, 2, generator=g, dtype=torch.float64), torch.randn(2, 3, 4, 2, 2, generator=g, dtype=torch.float64)
    t = torch.tensor([[0, 500, 999], [10, 10, 998]])
    xt, v = add_noise(x0, eps, t, ac), v_target(x0, eps, t, ac)
    for b in range(2):
        for f in range(3):
            a = ac[t[b, f]]
            assert torch.allclose(xt[b, f], a.sqrt() * x0[b, f] + (1 - a).sqrt() * eps[b, f])
            assert torch.allclose(v[b, f], a.sqrt() * eps[b, f] - (1 - a).sqrt() * x0[b, f])
    # the sampler's one v-prediction conversion inverts the training target
    x0_hat, eps_hat = v_to_x0_eps(xt, v, ac[t].reshape(2, 3, 1, 1, 1))
    assert torch.allclose(x0_hat, x0) and torch.allclose(eps_hat, eps)
    assert torch.equal(v[0, 2], -x0[0, 2])  # zero terminal SNR: v = -x0 at t = 999
    with pytest.raises(ValueError, match="noise levels"):
        add_noise(x0, eps, t + 1, ac)


def test_v_target_matches_diffusers_get_velocity():
    from diffusers import CogVideoXDDIMScheduler
    sch = CogVideoXDDIMScheduler(rescale_betas_zero_snr=True, snr_shift_scale=3.0)
    x0, eps = torch.randn(4, 8), torch.randn(4, 8)
    t = torch.tensor([0, 250, 700, 999])
    ref = sch.get_velocity(x0, eps, t)
    assert torch.allclose(v_target(x0, eps, t, alphas_cumprod()), ref, atol=1e-6)


def test_noise_level_modes():
    g = torch.Generator().manual_seed(0)
    t, m = sample_noise_levels(ObjectiveConfig(noise_mode="diffusion_forcing"), 64, 6, g)
    assert t.shape == (64, 6) and m.all() and (t.min() >= 0) and (t.max() <= 999)
    assert (t != t[:, :1]).any(dim=1).float().mean() > 0.9  # independent per frame
    t, m = sample_noise_levels(ObjectiveConfig(noise_mode="uniform"), 64, 6, g)
    assert (t == t[:, :1]).all() and m.all()
    cfg = ObjectiveConfig(noise_mode="resim_cond_aug", num_history_frames=2, cond_aug_max_t=100)
    t, m = sample_noise_levels(cfg, 256, 6, g)
    assert (t[:, :2] == t[:, :1]).all() and (t[:, 2:] == t[:, 2:3]).all() and t[:, 0].max() <= 100
    assert not m[:, :2].any() and m[:, 2:].all()
    assert t[:, 2].max() > 900  # the future level spans the whole range
    with pytest.raises(ValueError, match="num_history_frames"):
        sample_noise_levels(ObjectiveConfig(noise_mode="resim_cond_aug", num_history_frames=6), 2, 6, g)


def test_low_level_fraction_draws_the_low_levels_that_often_and_changes_nothing_at_zero():
    base = ObjectiveConfig(noise_mode="resim_cond_aug", num_history_frames=2, cond_aug_max_t=100)
    ref, _ = sample_noise_levels(base, 4096, 6, torch.Generator().manual_seed(3))
    same, _ = sample_noise_levels(dataclasses.replace(base, low_level_fraction=0.0), 4096, 6,
                                  torch.Generator().manual_seed(3))
    assert torch.equal(ref, same)   # the default draws the same random numbers as before the option
    for mode, hist in (("resim_cond_aug", 2), ("uniform", 0), ("diffusion_forcing", 0)):
        cfg = dataclasses.replace(base, noise_mode=mode, num_history_frames=hist, low_level_fraction=0.5,
                                  low_level_max_t=150)
        t, m = sample_noise_levels(cfg, 4096, 6, torch.Generator().manual_seed(1))
        fut = t[m].float()
        # half from U{0..150}, half from U{0..999}: P(t <= 150) = 0.5 + 0.5 * 151 / 1000 = 0.5755
        assert abs(float((fut <= 150).float().mean()) - 0.5755) < 0.03, mode
        assert fut.max() > 900, mode      # the rest still spans the whole range
        if mode == "resim_cond_aug":      # the history's t_aug is untouched, the future still shares one level
            assert (t[:, 2:] == t[:, 2:3]).all() and t[:, 0].max() <= 100
    for bad in ({"low_level_fraction": 1.5}, {"low_level_fraction": -0.1},
                {"low_level_fraction": 0.5, "low_level_max_t": 1000}):
        with pytest.raises(ConfigError, match="low_level"):
            ObjectiveConfig(**bad)


class _Spy(torch.nn.Module):
    """Records what the objective passes to the model; predicts zeros via a trainable scalar. No ``cfg``: the
    objective must not read the network's configuration."""

    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.zeros(()))
        self.calls = []

    def forward(self, x, t, text, trajectory=None, actions=None, trajectory_keep=None, action_keep=None):
        self.calls.append(dict(t=t, text=text, traj=trajectory, actions=actions, keep_traj=trajectory_keep,
                               keep_act=action_keep))
        return x * self.w


def _batch(b=400, nf=4, sources=None):
    g = torch.Generator().manual_seed(3)
    return {"latents": torch.randn(b, nf, 2, 2, 2, generator=g), "text": torch.ones(b, 3, 5),
            "null_text": torch.zeros(b, 3, 5), "trajectory": torch.randn(b, 8, 3, generator=g),
            "source": sources or (["carla", "navsim"] * (b // 2))}


def test_condition_dropout_rates_and_carla():
    spy = _Spy()
    training_losses(spy, _batch(), ObjectiveConfig(), torch.Generator().manual_seed(0), ego_motion_actions=True)
    c = spy.calls[-1]
    kept_text = (c["text"][:, 0, 0] == 1).float()
    assert 0.4 < kept_text.mean() < 0.6                         # p = 0.5, prefix (null_text) otherwise
    keep = c["keep_traj"]
    assert keep[0::2].all()                                      # CARLA always keeps its trajectory
    assert 0.38 < keep[1::2].float().mean() < 0.62               # NAVSIM: p = 0.5
    assert c["actions"].shape == (400, 4, 3)                     # derived from the trajectory
    ka = c["keep_act"]
    assert not ka[:, 0].any()                                    # history frame: no action
    assert not ka[1::2][~keep[1::2]].any()                       # dropped trajectory → dropped actions
    assert 0.7 < ka[0::2, 1:].float().mean() < 0.9               # p = 0.2 per frame otherwise


def test_actions_are_derived_only_when_the_caller_says_the_model_takes_them():
    """The objective does not look inside the network: without ``ego_motion_actions`` a trajectory gives no
    actions (a model without an ego-motion encoder gets none), with it they are derived; TrainableWorldModel
    says so from its own config."""
    from resim.models.world.config import ActionConfig, preset
    from resim.train.tasks.world_model import TrainableWorldModel

    spy = _Spy()
    training_losses(spy, _batch(8), ObjectiveConfig(), torch.Generator().manual_seed(0))
    assert spy.calls[-1]["actions"] is None
    training_losses(spy, _batch(8), ObjectiveConfig(), torch.Generator().manual_seed(0), ego_motion_actions=True)
    assert spy.calls[-1]["actions"].shape == (8, 4, 3)
    assert ActionConfig().takes_ego_motion and not ActionConfig(kind="none").takes_ego_motion
    assert not ActionConfig(kind="discrete", num_actions=4).takes_ego_motion
    m = TrainableWorldModel(preset("tiny"), ObjectiveConfig(noise_mode="diffusion_forcing", num_history_frames=1))
    batch = {"latents": torch.randn(2, 3, 16, 8, 12), "text": torch.randn(2, 16, 64), "null_text": torch.randn(2, 16, 64),
             "trajectory": torch.randn(2, 8, 3), "source": ["carla", "carla"]}
    _, logs = m.loss(batch)
    assert logs["actions_derived"] == 1.0


def test_loss_masks_history_in_cond_aug():
    spy = _Spy()
    batch = _batch(8, 4)
    cfg = ObjectiveConfig(noise_mode="resim_cond_aug", num_history_frames=2, text_drop_prob=0.0)
    loss, logs = training_losses(spy, batch, cfg, torch.Generator().manual_seed(0))
    # with a zero prediction the per-frame loss is E|v|^2; recompute on the future frames only
    t = spy.calls[-1]["t"]
    ac = alphas_cumprod()
    g = torch.Generator().manual_seed(0)
    sample_noise_levels(cfg, 8, 4, g)
    noise = torch.randn(batch["latents"].shape, generator=g)
    v = v_target(batch["latents"], noise, t, ac)
    assert torch.allclose(loss, (v[:, 2:] ** 2).mean(), atol=1e-6)
    assert logs["loss"] == pytest.approx(float(loss.detach()))


def test_missing_null_text_is_named():
    b = _batch(4)
    del b["null_text"]
    with pytest.raises(ValueError, match="null_text"):
        training_losses(_Spy(), b, ObjectiveConfig())


def test_world_model_loss_trains(tiny_model):
    """training_losses(model, batch, objective) → finite loss with logs; a few Adam steps on one batch lower it. The
    trainer's entry point is TrainableWorldModel.loss (the network bound to its objective)."""
    from resim.train.tasks.world_model import TrainableWorldModel

    torch.manual_seed(0)
    model = tiny_model.train()
    objective = ObjectiveConfig(noise_mode="diffusion_forcing", num_history_frames=1)
    assert not hasattr(model, "objective") and not hasattr(model, "loss")   # the network knows no objective
    batch = {"latents": torch.randn(2, 3, 16, 8, 12), "text": torch.randn(2, 16, 64),
             "null_text": torch.randn(2, 16, 64), "trajectory": torch.randn(2, 8, 3), "source": ["carla", "opendv"]}
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    first = None
    for _ in range(25):
        g = torch.Generator().manual_seed(1)  # same draws each step: the loss must go down
        loss, logs = training_losses(model, batch, objective, g, ego_motion_actions=model.cfg.actions.takes_ego_motion)
        first = first if first is not None else float(loss.detach())
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert torch.isfinite(loss) and {"loss", "t_mean", "text_kept", "trajectory_kept", "actions_kept"} <= set(logs)
    assert float(loss.detach()) < 0.8 * first
    trainable = TrainableWorldModel(model.cfg, objective)
    trainable.load_state_dict(model.state_dict())        # same parameters: the objective is configuration
    loss2, _ = trainable.loss(batch)  # the Trainer's entry point
    assert torch.isfinite(loss2)


def test_batch_clip_geometry_overrides_config():
    """Mixed datasets: a NAVSIM-style batch (T=3 latent frames, 1 of history, 2 s each) under a config
    written for OpenDV (3 history latent frames, 0.4 s) takes its history and frame duration from the batch."""
    from resim.models.world.conditioning import actions_from_trajectory
    cfg = ObjectiveConfig(noise_mode="resim_cond_aug", num_history_frames=3, text_drop_prob=0.0,
                          trajectory_drop_prob=0.0, action_drop_prob=0.0)
    batch = {**_batch(8, 3), "num_history_latent_frames": 1, "latent_frame_dt_s": 2.0}
    spy = _Spy()
    loss, _ = training_losses(spy, batch, cfg, torch.Generator().manual_seed(0), ego_motion_actions=True)
    c = spy.calls[-1]
    t = c["t"]
    assert bool((t[:, 1] == t[:, 2]).all())  # one future level; history = frame 0 only
    g = torch.Generator().manual_seed(0)
    sample_noise_levels(cfg, 8, 3, g, num_history_frames=1)
    v = v_target(batch["latents"], torch.randn(batch["latents"].shape, generator=g), t, alphas_cumprod())
    assert torch.allclose(loss, (v[:, 1:] ** 2).mean(), atol=1e-6)  # loss on the 2 future frames
    acts, valid = actions_from_trajectory(batch["trajectory"], 3, 1, 2.0, 0.5)
    assert torch.equal(c["actions"], acts) and valid[0].tolist() == [False, True, True]
    assert torch.equal(c["keep_act"], valid)
    with pytest.raises(ValueError, match="resim_cond_aug needs"):  # the config alone does not fit T=3
        training_losses(spy, batch, ObjectiveConfig(noise_mode="resim_cond_aug", num_history_frames=3,
                                                    geometry_from_batch=False))


def test_world_model_trains_on_alternating_clip_lengths(tiny_model):
    """T_latent changes from step to step (13 then 3): sin-cos positions per T, gradients everywhere finite."""
    torch.manual_seed(0)
    objective = ObjectiveConfig(noise_mode="resim_cond_aug", num_history_frames=3)
    model = tiny_model.train()
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    for nf, hist, dt in ((13, 3, 0.4), (3, 1, 2.0), (13, 3, 0.4)):
        batch = {"latents": torch.randn(2, nf, 16, 8, 12), "text": torch.randn(2, 16, 64),
                 "null_text": torch.randn(2, 16, 64), "trajectory": torch.randn(2, 8, 3), "source": ["navsim"] * 2,
                 "num_history_latent_frames": hist, "latent_frame_dt_s": dt}
        loss, _ = training_losses(model, batch, objective, ego_motion_actions=model.cfg.actions.takes_ego_motion)
        opt.zero_grad()
        loss.backward()
        assert torch.isfinite(loss)
        assert all(p.grad is None or torch.isfinite(p.grad).all() for p in model.parameters())
        opt.step()


@pytest.mark.parametrize("make,match", [
    (lambda: ObjectiveConfig(latent_frame_dt_s=-0.4), "latent_frame_dt_s"),
    (lambda: ObjectiveConfig(latent_frame_dt_s=0.0), "latent_frame_dt_s"),
    (lambda: ObjectiveConfig(waypoint_dt_s=0.0), "waypoint_dt_s"),
    (lambda: ObjectiveConfig(waypoint_dt_s=float("nan")), "waypoint_dt_s"),
])
def test_objective_durations_must_be_positive(make, match):
    """A zero/negative duration used to be accepted and silently gave all-null or time-reversed actions."""
    from resim.config import ConfigError
    with pytest.raises(ConfigError, match=match):
        make()


@pytest.mark.parametrize("scale", [(0.0, 0.5, 0.1), (2.0, -0.5, 0.1)])
def test_action_input_scale_must_be_positive(scale):
    """Actions are divided by input_scale: a zero made the loss NaN, a negative flipped the action's sign."""
    from resim.config import ConfigError
    from resim.models.world.config import preset
    from resim.train.tasks.world_model import build_world
    with pytest.raises(ConfigError, match="actions.input_scale"):
        preset("tiny", actions=dict(input_scale=scale))
    with pytest.raises(ConfigError, match="actions.input_scale"):   # the training entry point (--set overrides)
        build_world({"preset": "tiny", "overrides": {"actions": {"input_scale": list(scale)}}})


def test_shuffle_commands_control_permutes_prompts():
    """The shuffled-command control: the model sees the batch's prompts, each moved to another sample."""
    b = _batch(64, 4)
    b["text"] = torch.arange(64.0)[:, None, None].expand(64, 3, 5).clone()
    spy = _Spy()
    training_losses(spy, b, ObjectiveConfig(text_drop_prob=0.0), torch.Generator().manual_seed(0))
    assert torch.equal(spy.calls[-1]["text"][:, 0, 0], torch.arange(64.0))           # off: as given
    training_losses(spy, b, ObjectiveConfig(text_drop_prob=0.0, shuffle_commands=True), torch.Generator().manual_seed(0))
    seen = spy.calls[-1]["text"][:, 0, 0]
    assert sorted(seen.tolist()) == list(range(64)) and (seen != torch.arange(64.0)).float().mean() > 0.8
