"""Metrics against independent references (scipy.stats.gaussian_kde, brute force)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import optimize, stats

from treeinfer.errors import ConfigError, SimulationError
from treeinfer.evaluation import metrics


def _scipy_interval(x, level=0.95):
    """Reference quantiles: scipy KDE CDF (integrate_box_1d) + brentq."""
    kde = stats.gaussian_kde(x)
    a = 0.5 * (1 - level)
    lo_b, hi_b = x.min() - 20 * x.std(), x.max() + 20 * x.std()
    cdf = lambda y: kde.integrate_box_1d(-np.inf, y)
    lo = optimize.brentq(lambda y: cdf(y) - a, lo_b, hi_b, xtol=1e-12)
    hi = optimize.brentq(lambda y: cdf(y) - (1 - a), lo_b, hi_b, xtol=1e-12)
    return lo, hi


@pytest.fixture
def rng():
    return np.random.default_rng(0)


def test_bandwidth_matches_scipy(rng):
    x = rng.gamma(2.0, 0.05, size=(40, 3, 7))
    kde = metrics.kde_1d(x)
    for b in range(3):
        for t in range(7):
            ref = np.sqrt(stats.gaussian_kde(x[:, b, t]).covariance[0, 0])
            np.testing.assert_allclose(kde.bandwidth[b, t], ref, rtol=1e-5)


def test_interval_matches_scipy_kde_quantiles(rng):
    # bimodal + skewed columns so the KDE quantile differs from a Gaussian one
    P, B, T = 50, 2, 5
    x = np.concatenate(
        [rng.normal(0.0, 0.1, (P // 2, B, T)), rng.gamma(2.0, 0.3, (P - P // 2, B, T)) + 1.0]
    )
    lower, upper, mean = metrics.predictive_interval(x, 0.95)
    assert lower.shape == upper.shape == mean.shape == (B, T)
    for b in range(B):
        for t in range(T):
            lo, hi = _scipy_interval(x[:, b, t])
            np.testing.assert_allclose([lower[b, t], upper[b, t]], [lo, hi], rtol=2e-5, atol=2e-6)
    np.testing.assert_allclose(mean, x.mean(0), rtol=1e-5)


def test_interval_level_and_2d_input(rng):
    x = rng.normal(size=(30, 4))
    lo80, hi80, _ = metrics.predictive_interval(x, 0.8)
    lo95, hi95, _ = metrics.predictive_interval(x, 0.95)
    for t in range(4):
        ref = _scipy_interval(x[:, t], 0.8)
        np.testing.assert_allclose([lo80[t], hi80[t]], ref, rtol=2e-5, atol=2e-6)
    assert np.all(lo95 < lo80) and np.all(hi95 > hi80)


def test_degenerate_step_is_zero_width_not_nan(rng):
    x = rng.normal(0.0, 0.1, size=(20, 6))
    x[:, 0] = 0.0  # t = 0: displacement exactly zero
    x[:, 1] = 0.3  # constant non-zero (float32 rounding in the mean)
    lower, upper, _mean = metrics.predictive_interval(x)
    assert np.all(np.isfinite(lower)) and np.all(np.isfinite(upper))
    assert lower[0] == upper[0] == 0.0
    np.testing.assert_allclose([lower[1], upper[1]], [0.3, 0.3], rtol=1e-6)
    gt = np.concatenate([[0.0, 0.3], x.mean(0)[2:]])
    assert float(metrics.fraction_outside(lower, upper, gt)) == 0.0
    nll = metrics.predictive_nll(x, gt)
    assert int(nll.n_degenerate) == 2 and int(nll.n_points) == 4
    assert np.isfinite(float(nll.total))


def test_jit_and_vmap_friendly(rng):
    # more series than bands._HOST_MAX_SERIES: the eager call runs the jitted program too (a few
    # series go to the host twin, tests/test_bands_host.py)
    x = jnp.asarray(rng.normal(size=(16, 5, 20)))
    valid = jnp.asarray(rng.random(16) > 0.2)
    f = jax.jit(metrics.predictive_interval, static_argnames=("level", "n_iter"))
    a = f(x, level=0.9, valid=valid)
    b = metrics.predictive_interval(x, 0.9, valid)
    for u, v in zip(a, b):
        np.testing.assert_allclose(u, v, rtol=1e-6)
    gt = jnp.asarray(rng.normal(size=(5, 20)))
    nll_jit = jax.jit(metrics.predictive_nll)(x, gt, None, valid)
    np.testing.assert_allclose(
        nll_jit.total, metrics.predictive_nll(x, gt, valid=valid).total, rtol=1e-6
    )
    # vmap over a leading "condition" axis (e.g. noise levels): same as a loop
    xs = jnp.stack([x, 2.0 * x])
    lo_v, hi_v, _ = jax.vmap(lambda p: metrics.predictive_interval(p, 0.9, valid))(xs)
    np.testing.assert_allclose(
        lo_v[1], metrics.predictive_interval(2.0 * x, 0.9, valid).lower, rtol=1e-5
    )
    np.testing.assert_allclose(hi_v[0], b.upper, rtol=1e-5)


def test_invalid_particles_are_excluded(rng):
    x = rng.normal(size=(25, 2, 4))
    valid = np.ones(25, bool)
    valid[[3, 7]] = False
    y = x.copy()
    y[3] = 1e6  # unstable but flagged
    y[7] = np.nan
    y[11, 0, 2] = np.inf  # unflagged non-finite: excluded automatically
    valid_all = valid.copy()
    valid_all[11] = False
    ref = metrics.predictive_interval(x[valid_all], 0.95)
    got = metrics.predictive_interval(y, 0.95, valid)
    for u, v in zip(got, ref):
        np.testing.assert_allclose(u, v, rtol=1e-5, atol=1e-6)
    gt = rng.normal(size=(2, 4))
    np.testing.assert_allclose(
        metrics.predictive_nll(y, gt, valid=valid).total,
        metrics.predictive_nll(x[valid_all], gt).total,
        rtol=1e-5,
    )
    s = metrics.summarize(y, gt, valid=valid)
    assert s["n_invalid_particles"] == 3 and s["n_valid_particles"] == 22


def test_too_few_particles_raise():
    x = np.zeros((3, 4))
    with pytest.raises(SimulationError, match="only 1 of 3"):
        metrics.predictive_interval(x, valid=np.array([True, False, False]))
    with pytest.raises(ConfigError):
        metrics.predictive_interval(x, level=1.5)
    # under jit the check cannot raise: NaN instead of a plausible-looking number
    f = jax.jit(metrics.predictive_interval)
    for v in ([True, False, False], [False, False, False]):
        assert np.all(np.isnan(np.asarray(f(x + 1.0, valid=jnp.asarray(v)))))


def test_ci_width_and_fraction_outside_by_hand():
    lower = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
    upper = np.array([[1.0, 2.0, 1.0], [4.0, 1.0, 1.0]])
    gt = np.array([[0.5, 3.0, 1.0], [np.nan, -0.5, 0.5]])
    mask = np.array([[True, True, True], [True, True, False]])
    np.testing.assert_allclose(metrics.ci_width(lower, upper, mask), (1 + 2 + 0 + 4 + 1) / 5)
    np.testing.assert_allclose(metrics.ci_width(lower, upper), 9 / 6)
    # usable GT points: (0,0) in, (0,1) out, (0,2) in (degenerate, equal), (1,1) out; NaN and masked
    # skipped
    np.testing.assert_allclose(metrics.fraction_outside(lower, upper, gt, mask), 2 / 4)
    # a hair beyond a degenerate bound is tolerated, a real miss is not
    assert (
        float(metrics.fraction_outside(np.array([1.0]), np.array([1.0]), np.array([1.0 + 1e-7])))
        == 0.0
    )
    assert (
        float(metrics.fraction_outside(np.array([1.0]), np.array([1.0]), np.array([1.01]))) == 1.0
    )


def test_predictive_nll_matches_scipy_logpdf(rng):
    P, B, T = 30, 2, 6
    x = rng.normal(size=(P, B, T)) * np.linspace(0.1, 1.0, T)
    gt = rng.normal(size=(B, T))
    gt[1, 0] = 40.0  # far tail: a naive exp() would underflow to log(0)
    mask = np.ones((B, T), bool)
    mask[0, -1] = False
    ref = 0.0
    for b in range(B):
        for t in range(T):
            if mask[b, t]:
                ref -= stats.gaussian_kde(x[:, b, t]).logpdf(gt[b, t])[0]
    nll = metrics.predictive_nll(x, gt, mask)
    assert np.isfinite(float(nll.total))
    np.testing.assert_allclose(nll.total, ref, rtol=1e-4)
    np.testing.assert_allclose(nll.mean, ref / (B * T - 1), rtol=1e-4)
    assert int(nll.n_points) == B * T - 1


def test_posterior_nll():
    ll = np.array([[-1.0, -2.0], [-3.0, -4.0], [-np.inf, 0.0], [-5.0, -5.0]])
    # particle 2 unstable (-inf) excluded automatically, particle 3 flagged invalid
    valid = np.array([True, True, True, False])
    np.testing.assert_allclose(metrics.posterior_nll(ll, valid), (3 + 7) / 2)
    np.testing.assert_allclose(metrics.posterior_nll(np.array([-1.0, -3.0])), 2.0)


def _scipy_joint(xs, t, level):
    kde = stats.gaussian_kde(xs.T)
    return kde.logpdf(t[:, None])[0] >= np.quantile(kde.logpdf(xs.T), 1 - level)


def test_posterior_vs_truth(rng):
    cov = np.array([[1.0, 0.9], [0.9, 1.0]])
    xs = rng.multivariate_normal([0.0, 0.0], cov, size=400)
    # (1.5, 1.5) lies along the correlation: inside. (1.5, -1.5) is inside both
    # marginal intervals but far outside the joint region.
    inside = metrics.posterior_vs_truth(xs, np.array([1.5, 1.5]))
    outside = metrics.posterior_vs_truth(xs, np.array([1.5, -1.5]))
    assert inside.in_joint is True and outside.in_joint is False
    assert np.all(outside.in_marginal)
    for chk, t in [(inside, [1.5, 1.5]), (outside, [1.5, -1.5])]:
        assert chk.in_joint == _scipy_joint(xs, np.array(t), 0.95)
        np.testing.assert_allclose(chk.mean, xs.mean(0), atol=1e-5)
        np.testing.assert_allclose(chk.abs_error, np.abs(xs.mean(0) - t), atol=1e-5)
        np.testing.assert_allclose(chk.rel_error, np.abs(xs.mean(0) - t) / 1.5, atol=1e-5)
    far = metrics.posterior_vs_truth(xs, np.array([5.0, 0.0]))
    assert not far.in_marginal[0] and far.in_marginal[1] and far.in_joint is False


def test_posterior_vs_truth_log_space_and_degenerate(rng):
    theta = np.exp(rng.normal([np.log(50.0), np.log(2.0)], 0.1, size=(200, 2)))
    chk = metrics.posterior_vs_truth(theta, np.array([50.0, 2.0]), log=True)
    np.testing.assert_allclose(chk.mean, np.log(theta).mean(0), atol=1e-5)
    assert np.all(chk.in_marginal) and chk.in_joint is True
    collapsed = np.tile([1.0, 2.0], (10, 1))
    chk = metrics.posterior_vs_truth(collapsed, np.array([1.0, 2.0]))
    assert chk.in_joint is None and np.all(chk.in_marginal)
    with pytest.raises(ConfigError):
        metrics.posterior_vs_truth(theta, np.array([-1.0, 2.0]), log=True)


def test_summarize_is_json_ready(rng):
    import json

    pred = rng.normal(size=(20, 2, 5))
    pred[:, :, 0] = 0.0
    gt = rng.normal(size=(2, 5))
    gt[:, 0] = 0.0
    parts = rng.normal(size=(20, 2))
    s = metrics.summarize(
        pred,
        gt,
        log_likelihood=rng.normal(size=20),
        particles=parts,
        truth=np.zeros(2),
        labels=["Kp[b1]", "Kd[b1]"],
    )
    json.dumps(s)
    lower, upper, _ = metrics.predictive_interval(pred)
    np.testing.assert_allclose(
        s["pct_outside"], 100 * float(metrics.fraction_outside(lower, upper, gt))
    )
    assert s["n_points"] == 8 and s["n_degenerate_points"] == 2
    assert set(s["parameters"]) == {"Kp[b1]", "Kd[b1]"}


# --------------------------------------------------------------------------- posterior predictive
# (simulations + noise model; issue 11)


def _mixture_interval(x, s, level, kind="gaussian", df=4.0):
    """Reference: scipy mixture CDF + brentq; kernel scale sqrt(s^2 + h^2), h from gaussian_kde."""
    comp = stats.norm if kind == "gaussian" else stats.t(df)
    s = np.sqrt(s**2 + stats.gaussian_kde(x).covariance[0, 0])
    cdf = lambda y: np.mean(comp.cdf((y - x) / s))
    a = 0.5 * (1 - level)
    lo_b, hi_b = x.min() - 50 * s.max(), x.max() + 50 * s.max()
    return (
        optimize.brentq(lambda y: cdf(y) - a, lo_b, hi_b, xtol=1e-12),
        optimize.brentq(lambda y: cdf(y) - (1 - a), lo_b, hi_b, xtol=1e-12),
    )


@pytest.mark.parametrize("kind", ["gaussian", "student_t"])
def test_noisy_interval_matches_scipy_mixture(rng, kind):
    x = rng.normal(0.05, 0.004, size=(30, 3))
    s = rng.uniform(0.001, 0.003, size=30)
    lo, hi, mean = (
        np.asarray(a, float)
        for a in metrics.noisy_predictive_interval(
            jnp.asarray(x, jnp.float64) if jax.config.jax_enable_x64 else x, s, 0.9, kind=kind
        )
    )
    for j in range(3):
        rl, rh = _mixture_interval(x[:, j], s, 0.9, kind)
        assert lo[j] == pytest.approx(rl, abs=2e-6) and hi[j] == pytest.approx(rh, abs=2e-6)
    np.testing.assert_allclose(mean, x.mean(0), rtol=1e-5)


def test_predictive_band_at_t0_is_the_noise(rng):
    """All particles predict 0 at t = 0: the parameter band is zero-width there, the predictive
    band is the noise's own 95% interval (+-1.96 sigma), never zero-width."""
    pred = np.concatenate([np.zeros((20, 1)), rng.normal(0.1, 0.01, (20, 4))], axis=1)
    bands = metrics.predictive_bands(pred, 0.002, 0.95)
    assert float(bands.parameter.upper[0] - bands.parameter.lower[0]) == 0.0
    np.testing.assert_allclose(
        [bands.predictive.lower[0], bands.predictive.upper[0]],
        [-stats.norm.ppf(0.975) * 0.002, stats.norm.ppf(0.975) * 0.002],
        rtol=1e-4,
    )
    assert np.all(
        np.asarray(bands.predictive.upper - bands.predictive.lower)
        > np.asarray(bands.parameter.upper - bands.parameter.lower)
    )


def test_noisy_nll_zero_spread_matches_scipy(rng):
    """Identical particles (zero spread): finite, equals the noise model's own NLL."""
    tau = np.tile(rng.normal(0, 0.05, (2, 6)), (8, 1, 1))
    y = tau[0] + 0.002 * rng.standard_normal((2, 6))
    nll = metrics.noisy_predictive_nll(tau, y, 0.002)
    ref = -stats.norm.logpdf(y, tau[0], 0.002)
    assert np.isfinite(float(nll.total))
    assert float(nll.total) == pytest.approx(ref.sum(), rel=1e-5)
    assert float(nll.mean) == pytest.approx(ref.mean(), rel=1e-5) and int(nll.n_points) == 12
    # the KDE NLL is undefined there (degenerate steps): the old metric skips every point
    assert int(metrics.predictive_nll(tau, y).n_points) == 0


def test_noisy_nll_mixture_matches_logsumexp(rng):
    from scipy.special import logsumexp

    x = rng.normal(0, 0.01, (16, 5))
    s = rng.uniform(0.001, 0.004, 16)
    y = rng.normal(0, 0.01, 5)
    valid = np.ones(16, bool)
    valid[3] = False
    got = metrics.noisy_predictive_nll(x, y, s, valid=valid, kind="student_t", df=5.0)
    h2 = np.array([stats.gaussian_kde(x[valid, j]).covariance[0, 0] for j in range(5)])
    lp = stats.t.logpdf(y[None], 5.0, loc=x, scale=np.sqrt(s[:, None] ** 2 + h2))[valid]
    ref = -(logsumexp(lp, axis=0) - np.log(valid.sum()))
    assert float(got.total) == pytest.approx(ref.sum(), rel=1e-5)


def test_predictive_draws(rng):
    x = rng.normal(0, 0.01, (4, 3))
    d = metrics.posterior_predictive_draws(jax.random.key(0), x, np.full(4, 0.002), n_draws=4000)
    assert d.shape == (4000, 4, 3)
    np.testing.assert_allclose(np.asarray(d).mean(0), x, atol=3e-4)
    np.testing.assert_allclose(np.asarray(d).std(0), 0.002, rtol=0.06)


def test_noisy_band_bad_sigma():
    with pytest.raises(ConfigError, match="sigma"):
        metrics.noisy_predictive_interval(np.zeros((3, 4)), -1.0)
    with pytest.raises(ConfigError, match="sigma"):
        metrics.noisy_predictive_interval(np.zeros((3, 4)), np.ones(2))


@pytest.mark.parametrize("sigma", [-0.01, float("nan"), [0.01, 0.0, 0.02]])
def test_noisy_band_refuses_a_noise_scale_that_is_not_finite_and_positive(sigma):
    from treeinfer.evaluation.bands import noisy_predictive_interval

    pred = np.random.default_rng(0).normal(size=(3, 5))
    with pytest.raises(ConfigError, match="finite and positive"):
        noisy_predictive_interval(pred, sigma)
    with pytest.raises(ConfigError, match="finite and >= 0"):
        noisy_predictive_interval(pred, 0.01, extra_variance=np.array([0, 1, -1e-9, 0, 0.0]))
    lo, hi, _ = noisy_predictive_interval(pred, 0.01, extra_variance=np.zeros(5))  # accepted
    assert np.all(np.asarray(hi) > np.asarray(lo))
