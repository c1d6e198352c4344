"""The fit verdict from posterior predictive checks (issue 27, item 2): synthetic residuals
drawn from the stated noise model give ``ok``; residuals from misspecified models give the
warning or ``poor_fit`` each check is for. The Ljung-Box statistic and the whitening are checked
against their distributions under the model (chi2, standard normal), not against themselves."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from scipy import stats

from treeinfer.data.trajectories import Observations
from treeinfer.evaluation.checks import fit_checks, fit_verdict_from_run
from treeinfer.evaluation.ppc import (
    explained_variance,
    ppc_stats,
    standardised_residuals,
)

SIGMA = 2e-3
B, T = 3, 300


def _ar1(rng, rho, shape):
    e = rng.standard_normal(shape)
    out = np.empty(shape)
    out[..., 0] = e[..., 0]
    for t in range(1, shape[-1]):
        out[..., t] = rho * out[..., t - 1] + np.sqrt(1 - rho**2) * e[..., t]
    return out


def _verdict(r, **kw):
    return fit_checks(residuals=r, noise_sigma=SIGMA, **kw)


def test_residuals_from_the_stated_model_are_ok():
    """100 data sets of white N(0, sigma) residuals: every one ok (no false alarm)."""
    rng = np.random.default_rng(0)
    bad = [
        v.reasons
        for v in (_verdict(SIGMA * rng.standard_normal((B, T))) for _ in range(100))
        if v.status != "ok"
    ]
    assert bad == []


def test_autocorrelated_residuals_warn_of_model_misfit_but_are_not_poor():
    """AR(1) residuals (rho 0.9) of the right marginal scale: the bands cover the data, so not
    poor_fit; the autocorrelation says the model misses something."""
    r = SIGMA * _ar1(np.random.default_rng(1), 0.9, (B, T))
    v = _verdict(r)
    assert v.status == "warning"
    assert any(s.startswith("model misfit: residuals autocorrelated") for s in v.reasons)
    assert v.measures["ppc"]["lag1"] == pytest.approx(0.9, abs=0.06)


def test_understated_noise_fails_coverage():
    """Residuals 3x the model's noise: ~51% outside the 95% band: poor_fit."""
    r = 3 * SIGMA * np.random.default_rng(2).standard_normal((B, T))
    v = _verdict(r)
    assert v.status == "poor_fit"
    assert "do not hold the data" in v.reasons[0]
    assert v.measures["fraction_outside"] == pytest.approx(2 * stats.norm.sf(1.96 / 3), abs=0.05)


def test_outliers_and_bias_warn():
    rng = np.random.default_rng(3)
    r = SIGMA * rng.standard_normal((B, T))
    r[:, ::40] += 20 * SIGMA  # a slipping gripper: 2.5% of the points far out
    v = _verdict(r)
    assert any("outliers" in s and "student_t" in s for s in v.reasons)
    r = SIGMA * (rng.standard_normal((B, T)) + 0.8)  # the model sits below the data
    v = _verdict(r)
    assert v.status == "warning"
    assert any("systematically above" in s for s in v.reasons)


def test_coverage_thresholds_respect_sampling_noise():
    """6% outside with 900 points is sampling noise; 12% is a warning; 30% poor."""
    z = [np.random.default_rng(4).standard_normal(T) for _ in range(B)]
    assert fit_checks(standardised=z, fraction_outside=0.06).status == "ok"
    assert fit_checks(standardised=z, fraction_outside=0.12).status == "warning"
    assert fit_checks(standardised=z, fraction_outside=0.30).status == "poor_fit"
    # too few outside (bands wider than needed) is never a failure
    assert fit_checks(standardised=z, fraction_outside=0.0).status == "ok"


def test_ljung_box_follows_its_chi2_reference_under_white_noise():
    """Q over 10 lags of 300 white samples ~ chi2(10): KS test against scipy's chi2, and the
    p-values are uniform."""
    rng = np.random.default_rng(5)
    qs = np.array([ppc_stats([rng.standard_normal(T)]).ljung_box for _ in range(400)])
    assert stats.kstest(qs, stats.chi2(10).cdf).pvalue > 0.01
    # under AR(1) rho = 0.4 the test rejects almost always (rho = 0.3: ~80% at n = 300)
    ps = [ppc_stats([_ar1(rng, 0.4, (T,))]).ljung_box_p for _ in range(50)]
    assert np.mean(np.array(ps) < 1e-3) > 0.9


def test_whitening_with_the_full_predictive_covariance():
    """Data drawn from MVN(mean of draws, cov of draws + sigma^2 I + extra): the standardised
    residuals are white standard normal (std 1, no lag-1 correlation), while dividing by sigma
    alone would show a strong autocorrelation (the draws' and the extra term's slow parts)."""
    rng = np.random.default_rng(6)
    t = np.linspace(0, 3, T)
    n_draws = 64
    amp = 1 + 0.3 * rng.standard_normal(n_draws)  # parameter uncertainty: a slow, shared shape
    draws = 0.05 * amp[:, None, None] * (1 - np.exp(-2 * t))[None, None, :] * np.ones((1, B, 1))
    lag = np.abs(t[:, None] - t[None, :])
    extra = (3 * SIGMA) ** 2 * np.exp(-lag / 0.3)  # a slow error (force noise, AR) the model has
    cov = np.cov(draws[:, 0], rowvar=False) + SIGMA**2 * np.eye(T) + extra
    chol = np.linalg.cholesky(cov + 1e-12 * np.eye(T))
    x = draws.mean(axis=0) + np.stack([chol @ rng.standard_normal(T) for _ in range(B)])
    z = standardised_residuals(x, draws, None, SIGMA**2, np.broadcast_to(extra, (B, T, T)))
    s = ppc_stats(z)
    assert s.z_std == pytest.approx(1.0, abs=0.08)
    assert abs(s.lag1) < 0.1 and s.ljung_box_p > 1e-3
    naive = ppc_stats([(x[b] - draws.mean(axis=0)[b]) / SIGMA for b in range(B)])
    assert naive.lag1 > 0.8


def test_noise_columns_are_never_judged_by_their_box():
    """sigma_x far beyond its box (the issue's clean case) with bands that cover: ok, not
    poor_fit; a gain beyond its box with covering bands: only a warning."""
    rng = np.random.default_rng(7)
    lo, hi = np.array([0.0, 0.0, -9.0]), np.array([5.0, 5.0, -7.0])
    theta = np.column_stack(
        [2 + 0.05 * rng.standard_normal(64), 3 + 0.05 * rng.standard_normal(64)]
        + [-5 + 0.05 * rng.standard_normal(64)]  # log sigma_x 2 above the box's top
    )
    z = [rng.standard_normal(T) for _ in range(B)]
    kw = dict(standardised=z, fraction_outside=0.05, lower=lo, upper=hi)
    v = fit_checks(theta=theta, labels=["Kp[a]", "Kd[a]", "sigma_x"], **kw)
    assert v.status == "ok", v.reasons
    theta[:, 0] = 5.5 + 0.05 * rng.standard_normal(64)
    v = fit_checks(theta=theta, labels=["Kp[a]", "Kd[a]", "sigma_x"], **kw)
    assert v.status == "warning" and "Kp[a]" in v.reasons[0]
    # without a coverage measurement the box is all there is: poor_fit as before
    v = fit_checks(theta=theta, labels=["Kp[a]", "Kd[a]", "sigma_x"], lower=lo, upper=hi)
    assert v.status == "poor_fit"


def _problem(x, likelihood):
    obs = Observations(
        force=np.ones_like(x),
        displacement=x,
        velocity=np.zeros_like(x),
        mask=np.ones(x.shape, bool),
        dt=0.01,
    )
    settings = {"likelihood": likelihood} if likelihood else {"kT": 0.05}
    labels = ("Kp[a]", "Kd[a]") + (("sigma_x",) if likelihood else ())
    d = len(labels)
    return SimpleNamespace(
        obs=obs, lower=np.full(d, -10.0), upper=np.full(d, 10.0), labels=labels,
        settings=settings, noise=None,
    )  # fmt: skip


def _prediction(truth, n_draws, sigma, rng):
    tau = truth[None] * (1 + 0.001 * rng.standard_normal((n_draws, 1, 1)))
    return SimpleNamespace(
        tau=tau, valid=np.ones(n_draws, bool), mean=tau.mean(axis=0),
        sigma=None if sigma is None else np.full(n_draws, sigma), force_variance=None,
    )  # fmt: skip


def test_fit_verdict_from_run_gaussian_and_boltzmann():
    """A run's own draws: white noise of the inferred sigma -> ok; the Boltzmann likelihood
    (no noise model) is judged by explained variance, and its coverage never gives poor_fit."""
    rng = np.random.default_rng(8)
    t = np.linspace(0, 3, T)
    truth = np.stack([0.05 * (1 - np.exp(-2 * t)) * (1 + 0.2 * b) for b in range(B)])
    x = truth + SIGMA * rng.standard_normal(truth.shape)
    theta = np.column_stack([rng.normal(2, 0.05, 32), rng.normal(0, 0.05, 32)])
    post = SimpleNamespace(theta=np.column_stack([theta, np.full(32, np.log(SIGMA))]))
    pred = _prediction(truth, 32, SIGMA, rng)
    fit = {"stable": np.ones(32, bool), "prediction": pred, "metrics": {"fraction_outside": 0.05}}
    v = fit_verdict_from_run(_problem(x, "gaussian"), post, fit)
    assert v.status == "ok", v.reasons
    assert v.measures["ppc"]["z_std"] == pytest.approx(1.0, abs=0.1)
    # Boltzmann, no noise level: the parameter band's coverage is not judged
    fit_b = {"stable": np.ones(32, bool), "prediction": _prediction(truth, 32, None, rng),
             "metrics": {"fraction_outside": 0.9}}  # fmt: skip
    v = fit_verdict_from_run(_problem(x, None), SimpleNamespace(theta=theta), fit_b)
    assert v.status == "ok", v.reasons
    assert v.measures["explained_variance"] > 0.95
    # a model that explains nothing (displacement in another unit): poor_fit
    v = fit_verdict_from_run(_problem(100 * x, None), SimpleNamespace(theta=theta), fit_b)
    assert v.status == "poor_fit" and "does not explain" in v.reasons[0]


def test_explained_variance_reference():
    rng = np.random.default_rng(9)
    x = rng.standard_normal((2, 50))
    r = 0.5 * rng.standard_normal((2, 50))
    ref = 1 - (r**2).sum() / sum(((row - row.mean()) ** 2).sum() for row in x)
    assert explained_variance(r, x) == pytest.approx(ref)
