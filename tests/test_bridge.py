"""The tempered bridge (treeinfer.inference.bridge) against closed-form targets."""

import math

import numpy as np
import pytest
from scipy import stats

from treeinfer.errors import ConfigError
from treeinfer.inference.bridge import tempered_bridge
from treeinfer.inference.importance import systematic_resample


def _mixture(weights, means, sd):
    """log density of an equal-covariance Gaussian mixture (normalised), [M, D] -> [M]."""

    def log_p(x):
        x = np.atleast_2d(x)
        terms = [
            math.log(w) + stats.multivariate_normal(m, sd**2 * np.eye(len(m))).logpdf(x)
            for w, m in zip(weights, means)
        ]
        return np.logaddexp.reduce(np.stack(terms), axis=0)

    return log_p


def _one_lobe_draws(log_p, centre, sd, m, seed):
    """Importance draws from a narrow Gaussian at one lobe: ``(draws, log_weights)``."""
    rng = np.random.default_rng(seed)
    x = centre + sd * rng.standard_normal((m, len(centre)))
    lq = stats.multivariate_normal(centre, sd**2 * np.eye(len(centre))).logpdf(x)
    return x, log_p(x) - lq


def test_the_bridge_finds_the_lobe_the_importance_draws_missed():
    # two lobes of equal mass 2.5 sd apart; the importance draws come from a proposal at the
    # first lobe only, so their weights give the second almost no mass and resampling them
    # (what resample-move started from before) keeps the cloud at the first lobe
    log_p = _mixture([0.5, 0.5], [np.zeros(3), np.array([2.5, 0.0, 0.0])], 1.0)
    draws, lw = _one_lobe_draws(log_p, np.zeros(3), 0.6, 800, 0)
    plain = draws[systematic_resample(np.random.default_rng(1), lw, 512)]
    res = tempered_bridge(log_p, draws, lw, 512, seed=3)
    assert res.beta == 1.0 and np.all(res.log_weights == 0.0)
    share = np.mean(res.chains[:, 0] > 1.25)
    # the exact share beyond the midpoint is 0.5; 512 particles after a few stages of
    # resampling: well within 0.12 (the plain resample's share is about 0.1)
    assert abs(share - 0.5) < 0.12, share
    assert np.mean(plain[:, 0] > 1.25) < share - 0.2
    np.testing.assert_allclose(res.chains.mean(0), [1.25, 0.0, 0.0], atol=0.25)
    np.testing.assert_allclose(res.chains[:, 1:].std(0), 1.0, atol=0.15)


def test_log_evidence_is_the_targets_normalising_constant():
    # p = c * N(mu, S): the bridge's evidence estimate is log c (q is normalised)
    mu, c = np.array([0.4, -0.3]), 7.5
    gauss = stats.multivariate_normal(mu, np.diag([0.5, 2.0]))

    def log_p(x):
        return math.log(c) + gauss.logpdf(np.atleast_2d(x))

    draws, lw = _one_lobe_draws(log_p, mu + 0.5, 0.4, 600, 2)
    res = tempered_bridge(log_p, draws, lw, 1024, seed=5)
    assert res.stages >= 1
    assert abs(res.log_evidence - math.log(c)) < 0.15, res.log_evidence
    np.testing.assert_allclose(res.chains.mean(0), mu, atol=0.12)
    np.testing.assert_allclose(res.chains.std(0), np.sqrt([0.5, 2.0]), rtol=0.15)


def test_unstable_simulations_get_no_weight_and_stages_are_capped():
    log_p0 = _mixture([1.0], [np.zeros(2)], 0.3)

    def log_p(x):
        out = log_p0(x)
        return np.where(np.atleast_2d(x)[:, 0] > 0.5, np.nan, out)  # "unstable" half-plane

    draws, lw = _one_lobe_draws(log_p0, np.zeros(2), 0.6, 400, 4)
    res = tempered_bridge(log_p, draws, lw, 256, seed=0, max_stages=1, stage_ess=0.9)
    assert res.stages == 1
    assert np.all(np.isfinite(res.log_density))
    assert np.all(res.chains[:, 0] <= 0.5)
    if res.beta < 1.0:
        assert np.any(res.log_weights != 0.0)  # the rest of the way, as weights


def test_bad_arguments_are_config_errors():
    x = np.zeros((4, 2))
    with pytest.raises(ConfigError, match="no importance draw"):
        tempered_bridge(lambda y: np.zeros(len(y)), x, np.full(4, -np.inf), 8)
    with pytest.raises(ConfigError, match="n_chains"):
        tempered_bridge(lambda y: np.zeros(len(y)), x, np.zeros(4), 1)
    with pytest.raises(ConfigError, match="stage_ess"):
        tempered_bridge(lambda y: np.zeros(len(y)), x, np.zeros(4), 8, stage_ess=1.5)
