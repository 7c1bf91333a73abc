"""PSNR/SSIM against scikit-image; the Fréchet distance against scipy in float64."""
import numpy as np
import pytest
import scipy.linalg
import torch
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from resim.eval.fidelity import PSNR_CAP_DB, psnr, ssim
from resim.eval.frechet import FeatureStats, frechet_distance, frechet_from_stats


def _videos(seed=0, shape=(2, 3, 3, 32, 40)):
    g = torch.Generator().manual_seed(seed)
    a = torch.randint(0, 256, shape, generator=g, dtype=torch.uint8)
    noise = torch.randint(-40, 41, shape, generator=g)
    b = (a.int() + noise).clamp(0, 255).to(torch.uint8)
    return a, b


def test_ssim_matches_skimage():
    a, b = _videos()
    ours = ssim(a, b, "uint8")
    for i in range(a.shape[0]):
        for t in range(a.shape[1]):
            x = a[i, t].permute(1, 2, 0).numpy().astype(np.float64) / 255
            y = b[i, t].permute(1, 2, 0).numpy().astype(np.float64) / 255
            ref = structural_similarity(x, y, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                        data_range=1.0, channel_axis=2)
            assert ours[i, t].item() == pytest.approx(ref, abs=1e-10)


def test_psnr_matches_skimage_and_caps_identical():
    a, b = _videos(1)
    ours = psnr(a, b, "uint8")
    ref = peak_signal_noise_ratio(a[0, 0].numpy(), b[0, 0].numpy(), data_range=255)
    assert ours[0, 0].item() == pytest.approx(ref, rel=1e-10)
    same = psnr(a, a, "uint8")
    assert torch.all(same == PSNR_CAP_DB)
    assert torch.allclose(ssim(a, a, "uint8"), torch.ones(2, 3, dtype=torch.float64))


def test_value_range_must_be_stated_correctly():
    a, _ = _videos()
    with pytest.raises(ValueError, match="floating point"):
        psnr(a.float(), a.float(), "uint8")
    with pytest.raises(ValueError, match="span"):
        psnr(a.float(), a.float(), "unit")


def test_frechet_against_scipy_float64():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(400, 16)) @ rng.normal(size=(16, 16))
    y = rng.normal(size=(300, 16)) @ rng.normal(size=(16, 16)) + 0.5
    mu1, mu2 = x.mean(0), y.mean(0)
    c1, c2 = np.cov(x, rowvar=False), np.cov(y, rowvar=False)
    covmean = scipy.linalg.sqrtm(c1 @ c2).real
    ref = ((mu1 - mu2) ** 2).sum() + np.trace(c1 + c2 - 2 * covmean)
    sx, sy = FeatureStats(16), FeatureStats(16)
    for chunk in np.array_split(x, 7):  # streaming in chunks gives the same statistics
        sx.update(torch.from_numpy(chunk))
    sy.update(torch.from_numpy(y))
    with pytest.warns(UserWarning, match="biased"):
        res = frechet_from_stats(sx, sy)
    assert res.value == pytest.approx(ref, rel=1e-8)
    assert frechet_distance(*sx.mean_cov(), *sx.mean_cov()) == pytest.approx(0.0, abs=1e-8)
