"""The quality report says how many frames scored the PSNR cap (identical frames: infinite PSNR, capped at
PSNR_CAP_DB), overall, per horizon and per frame, so a mean that includes capped values never passes silently."""
import pytest
import torch

from resim.eval.fidelity import PSNR_CAP_DB, psnr
from resim.eval.quality import Networks, QualityConfig, VideoQualityEvaluator
from resim.eval.report import format_quality


def _evaluator():
    # 2 conditioning + 8 future frames at 2 Hz: horizon bins (0, 1] s = future frames 0-1, (1, 2] = 2-3, (2, 4] = 4-7
    return VideoQualityEvaluator(QualityConfig(metrics=("psnr",), num_conditioning_frames=2, fps_hz=2.0), Networks())


def _pair(seed: int):
    g = torch.Generator().manual_seed(seed)
    gt = torch.randint(0, 256, (3, 10, 3, 16, 16), generator=g, dtype=torch.uint8)
    gen = gt.clone()
    noise = torch.randint(-20, 21, gt.shape, generator=g)
    differ = torch.zeros(3, 10, dtype=torch.bool)
    differ[0, 2:] = True            # clip 0: every future frame differs
    differ[1, [3, 7, 8]] = True     # clip 1: future frames 1, 5, 6 differ
    differ[2, :2] = True            # clip 2: only conditioning frames differ (never scored)
    gen = torch.where(differ[..., None, None, None], (gt.long() + noise).clamp(0, 255).to(torch.uint8), gen)
    return gen, gt


def test_capped_frames_reported_overall_per_horizon_per_frame():
    gen, gt = _pair(0)
    ev = _evaluator()
    ev.update(gen[:2], gt[:2])
    ev.update(gen[2:], gt[2:])                      # streaming: counts add up over batches
    rep = ev.compute()
    p = psnr(gen[:, 2:], gt[:, 2:], "uint8")        # (3, 8) independent per-frame values
    capped = p >= PSNR_CAP_DB
    assert int(capped.sum()) == 5 + 8               # clip 1: 5 identical future frames; clip 2: all 8
    o = rep["overall"]["psnr"]
    assert o["frames"] == 24 and o["capped_frames"] == 13 and o["cap_db"] == PSNR_CAP_DB
    assert o["mean"] == pytest.approx(float(p.mean()), rel=1e-12)  # the mean still includes them ...
    assert any("13 of 24" in w and "PSNR" in w for w in rep["warnings"])   # ... and the report says so
    assert [r["psnr_capped_frames"] for r in rep["per_horizon"]] == [
        int(capped[:, 0:2].sum()), int(capped[:, 2:4].sum()), int(capped[:, 4:8].sum())]
    assert rep["per_frame"]["psnr_capped_frames"] == capped.sum(0).tolist()
    text = format_quality(rep)
    assert "psnr capped" in text and "capped_frames=13" in text


def test_no_capped_frames_reports_zero_and_no_warning():
    gen, gt = _pair(1)
    gen = (gt.long() + 1).clamp(max=255).to(torch.uint8)   # every frame differs a little somewhere
    gen[..., 0, 0, 0] = gt[..., 0, 0, 0] ^ 1
    ev = _evaluator()
    ev.update(gen, gt)
    rep = ev.compute()
    assert rep["overall"]["psnr"]["capped_frames"] == 0 and rep["overall"]["psnr"]["mean"] < PSNR_CAP_DB
    assert all(r["psnr_capped_frames"] == 0 for r in rep["per_horizon"])
    assert not any("PSNR" in w for w in rep["warnings"])
