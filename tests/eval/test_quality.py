"""VideoQualityEvaluator: identical sets score the ideal values, horizons bin as specified, streaming equals
one pass, conditioning frames never count, the protocol names everything. Small stand-in feature networks
keep this fast; the real Inception/I3D/LPIPS networks are tested in test_feature_nets.py."""
import math

import pytest
import torch
from torch import nn

from resim.config import ConfigError
from resim.eval.fidelity import PSNR_CAP_DB, psnr, ssim
from resim.eval.lpips import LPIPS
from resim.eval.quality import Networks, QualityConfig, VideoQualityEvaluator, build_networks, horizon_bins
from resim.eval.report import format_quality, plot_quality
from resim.shards.safejson import write_json


class FrameFeat(nn.Module):
    """(N, 3, H, W) [0, 1] -> (N, 12): a fixed random conv net standing in for Inception."""
    weights_sha256 = "random-init"

    def __init__(self):
        super().__init__()
        g = torch.Generator().manual_seed(0)
        self.w = nn.Parameter(torch.randn(12, 3, 5, 5, generator=g) * 0.3, requires_grad=False)

    def forward(self, x):
        return torch.tanh(nn.functional.conv2d(x.float() * 2 - 1, self.w, stride=2)).mean(dim=(2, 3))


class ClipFeat(FrameFeat):
    """(B, T, 3, H, W) -> (B, 24): frame features averaged + temporal differences (stands in for I3D)."""

    def forward(self, clips):
        f = super().forward(clips.flatten(0, 1)).view(clips.shape[0], clips.shape[1], -1)
        return torch.cat([f.mean(1), (f[:, 1:] - f[:, :-1]).abs().mean(1)], dim=1)


def _nets(lpips=None):
    return Networks(fid=FrameFeat(), fvd=ClipFeat(), lpips=lpips, names={"fid": "stand-in", "fvd": "stand-in"},
                    dreamsim_reason="not installed (test)")


def _clips(n=6, t=14, seed=0, hw=(24, 32)):
    g = torch.Generator().manual_seed(seed)
    return torch.randint(0, 256, (n, t, 3, *hw), generator=g, dtype=torch.uint8)


def _cfg(**kw):
    base = dict(fps_hz=4.0, num_conditioning_frames=2, metrics=("psnr", "ssim", "fid", "fvd", "dreamsim"))
    base.update(kw)
    return QualityConfig(**base)


def test_horizon_bins_closed_form():
    bins = horizon_bins(40, 10.0)
    assert [(b["from_s"], b["horizon_s"]) for b in bins] == [(0.0, 1.0), (1.0, 2.0), (2.0, 4.0)]
    assert bins[0]["frames"] == list(range(10)) and bins[1]["frames"] == list(range(10, 20))
    assert bins[2]["frames"] == list(range(20, 40))
    # 50 frames = 5 s: the 8 s bin holds the last second only; explicit horizons respected
    assert [len(b["frames"]) for b in horizon_bins(50, 10.0)] == [10, 10, 20, 10]
    assert [b["horizon_s"] for b in horizon_bins(12, 4.0, (0.5, 3.0))] == [0.5, 3.0]
    with pytest.raises(ValueError, match="no future frames"):
        horizon_bins(0, 10.0)


def test_identical_sets_score_ideal_values():
    torch.manual_seed(0)
    lp = LPIPS("alex")
    for i in range(5):  # non-negative heads, as trained LPIPS heads are
        getattr(lp, f"lin{i}").model[1].weight.data.abs_()
    gt = _clips(n=3, hw=(64, 64), t=11)
    ev = VideoQualityEvaluator(_cfg(metrics=("psnr", "ssim", "lpips", "fid", "fvd")), _nets(lpips=lp))
    with pytest.warns(UserWarning, match="biased"):
        ev.update(gt.clone(), gt)
        rep = ev.compute()
    o = rep["overall"]
    assert o["psnr"]["mean"] == PSNR_CAP_DB and o["psnr"]["std"] == 0
    assert o["ssim"]["mean"] == pytest.approx(1.0, abs=1e-12)
    assert o["lpips"]["mean"] == pytest.approx(0.0, abs=1e-6)
    assert o["fid"] == pytest.approx(0.0, abs=1e-6)
    assert o["fvd"] == pytest.approx(0.0, abs=1e-6)
    assert all(r["fid"] == pytest.approx(0.0, abs=1e-6) for r in rep["per_horizon"])
    assert any("biased" in w for w in rep["warnings"])


def test_per_horizon_values_equal_direct_computation_and_streaming_equals_one_pass():
    gt, gen = _clips(seed=1), _clips(seed=2) // 2  # darker: a shifted feature distribution
    gen[:, :, :, :12] = gt[:, :, :, :12]  # partly right, so SSIM/PSNR are informative
    one = VideoQualityEvaluator(_cfg(), _nets())
    two = VideoQualityEvaluator(_cfg(), _nets())
    with pytest.warns(UserWarning):
        one.update(gen, gt)
        two.update(gen[:2], gt[:2])
        two.update(gen[2:], gt[2:])
        r1, r2 = one.compute(), two.compute()
    p = psnr(gen[:, 2:], gt[:, 2:], "uint8")  # (B, 12 future frames); fps 4 -> bins (0,1],(1,2],(2,4]
    s = ssim(gen[:, 2:], gt[:, 2:], "uint8")
    for row, ks in zip(r1["per_horizon"], [range(0, 4), range(4, 8), range(8, 12)]):
        ks = list(ks)
        assert row["psnr"] == pytest.approx(float(p[:, ks].mean()), rel=1e-9)
        assert row["ssim"] == pytest.approx(float(s[:, ks].mean()), rel=1e-9)
    assert r1["overall"]["psnr"]["mean"] == pytest.approx(float(p.mean()), rel=1e-9)
    for a, b in zip(r1["per_horizon"], r2["per_horizon"]):
        for k in ("psnr", "ssim", "fid"):
            assert a[k] == pytest.approx(b[k], rel=1e-6, abs=1e-9)
    assert r1["overall"]["fvd"] == pytest.approx(r2["overall"]["fvd"], rel=1e-6)
    assert r1["overall"]["fid"] > 0.01 and r1["overall"]["fvd"] > 0.0
    assert r1["protocol"]["clips"] == 6 and r1["protocol"]["future_frames_scored"] == 12


def test_conditioning_frames_excluded_and_resize_in_protocol():
    gt = _clips(seed=3)
    gen = gt.clone()
    gen[:, :2] = 255 - gen[:, :2]  # wrong conditioning frames only: must not count
    ev = VideoQualityEvaluator(_cfg(resolution_hw=(16, 20), metrics=("psnr", "ssim", "fid")), _nets())
    with pytest.warns(UserWarning):
        ev.update(gen, gt)
        rep = ev.compute()
    assert rep["overall"]["psnr"]["mean"] == PSNR_CAP_DB
    pr = rep["protocol"]
    assert pr["conditioning_frames_excluded"] == 2 and pr["metric_resolution_hw"] == [16, 20]
    assert "bilinear" in pr["resize"] and pr["input_resolution_hw"] == [24, 32]
    assert pr["networks"]["fid"]["weights_sha256"] == "random-init" and pr["placeholder_networks"] == ["fid"]
    text = format_quality(rep)
    assert text.startswith("protocol:") and "random-init" in text and "PLACEHOLDER" not in text
    assert any("placeholder" in w for w in rep["warnings"])


def test_dreamsim_reported_not_available_with_reason(tmp_path):
    ev = VideoQualityEvaluator(_cfg(metrics=("psnr", "dreamsim")), _nets())
    ev.update(_clips(n=2), _clips(n=2, seed=5))
    rep = ev.compute()
    assert rep["protocol"]["dreamsim"]["available"] is False
    assert rep["overall"]["dreamsim"].startswith("not available: ") and "dreamsim" not in rep["per_frame"]
    write_json(rep, tmp_path / "q.json")
    plot_quality(rep, tmp_path / "q.png")
    assert (tmp_path / "q.png").stat().st_size > 1000


def test_value_range_and_shape_errors():
    ev = VideoQualityEvaluator(_cfg(metrics=("psnr",)), _nets())
    with pytest.raises(ValueError, match="floating point"):
        ev.update(_clips().float(), _clips().float())
    ev2 = VideoQualityEvaluator(_cfg(value_range="unit", metrics=("psnr",)), _nets())
    with pytest.raises(ValueError, match="values span"):
        ev2.update(_clips().float(), _clips().float())
    ev.update(_clips(), _clips(seed=4))
    with pytest.raises(ValueError, match="one evaluator per clip geometry"):
        ev.update(_clips(t=10), _clips(t=10))
    with pytest.raises(ValueError, match="differ in shape"):
        ev.update(_clips(), _clips(hw=(24, 30)))
    with pytest.raises(ConfigError, match="unknown metrics"):
        QualityConfig(metrics=("psnr", "is"))


def test_networks_need_weights_unless_placeholders_allowed():
    with pytest.raises(ConfigError, match="allow_placeholder_networks"):
        build_networks(QualityConfig(metrics=("lpips",)), "cpu")
    nets = build_networks(QualityConfig(metrics=("lpips",), lpips_net="alex", allow_placeholder_networks=True), "cpu")
    assert nets.lpips.weights_sha256 == "random-init" and nets.fid is None and nets.fvd is None
    assert "not requested" in nets.dreamsim_reason or "not installed" in nets.dreamsim_reason or nets.dreamsim_reason
    assert math.isfinite(float(nets.lpips(torch.rand(1, 3, 64, 64), torch.rand(1, 3, 64, 64))))


def test_rejected_batches_leave_the_evaluator_untouched():
    """A rejected first batch used to fix the clip geometry (frames, size) anyway: every valid batch after it
    was refused as "another geometry", and compute() then returned an empty report."""
    ev = VideoQualityEvaluator(_cfg(metrics=("psnr", "ssim")), _nets())
    bad = torch.rand(1, 10, 3, 16, 16)                       # float frames, value_range uint8
    with pytest.raises(ValueError, match="floating point"):
        ev.update(bad, bad)
    tiny = _clips(n=1, hw=(8, 8))                            # passes the range check, fails in SSIM
    with pytest.raises(ValueError, match="smaller than the 11x11 SSIM window"):
        ev.update(tiny, tiny)
    with pytest.raises(ValueError, match="no future frames"):
        ev.update(_clips(n=1, t=2), _clips(n=1, t=2))        # only conditioning frames
    with pytest.raises(ValueError, match="no clips were added"):
        ev.compute()
    gt = _clips(n=2)
    ev.update(gt.clone(), gt)                                # the first valid batch sets the geometry
    rep = ev.compute()
    assert rep["protocol"]["clips"] == 2 and rep["protocol"]["input_resolution_hw"] == [24, 32]
    assert rep["overall"]["psnr"]["mean"] == PSNR_CAP_DB and rep["overall"]["psnr"]["frames"] == 2 * 12


def test_non_finite_config_and_missing_weight_files_are_config_errors(tmp_path):
    with pytest.raises(ConfigError, match="fps_hz must be a finite number"):
        QualityConfig(fps_hz=float("nan"))
    with pytest.raises(ConfigError, match="horizons_s"):
        QualityConfig(horizons_s=(1.0, float("nan")))
    # a missing weights file used to surface as FileNotFoundError from deep inside the loader
    with pytest.raises(ConfigError, match=r"fid: fid_weights .*nonexist.pth is not a file"):
        build_networks(QualityConfig(metrics=("fid",), fid_weights=tmp_path / "nonexist.pth"), "cpu")
    junk = tmp_path / "junk.pth"
    junk.write_bytes(b"not a checkpoint" * 10)
    with pytest.raises(ConfigError, match="fvd: cannot load its weights"):
        build_networks(QualityConfig(metrics=("fvd",), fvd_weights=junk), "cpu")
