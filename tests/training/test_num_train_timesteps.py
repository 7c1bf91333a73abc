"""``objective.schedule.num_train_timesteps`` (N) other than CogVideoX's 1000 is carried everywhere: the schedule
and the DDIM sampler equal diffusers' for that N, training draws and logs levels in [0, N), the rollout and the
model check their levels against N (a clear ConfigError, never an IndexError), and pretrained CogVideoX weights
(trained with 1000 levels) refuse another N."""
import json

import pytest
import torch

from resim.config import ConfigError
from resim.diffusion.config import ObjectiveConfig, ScheduleConfig
from resim.diffusion.ddim import DDIMSchedule, ddim_step, ddim_timesteps
from resim.diffusion.guidance import guidance_preset
from resim.diffusion.losses import training_losses
from resim.diffusion.noise_levels import sample_noise_levels
from resim.diffusion.schedule import alphas_cumprod
from resim.models.world.config import preset
from resim.models.world.dit import WorldModel
from resim.sample.rollout import Condition, RolloutConfig, rollout
from resim.train.tasks.world_model import TrainableWorldModel

diffusers = pytest.importorskip("diffusers")


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _diffusers_sched(n: int):
    # THUDM/CogVideoX-2b's scheduler config with num_train_timesteps = n
    return diffusers.CogVideoXDDIMScheduler(
        beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear", clip_sample=False, num_train_timesteps=n,
        prediction_type="v_prediction", rescale_betas_zero_snr=True, set_alpha_to_one=True, snr_shift_scale=3.0,
        steps_offset=0, timestep_spacing="trailing")


def _objective(n: int, **kw) -> ObjectiveConfig:
    return ObjectiveConfig(schedule=ScheduleConfig(num_train_timesteps=n), **kw)


# ---------------------------------------------------------------------------------------------- schedules
@pytest.mark.parametrize("n", [500, 250, 2000])
def test_alphas_cumprod_match_diffusers_for_other_n(n):
    ours = alphas_cumprod(ScheduleConfig(num_train_timesteps=n))
    ref = _diffusers_sched(n).alphas_cumprod.to(torch.float64)   # diffusers computes in float32
    assert ours.shape == (n,) and ours[-1] == 0.0 and torch.all(ours[1:] < ours[:-1])
    torch.testing.assert_close(ours, ref, rtol=0, atol=1e-6)


@pytest.mark.parametrize("steps", [1, 7, 10, 30, 50, 125, 500])
def test_ddim_timesteps_match_diffusers_for_500(steps):
    s = _diffusers_sched(500)
    s.set_timesteps(steps)
    assert ddim_timesteps(steps, 500) == s.timesteps.tolist()
    ours = DDIMSchedule(steps, alphas_cumprod(ScheduleConfig(num_train_timesteps=500)))
    assert ours.timesteps[0] == 499 and ours.steps[-1].t_prev == -1


@pytest.mark.parametrize("steps", [50, 10, 4])
def test_ddim_loop_matches_diffusers_for_500(steps):
    """Same 'model' (a fixed function of x and t), every step equal to diffusers' scheduler with N = 500."""
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, 3, 4, 5, 6, generator=g, dtype=torch.float64)
    w = torch.randn(4, 4, generator=g, dtype=torch.float64) * 0.3

    def fake_v(x, t):
        return torch.tanh(torch.einsum("btchw,cd->btdhw", x, w)) * (1 + t / 500.0) + 0.1 * x

    ref = _diffusers_sched(500)
    ours = DDIMSchedule(steps, alphas_cumprod(ScheduleConfig(num_train_timesteps=500)))
    ref.alphas_cumprod = ours.alphas_cumprod.clone()   # the same ᾱ (float64): compare the stepping only
    ref.set_timesteps(steps)
    assert [s.t for s in ours] == ref.timesteps.tolist()
    xr, xo = x.clone(), x.clone()
    for step in ours:
        xr = ref.step(fake_v(xr, step.t), step.t, xr).prev_sample
        xo, _ = ddim_step(xo, fake_v(xo, step.t), step.a_t, step.a_prev)
        torch.testing.assert_close(xo, xr, rtol=1e-10, atol=1e-10)


# ---------------------------------------------------------------------------------------------- training
def test_objective_defaults_follow_n():
    cfg = _objective(500, noise_mode="resim_cond_aug", num_history_frames=2)   # cond_aug_max_t left at default
    assert cfg.cond_aug_max_t is None and cfg.cond_aug_max_level == 499
    t, _ = sample_noise_levels(cfg, 4096, 5, generator=torch.Generator().manual_seed(0))
    assert int(t.min()) == 0 and int(t.max()) == 499            # history and future both reach N - 1, no more
    assert _objective(1000).cond_aug_max_level == 999           # CogVideoX: unchanged
    with pytest.raises(ConfigError, match=r"cond_aug_max_t=500 must be in \[0, num_train_timesteps = 500\)"):
        _objective(500, cond_aug_max_t=500)
    assert _objective(2000, cond_aug_max_t=1500).cond_aug_max_level == 1500


@pytest.mark.parametrize("n", [500, 90, 1000])
def test_loss_logs_bin_thirds_of_n(n):
    torch.manual_seed(0)
    obj = _objective(n, cond_aug_max_t=n - 1, text_drop_prob=0.0)
    model = WorldModel(preset("tiny")).eval()
    c = model.cfg
    batch = {"latents": torch.randn(4, 6, c.in_channels, 4, 4), "text": torch.randn(4, 3, c.text_embed_dim)}
    seen: dict[str, int] = {}
    for s in range(6):   # 144 levels drawn: every third of [0, N) gets some
        _, logs = training_losses(model, batch, obj, generator=torch.Generator().manual_seed(s))
        for k in logs:
            seen[k] = seen.get(k, 0) + 1
    assert {"loss_t_low", "loss_t_mid", "loss_t_high"} <= set(seen)
    from resim.diffusion.losses import loss_level_bins
    assert [b[1:] for b in loss_level_bins(n)] == [(0, n // 3), (n // 3, 2 * n // 3), (2 * n // 3, n)]
    assert [b[1:] for b in loss_level_bins(1000)] == [(0, 333), (333, 666), (666, 1000)]


def test_model_text_level_checked_against_n():
    TrainableWorldModel(preset("tiny", text_timestep_value=1500), objective=_objective(2000))
    with pytest.raises(ConfigError, match=r"text_timestep_value=700 not in \[0, 500\)"):
        TrainableWorldModel(preset("tiny", text_timestep_value=700), objective=_objective(500))
    with pytest.raises(ConfigError, match="text_timestep_value"):
        preset("tiny", text_timestep_value=-1)


def test_pretrained_cogvideox_refuses_other_n(tmp_path):
    from diffusers import CogVideoXTransformer3DModel
    tiny = dict(num_attention_heads=2, attention_head_dim=16, in_channels=16, out_channels=16, time_embed_dim=32,
                text_embed_dim=64, num_layers=1, sample_width=12, sample_height=8, sample_frames=49, patch_size=2,
                max_text_seq_length=16)
    src = CogVideoXTransformer3DModel(**tiny)
    src.save_pretrained(tmp_path / "pipe" / "transformer")          # a pipeline folder, as CogVideoX-2b ships
    (tmp_path / "pipe" / "scheduler").mkdir()
    (tmp_path / "pipe" / "scheduler" / "scheduler_config.json").write_text(json.dumps({"num_train_timesteps": 1000}))
    for folder in (tmp_path / "pipe", tmp_path / "pipe" / "transformer"):
        with pytest.raises(ConfigError, match="pretrained weights were trained with 1000 noise levels"):
            TrainableWorldModel.from_cogvideox(folder, objective=_objective(500))
        with pytest.raises(ConfigError, match="pretrained weights were trained with 1000 noise levels"):
            WorldModel.from_cogvideox(folder, num_train_timesteps=500)    # the network alone checks it too
        model = TrainableWorldModel.from_cogvideox(folder, objective=_objective(1000))
        assert model.objective.schedule.num_train_timesteps == 1000
    src.save_pretrained(tmp_path / "bare")                           # no scheduler saved with it: nothing to check
    TrainableWorldModel.from_cogvideox(tmp_path / "bare", objective=_objective(500))
    # built with its own objective from the start: a text level valid only under N = 2000 is accepted
    m = TrainableWorldModel.from_cogvideox(tmp_path / "bare", objective=_objective(2000), text_timestep_value=1500)
    assert m.objective.schedule.num_train_timesteps == 2000 and m.cfg.text_timestep_value == 1500


# ---------------------------------------------------------------------------------------------- sampling
def _rollout(n: int, **rc):
    torch.manual_seed(0)
    model = WorldModel(preset("tiny")).eval()
    levels: list[torch.Tensor] = []
    model.register_forward_pre_hook(lambda m, args: levels.append(args[1].detach().clone()))
    c = model.cfg
    hist = torch.randn(1, 2, c.in_channels, 4, 4, generator=torch.Generator().manual_seed(1))
    cfg = RolloutConfig(history_frames=2, frames_per_round=1, chunk_frames=1, guidance=guidance_preset("none"), **rc)
    with torch.no_grad():
        res = rollout(model, hist, Condition(text=torch.randn(1, 3, c.text_embed_dim)), 1, cfg,
                      schedule=_objective(n).schedule)   # the run's schedule, not the model's
    return res, levels


def test_rollout_uses_the_models_n():
    res, levels = _rollout(500, num_steps=5, history_noise_level=400, kv_cache="off")
    assert res.latents.shape[1] == 3 and torch.isfinite(res.latents).all()
    new = [int(t[0, -1]) for t in levels]                 # the generated frame's level at each DDIM step
    assert new == ddim_timesteps(5, 500) == [499, 399, 299, 199, 99]
    assert all(int(t[0, 0]) == 400 for t in levels)       # history fed at history_noise_level
    # a model with more levels takes steps/levels a 1000-level one cannot
    res, levels = _rollout(2000, num_steps=1500, history_noise_level=1500, kv_cache="on")
    assert int(levels[1][0, -1]) == 1999 and torch.isfinite(res.latents).all()


@pytest.mark.parametrize("rc, msg", [
    (dict(num_steps=2, history_noise_level=700), r"history_noise_level=700 not in \[0, 500\)"),
    (dict(num_steps=501), "num_steps=501 > the model's num_train_timesteps=500"),
])
def test_rollout_refuses_levels_outside_n(rc, msg):
    with pytest.raises(ConfigError, match=msg):
        _rollout(500, **rc)
