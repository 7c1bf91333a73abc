import numpy as np
import pytest
from scipy import stats

from resim.train.tasks.reward.metrics import auc, mae, rankdata, reward_metrics, spearman


def test_rankdata_and_spearman_match_scipy():
    rng = np.random.default_rng(0)
    for _ in range(20):
        a = rng.integers(0, 6, 25).astype(float)   # many ties
        b = a + rng.normal(0, 2, 25)
        np.testing.assert_allclose(rankdata(a), stats.rankdata(a))
        assert spearman(a, b) == pytest.approx(stats.spearmanr(a, b).statistic, abs=1e-12)


def test_auc_is_pairwise_probability():
    rng = np.random.default_rng(1)
    s = rng.integers(0, 5, 40).astype(float)
    y = rng.random(40) < 0.4
    pos, neg = s[y], s[~y]
    brute = np.mean([(p > n) + 0.5 * (p == n) for p in pos for n in neg])
    assert auc(s, y) == pytest.approx(brute)
    assert auc([0.1, 0.2, 0.9, 0.8], [False, False, True, True]) == 1.0
    with pytest.raises(ValueError, match="both classes"):
        auc([1.0, 2.0], [True, True])


def test_reward_metrics_hazard_direction():
    true = np.array([0.1, 0.2, 0.9, 1.0])
    m = reward_metrics(true + 0.05, true, true < 0.5)
    assert m["mae"] == pytest.approx(0.05) and m["spearman"] == pytest.approx(1.0)
    assert m["hazard_auc"] == 1.0  # low predicted score = hazardous
    assert mae([1.0], [0.0]) == 1.0


def test_undefined_metrics_are_nan_not_errors():
    """A held-out split of one clip is a legitimate (useless) outcome of a small dataset: Spearman is nan
    (undefined) instead of raising after training, so the run still writes its checkpoint."""
    assert np.isnan(spearman([0.4], [0.2]))
    assert np.isnan(spearman([], []))
    with pytest.raises(ValueError, match="one shape"):
        spearman([0.1, 0.2], [0.1, 0.2, 0.3])   # a caller bug still raises
    m = reward_metrics(np.array([0.4]), np.array([0.2]), np.array([True]))
    assert m["n"] == 1 and m["mae"] == pytest.approx(0.2)
    assert np.isnan(m["spearman"]) and np.isnan(m["hazard_auc"])
