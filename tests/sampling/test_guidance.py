"""Guidance schedules vs. their formulas; guidance rescale vs. its closed form and diffusers' rescale_noise_cfg."""
import math

import pytest
import torch

from resim.config import ConfigError
from resim.diffusion.guidance import (GuidanceConfig, cfg_combine, combine_branches, guidance_preset,
                                        guidance_scales, rescale_guidance)


def test_linear_resim_schedule():
    w = guidance_scales("linear", 50, 7.5, 1.0)
    assert len(w) == 50 and w[0] == 7.5 and w[-1] == pytest.approx(1.0, abs=1e-12)
    steps = [w[i] - w[i + 1] for i in range(49)]
    assert all(d == pytest.approx(6.5 / 49) for d in steps)  # evenly decreasing
    assert w[10] == pytest.approx(7.5 - 6.5 * 10 / 49)


def test_constant_and_cosine_schedules():
    assert guidance_scales("constant", 7, 2.5) == [2.5] * 7
    w = guidance_scales("cosine", 11, 7.5, 1.0)
    assert w[0] == pytest.approx(7.5) and w[-1] == pytest.approx(1.0) and w[5] == pytest.approx(4.25)
    for i, wi in enumerate(w):
        assert wi == pytest.approx(1.0 + 6.5 * (1 + math.cos(math.pi * i / 10)) / 2)
    assert all(w[i] >= w[i + 1] for i in range(10))
    assert guidance_scales("linear", 1, 7.5, 1.0) == [7.5]
    with pytest.raises(ValueError, match="unknown guidance schedule"):
        guidance_scales("quadratic", 5, 2.0)


def test_cfg_combine():
    c, u = torch.tensor([2.0, -1.0]), torch.tensor([1.0, 1.0])
    torch.testing.assert_close(cfg_combine(c, u, 3.0), torch.tensor([4.0, -5.0]))
    torch.testing.assert_close(cfg_combine(c, u, 1.0), c)
    torch.testing.assert_close(cfg_combine(c, u, 0.0), u)


def test_rescale_closed_form():
    """v_c = a z, v_u = b z  =>  v_cfg = k z with k = b + w (a - b), std ratio |a|/|k|;
    rescaled = phi * sign(k) |a| z + (1 - phi) k z."""
    torch.manual_seed(0)
    z = torch.randn(3, 4, 2, 5, 5)
    a = torch.tensor([1.5, -0.5, 2.0]).view(3, 1, 1, 1, 1)
    b = torch.tensor([0.5, 1.0, 2.5]).view(3, 1, 1, 1, 1)
    w, phi = 2.5, 0.7
    v_c, v_u = a * z, b * z
    k = b + w * (a - b)
    expected = phi * torch.sign(k) * a.abs() * z + (1 - phi) * k * z
    got = rescale_guidance(cfg_combine(v_c, v_u, w), v_c, phi)
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-5)
    # after full rescale (phi=1) each sample's std equals the conditional one's
    full = rescale_guidance(cfg_combine(v_c, v_u, w), v_c, 1.0)
    torch.testing.assert_close(full.flatten(1).std(1), v_c.flatten(1).std(1), rtol=1e-5, atol=1e-6)
    assert rescale_guidance(v_c, v_u, 0.0) is v_c


def test_rescale_matches_diffusers():
    from diffusers.pipelines.stable_diffusion.pipeline_stable_diffusion import rescale_noise_cfg
    torch.manual_seed(1)
    v_c, v_u = torch.randn(2, 3, 4, 6, 6), torch.randn(2, 3, 4, 6, 6)
    g = cfg_combine(v_c, v_u, 2.5)
    torch.testing.assert_close(rescale_guidance(g, v_c, 0.7), rescale_noise_cfg(g, v_c, guidance_rescale=0.7))


def test_combine_branches_batched():
    torch.manual_seed(2)
    v_c, v_u = torch.randn(2, 3, 4), torch.randn(2, 3, 4)
    both = torch.cat([v_c, v_u])
    torch.testing.assert_close(combine_branches(both, 1.0, 0.7), v_c)
    torch.testing.assert_close(combine_branches(both, 2.5, 0.0), cfg_combine(v_c, v_u, 2.5))
    torch.testing.assert_close(combine_branches(both, 2.5, 0.7),
                               rescale_guidance(cfg_combine(v_c, v_u, 2.5), v_c, 0.7))


def test_presets_and_validation():
    r = guidance_preset("resim")
    assert r.scales(50)[0] == 7.5 and r.scales(50)[-1] == pytest.approx(1.0)
    v = guidance_preset("vid2world")
    assert v.scales(5) == [2.5] * 5 and v.rescale_phi == 0.7 and v.drop_recent_actions and not v.drop_text
    assert guidance_preset("none").scales(3) == [1.0] * 3
    with pytest.raises(ConfigError, match="rescale_phi"):
        GuidanceConfig(rescale_phi=1.5)
    with pytest.raises(ConfigError, match="drops nothing"):
        GuidanceConfig(drop_text=False, drop_trajectory=False)
    with pytest.raises(ConfigError, match="unknown guidance preset"):
        guidance_preset("nope")


@pytest.mark.parametrize("schedule,expect", [(None, [7.5, 4.25, 1.0]), ("constant", [7.5, 7.5, 7.5]),
                                             ("linear", [7.5, 4.25, 1.0])])
def test_guidance_schedule_setting_reaches_the_rollout_config(schedule, expect, tmp_path):
    """`resim sample --set rollout.guidance.schedule=...` (and `resim eval`, through the same settings) sets the
    per-step scales: the default stays ReSim's linear 7.5 -> 1."""
    from resim.cli import build_parser
    from resim.sample.settings import resolve_settings

    argv = ["sample", "--checkpoint", str(tmp_path), "--history", "h.mp4", "--out", "o", "--steps", "3"]
    if schedule:
        argv += ["--set", f"rollout.guidance.schedule={schedule}"]
    cfg = resolve_settings(build_parser().parse_args(argv)).rollout
    assert cfg.num_steps == 3 and cfg.guidance.scales(3) == pytest.approx(expect)


def test_a_constant_schedule_keeps_the_given_start_scale(tmp_path):
    """vid2world's constant guidance: a start scale set alone is its scale at every step."""
    from resim.sample.settings import rollout_config_for

    cfg, _ = rollout_config_for(tmp_path, "vid2world", 2, overrides={"guidance": {"scale_start": 3.0}})
    assert cfg.guidance.scales(2) == [3.0, 3.0] and cfg.guidance.scale_end == 3.0 and cfg.chunk_frames == 1
    cfg, _ = rollout_config_for(tmp_path, "resim", None, no_guidance=True, overrides={"chunk_frames": 5})
    assert not cfg.guidance.enabled and cfg.num_steps == 50 and cfg.chunk_frames == 5


def test_guidance_from_cli_is_shared_by_eval_and_sample():
    """One place turns a guidance preset, a start scale and a schedule into a GuidanceConfig (the settings of
    every sampling command, and distillation's teacher)."""
    from resim.diffusion.guidance import guidance_from_cli

    assert guidance_from_cli("resim").scales(3) == pytest.approx([7.5, 4.25, 1.0])
    assert guidance_from_cli("resim", 4.0, "constant").scales(2) == [4.0, 4.0]
    assert guidance_from_cli("vid2world", 3.0).scales(2) == [3.0, 3.0] and guidance_from_cli("vid2world", 3.0).scale_end == 3.0
    assert not guidance_from_cli("none", 9.0, "constant").enabled
