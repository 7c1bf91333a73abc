"""`resim eval detail`: the heading kept by the model's one-step prediction, on a model that knows the future and
one that predicts the mean (nothing), through a stand-in decoder and labeler that read the heading off the latents."""
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from training.diffusion.schedule import alphas_cumprod
from training.eval.detail_probe import (detail_probe, format_probe, kept_slope, one_step_predictions,
                                         paired_kept_difference)
from training.eval.worldeval import EvalClip

AC = alphas_cumprod()
H, T_LAT = 2, 5


class Oracle(torch.nn.Module):
    """Knows every clip's future (``futures`` (B, F, C, h, w), all clips in one batch): the exact v at any level."""

    def __init__(self, futures):
        super().__init__()
        self.futures = futures

    def forward(self, x, t, text, *rest, **kw):
        x0 = torch.cat([x[:, :H], self.futures[: x.shape[0]]], 1)
        a = AC[t].view(*t.shape, 1, 1, 1).to(x)
        noise = (x - a.sqrt() * x0) / (1 - a).clamp_min(1e-12).sqrt()
        return a.sqrt() * noise - (1 - a).sqrt() * x0


class Mean(torch.nn.Module):
    """Predicts x0 = 0 for the future whatever it sees (the mean of a zero-mean world): keeps no turn."""

    def forward(self, x, t, text, *rest, **kw):
        a = AC[t].view(*t.shape, 1, 1, 1).to(x)
        return a.sqrt() * x / (1 - a).clamp_min(1e-12).sqrt()   # v = sqrt(a) eps with x0 = 0, eps = x / sqrt(1 - a)


def _clips(yaws):
    """Clips whose future latents are their heading (degrees / 10) everywhere; history zeros."""
    out = []
    for i, y in enumerate(yaws):
        lat = np.zeros((T_LAT, 1, 2, 2), np.float32)
        lat[H:] = y / 10.0
        cmd = "Turning left" if y > 15 else "Turning right" if y < -15 else "Moving forward"
        frames = np.full((1 + 4 * (T_LAT - 1), 4, 4, 3), 0, np.uint8)
        frames[1 + 4 * (H - 1):] = np.uint8(128 + y)          # the originals' stand-in heading
        out.append(EvalClip(f"k{i}", f"ep{i}", lat, frames, None, cmd, 1 + 4 * (H - 1), 10.0, False))
    return out


class Labeler:
    """Reads the heading as the future frames' mean grey level - 128 (the stand-in decoder writes it there)."""

    def label(self, frames, fps_hz):
        y = float(np.mean(np.stack(frames[1:]).astype(np.float64))) - 128.0
        cmd = "Turning left" if y > 15 else "Turning right" if y < -15 else "Moving forward"
        return SimpleNamespace(command=cmd, yaw_deg=y)


def _runner(model, clips):
    def decode(cl, lat):
        v = np.zeros((lat.shape[0], 1 + 4 * (lat.shape[1] - 1), 4, 4, 3), np.uint8)
        fut = lat[:, H:].mean(dim=(1, 2, 3, 4)).numpy() * 10.0
        v[:, 1 + 4 * (H - 1):] = np.clip(np.round(128 + fut), 0, 255).astype(np.uint8)[:, None, None, None, None]
        return v

    return SimpleNamespace(model=model, schedule=None, batch_size=8, history_latents=lambda c: H,
                           text_for=lambda c: torch.zeros(1, 2, 4), decode=decode,
                           decode_recorded=lambda cl: decode(cl, torch.from_numpy(np.stack([c.latents for c in cl]))))


def test_kept_slope():
    ref = np.array([30.0, -40.0, 2.0, 20.0])
    r = kept_slope(0.5 * ref, ref)
    assert r["slope"] == pytest.approx(0.5) and r["ci95"][0] == pytest.approx(0.5) and r["ci95"][1] == pytest.approx(0.5)
    noisy = kept_slope(0.5 * ref + np.array([3.0, -2.0, 5.0, 1.0]), ref)
    assert noisy["ci95"][0] < noisy["slope"] < noisy["ci95"][1]
    assert np.isnan(kept_slope([1.0, 2.0], [0.0, 0.0])["slope"])
    with pytest.raises(ValueError):
        kept_slope([1.0], [1.0, 2.0])


def test_one_step_prediction_of_a_model_that_knows_the_future_is_that_future():
    clips = _clips([30.0, -40.0, 0.0])
    lat = torch.from_numpy(np.stack([c.latents for c in clips]))
    noise = torch.randn(lat[:, H:].shape, generator=torch.Generator().manual_seed(0))
    for level in (0, 99, 700):
        x0 = one_step_predictions(Oracle(lat[:, H:]), lat, H, torch.zeros(3, 2, 4), level, noise, batch_size=8)
        assert torch.allclose(x0, lat[:, H:], atol=1e-4), level
    with pytest.raises(ValueError, match="level"):
        one_step_predictions(Mean(), lat, H, torch.zeros(3, 2, 4), 1000, noise)


def test_the_probe_reads_a_kept_turn_as_kept_and_a_mean_prediction_as_lost():
    yaws = [30.0, -40.0, 0.0, 25.0, -20.0, 5.0]
    clips = _clips(yaws)
    futures = torch.from_numpy(np.stack([c.latents[H:] for c in clips]))
    good = detail_probe(_runner(Oracle(futures), clips), clips, Labeler(), levels=(0, 99, 499))
    assert good["recorded_through_vae"]["labeler_accuracy"] == 1.0
    for r in good["per_level"]:
        assert r["kept"]["slope"] == pytest.approx(1.0, abs=0.02) and r["labeler_accuracy"] == 1.0
        assert r["latent_mse"] < 1e-6
    bad = detail_probe(_runner(Mean(), clips), clips, Labeler(), levels=(0, 99, 499))
    for r in bad["per_level"]:
        assert abs(r["kept"]["slope"]) < 0.05 and r["latent_mse"] > 0.5
        assert r["labeler_accuracy"] == pytest.approx(2 / 6)    # every future read "forward": the 2 forward clips
    text = format_probe(bad)
    assert "one step from level 99" in text and "heading kept" in text


def test_paired_difference_of_two_models_on_the_same_clips():
    yaws = [30.0, -40.0, 0.0, 25.0, -20.0, 5.0]
    clips = _clips(yaws)
    futures = torch.from_numpy(np.stack([c.latents[H:] for c in clips]))
    good = detail_probe(_runner(Oracle(futures), clips), clips, Labeler(), levels=(0, 99))
    bad = detail_probe(_runner(Mean(), clips), clips, Labeler(), levels=(99, 499))
    diff = paired_kept_difference(good, bad)
    assert [d["level"] for d in diff] == [99]                 # only the levels both have
    assert diff[0]["difference"] == pytest.approx(1.0, abs=0.05) and diff[0]["ci95"][0] > 0.9
    other = detail_probe(_runner(Mean(), clips[:5]), clips[:5], Labeler(), levels=(99,))
    with pytest.raises(ValueError, match="same clips"):
        paired_kept_difference(good, other)
