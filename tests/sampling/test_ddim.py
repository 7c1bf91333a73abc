"""DDIM over CogVideoX's schedule vs. diffusers' CogVideoXDDIMScheduler (CogVideoX-2b's config)."""
import numpy as np
import pytest
import torch

from resim.diffusion.ddim import DDIMSchedule, cogvideox_alphas_cumprod, ddim_step, ddim_timesteps, forward_noise

diffusers = pytest.importorskip("diffusers")

# THUDM/CogVideoX-2b scheduler/scheduler_config.json (clip_sample=False, unlike the class default)
COGVIDEOX_2B = dict(beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear", clip_sample=False,
                    num_train_timesteps=1000, prediction_type="v_prediction", rescale_betas_zero_snr=True,
                    set_alpha_to_one=True, snr_shift_scale=3.0, steps_offset=0, timestep_spacing="trailing")


def _sched():
    return diffusers.CogVideoXDDIMScheduler(**COGVIDEOX_2B)


def test_alphas_cumprod_match_diffusers():
    ours = cogvideox_alphas_cumprod()
    ref = _sched().alphas_cumprod.to(torch.float64)
    torch.testing.assert_close(ours, ref, rtol=0, atol=1e-12)
    assert ours[-1] == 0.0 and 0.997 < ours[0] < 0.998  # SNR shift by 3 lowers ᾱ_0 from 0.99915
    assert torch.all(ours[1:] < ours[:-1])


@pytest.mark.parametrize("n", [1, 3, 7, 10, 30, 50, 100, 333, 1000])
def test_trailing_timesteps_match_diffusers(n):
    s = _sched()
    s.set_timesteps(n)
    assert ddim_timesteps(n) == s.timesteps.tolist()
    assert ddim_timesteps(n)[0] == 999


def test_timesteps_50():
    ts = ddim_timesteps(50)
    assert ts[:3] == [999, 979, 959] and ts[-1] == 19 and len(ts) == 50


@pytest.mark.parametrize("n", [50, 8, 4])
def test_ddim_loop_matches_diffusers(n):
    """Same inputs, same 'model' (a fixed nonlinear function of x and t): every step equal to diffusers'."""
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, 3, 4, 5, 6, generator=g, dtype=torch.float64)
    w = torch.randn(4, 4, generator=g, dtype=torch.float64) * 0.3

    def fake_v(x, t):  # depends on x and t so an off-by-one in the schedule would show
        return torch.tanh(torch.einsum("btchw,cd->btdhw", x, w)) * (1 + t / 1000.0) + 0.1 * x

    ref_s = _sched()
    ref_s.alphas_cumprod = ref_s.alphas_cumprod.to(torch.float64)
    ref_s.set_timesteps(n)
    xr, xo = x.clone(), x.clone()
    ours = DDIMSchedule(n)
    assert [s.t for s in ours] == ref_s.timesteps.tolist()
    for step in ours:
        xr_next = ref_s.step(fake_v(xr, step.t), step.t, xr).prev_sample
        xo_next, _ = ddim_step(xo, fake_v(xo, step.t), step.a_t, step.a_prev)
        torch.testing.assert_close(xo_next, xr_next, rtol=1e-10, atol=1e-10)
        xr, xo = xr_next, xo_next
    assert torch.isfinite(xo).all()


def test_ddim_step_float32_close_to_diffusers():
    s = _sched()
    s.set_timesteps(50)
    x = torch.randn(1, 2, 4, 3, 3)
    v = torch.randn_like(x)
    ref = s.step(v, 979, x).prev_sample
    step = DDIMSchedule(50).steps[1]
    ours, _ = ddim_step(x, v, step.a_t, step.a_prev)
    assert ours.dtype == torch.float32
    torch.testing.assert_close(ours, ref.float(), rtol=1e-5, atol=1e-5)


def test_perfect_v_recovers_x0_in_one_step():
    """If the model predicts the true v, a single DDIM step from any level lands exactly on x0."""
    ac = cogvideox_alphas_cumprod()
    x0 = torch.randn(2, 3, 4, 2, 2, dtype=torch.float64)
    eps = torch.randn_like(x0)
    for t in (999, 500, 10):
        a = float(ac[t])
        x_t = forward_noise(x0, eps, a)
        v = a ** 0.5 * eps - (1 - a) ** 0.5 * x0
        x_prev, x0_hat = ddim_step(x_t, v, a, 1.0)
        torch.testing.assert_close(x0_hat, x0)
        torch.testing.assert_close(x_prev, x0)


def test_bad_step_count():
    with pytest.raises(ValueError, match="num_steps"):
        ddim_timesteps(0)
    with pytest.raises(ValueError, match="num_steps"):
        ddim_timesteps(1001)
