"""Adaptive importance sampling and the importance posterior's own checks
(treeinfer.inference.importance), and the NumPy draws and Latin hypercube that replaced scipy.stats
on the fast path.

References: scipy.stats densities and scipy.stats.qmc points; closed-form moments of Gaussian
targets; numpy.quantile for the weighted band width.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from treeinfer.errors import ConfigError
from treeinfer.inference.fast import latin_hypercube
from treeinfer.inference.importance import (
    KHAT_LIMIT,
    _draw,
    _weighted_width,
    adaptive_importance,
    band_split,
    weighted_moments,
)

MEAN = np.array([1.0, -2.0, 0.5])
COV = np.array([[2.0, 0.6, 0.0], [0.6, 1.0, 0.3], [0.0, 0.3, 0.4]])


@pytest.mark.parametrize("df", [np.inf, 5.0])
def test_draws_and_densities_equal_scipy(df):
    x, log_q = _draw(np.random.default_rng(0), MEAN, COV, 40000, df)
    ref = (
        stats.multivariate_normal(MEAN, COV)
        if np.isinf(df)
        else stats.multivariate_t(MEAN, COV, df=df)
    )
    np.testing.assert_allclose(log_q, ref.logpdf(x), rtol=1e-12, atol=1e-12)
    scale = 1.0 if np.isinf(df) else df / (df - 2.0)  # the t's covariance
    np.testing.assert_allclose(np.cov(x.T), COV * scale, atol=0.06 * scale)
    np.testing.assert_allclose(x.mean(0), MEAN, atol=0.03)


def test_latin_hypercube_equals_scipy_qmc():
    from treeinfer.inference.mapfit import (
        latin_hypercube as scipy_lhs,  # scipy.stats.qmc.LatinHypercube
    )

    lo, hi = np.array([0.0, -1.0, 2.0, 3.0]), np.array([1.0, 3.0, 2.5, 9.0])
    for seed in (0, 3):
        np.testing.assert_array_equal(
            latin_hypercube(37, lo, hi, seed), scipy_lhs(37, lo, hi, seed)
        )


def _gauss_log_density(mean, cov):
    return lambda x: stats.multivariate_normal(mean, cov).logpdf(x)


def test_adaptive_rounds_recover_the_target_and_raise_the_ess():
    """A proposal off-centre by one target std, too wide and uncorrelated: one round
    gives a low effective sample size; the moment-matched rounds raise it several-fold and the
    mixture-weighted draws keep the target's mean and covariance (closed form)."""
    target = _gauss_log_density(MEAN, COV)
    q_mean = MEAN + np.sqrt(np.diag(COV))
    q_cov = np.diag(np.diag(COV) * [6.0, 1.5, 1.5])  # no correlation, 2.4x too wide in x0
    one, _ = adaptive_importance(target, q_mean, q_cov, 800, 100, seed=0, max_rounds=1)
    three, idx = adaptive_importance(
        target, q_mean, q_cov, 800, 100, seed=0, max_rounds=3, target_ess=np.inf
    )
    assert one.rounds == 1 and three.rounds == 3 and len(three.draws) == 2400
    assert three.ess > 3 * one.ess and three.khat <= KHAT_LIMIT and three.ok
    m, c = weighted_moments(three.draws, three.log_weights)
    se = np.sqrt(np.diag(COV) / three.ess)
    assert np.all(np.abs(m - MEAN) < 5 * se), (m, MEAN, se)
    np.testing.assert_allclose(c, COV, atol=0.25)
    np.testing.assert_array_equal(three.theta, three.draws[idx])
    # stops early once the effective sample size reaches the target
    early, _ = adaptive_importance(target, MEAN, COV, 800, 100, seed=0, max_rounds=3)
    assert early.rounds == 1 and early.ess >= 200
    with pytest.raises(ConfigError, match="max_rounds"):
        adaptive_importance(target, MEAN, COV, 10, 5, max_rounds=0)


def test_weighted_width_equals_numpy_quantiles():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(999, 4)) * [1.0, 2.0, 0.5, 3.0]
    w = np.full(999, 1.0 / 999)
    q = np.quantile(x, [0.025, 0.975], axis=0, method="inverted_cdf")
    assert _weighted_width(x, w, 0.95) == pytest.approx(np.mean(q[1] - q[0]), rel=1e-12)
    # integer weights = repeated draws
    k = rng.integers(1, 4, size=999)
    q = np.quantile(np.repeat(x, k, axis=0), [0.025, 0.975], axis=0, method="inverted_cdf")
    assert _weighted_width(x, k / k.sum(), 0.95) == pytest.approx(np.mean(q[1] - q[0]))


def test_band_split_flags_a_band_carried_by_a_few_draws():
    rng = np.random.default_rng(2)
    pred = rng.normal(size=(2000, 50))
    even = np.full(2000, -np.log(2000.0))
    assert band_split(pred, even)[2] < 0.05
    # the weight of one half concentrated on 5 draws: their spread decides that half's band
    lw = even.copy()
    lw[0::2] = -np.inf
    lw[0:10:2] = 0.0
    lw -= np.logaddexp.reduce(lw)
    a, b, split = band_split(pred, lw)
    assert split > 0.2 and np.isfinite(a) and np.isfinite(b)
    no_weight = np.where(np.arange(2000) % 2 == 0, -np.inf, 0.0)
    assert np.isnan(band_split(pred, no_weight)[2])


def test_student_t_later_rounds_keep_the_target():
    """Gaussian first round, Student-t later rounds (heavier tails): the mixture weights still
    give the target's moments."""
    target = _gauss_log_density(MEAN, COV)
    q_mean = MEAN - 0.5 * np.sqrt(np.diag(COV))
    res, _ = adaptive_importance(
        target, q_mean, COV * 2.0, 1500, 100, seed=4, max_rounds=3, target_ess=np.inf,
        df_adapt=6.0,
    )  # fmt: skip
    assert res.rounds == 3 and res.df == 6.0 and res.ok
    m, c = weighted_moments(res.draws, res.log_weights)
    se = np.sqrt(np.diag(COV) / res.ess)
    assert np.all(np.abs(m - MEAN) < 5 * se)
    np.testing.assert_allclose(c, COV, atol=0.2)


def test_sorted_resample_takes_one_draw_per_stratum():
    from treeinfer.inference.importance import leading_projection, sorted_resample

    rng = np.random.default_rng(5)
    key = rng.normal(size=1000)
    lw = np.full(1000, -np.log(1000.0))
    idx = sorted_resample(0, lw, 100, key)
    ranks = np.argsort(np.argsort(key))[idx]  # rank of each chosen draw along the key
    assert sorted(ranks // 10) == list(range(100))  # one from each block of 10 ranks
    # unequal weights: each draw appears floor(n w) or ceil(n w) times, as systematic resampling
    w = rng.gamma(1.0, size=1000)
    w /= w.sum()
    counts = np.bincount(sorted_resample(1, np.log(w), 500, key), minlength=1000)
    assert np.all(counts >= np.floor(500 * w)) and np.all(counts <= np.ceil(500 * w))
    # the leading prediction component: predictions a_i * u + noise project onto a_i
    a = rng.normal(size=400)
    u = rng.normal(size=30)
    pred = a[:, None] * u + 0.01 * rng.normal(size=(400, 30))
    proj = leading_projection(pred, np.full(400, -np.log(400.0)))
    assert abs(np.corrcoef(proj, a)[0, 1]) > 0.999
