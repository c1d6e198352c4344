"""The softening root plate (treeinfer.inference.pulltest.softening): the chain's tilts against
the closed form of the law ``q = (M / K) (1 + |M| / (K theta_s))`` (small angles, one hinge
turning under the ground moment), the same element through the chain with creep and lag as
their sum, and NUTS on a synthetic softening pull: the softening found, the linear chain's
band missing the held-out top of the ramp and the softening chain's band covering it."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
import pytest

from treeinfer.data import PullSetup
from treeinfer.inference.pulltest import (
    SOFT_TILT_PRIOR,
    chain_tilts,
    creep_tilts,
    fit_pull_test,
    lagged_creep_tilts,
    model_tilts,
    predictive_band,
    pull_model,
    softening_angle,
)

SETUP = PullSetup(
    name="synthetic",
    height=6.0,
    circumference_cm=(50.0,),
    sling_height=1.9,
    anchor_sling_height=0.35,
    anchor_distance=10.5,
    root_clino_height=1.0,
    trunk_clino_height=2.3,
)
KP = np.array([4.0e5, 2.5e5])


@pytest.fixture(scope="module")
def model():
    return pull_model(SETUP)


def test_softening_root_against_the_closed_form(model):
    """Stiff springs (P-Delta below 0.1%): the root clino reads the root hinge's rotation under
    the ground moment ``M = F h cos a``, ``(M / K)(1 + M / (K theta_s))``; the trunk clino adds
    the stem spring's linear ``F (h - h_root) cos a / K_stem``."""
    f = np.array([100.0, 1000.0, 3000.0])
    k_root, k_stem, theta_s = 2.0e7, 1.0e8, 2.0e-4  # rad: softening of 50-140% at these loads
    got, ok = chain_tilts(
        model, jnp.asarray([[k_root, k_stem]]), jnp.asarray(f), None, soft=jnp.asarray([theta_s])
    )
    assert bool(ok[0])
    ca = math.cos(model.cable_angle)
    m = f * SETUP.sling_height * ca
    root = m / k_root * (1 + m / (k_root * theta_s))
    assert root[-1] / (m[-1] / k_root) > 2.0  # far from linear: the test can fail
    np.testing.assert_allclose(np.asarray(got[0, 0]), root, rtol=3e-3)
    trunk = root + f * (SETUP.sling_height - SETUP.root_clino_height) * ca / k_stem
    np.testing.assert_allclose(np.asarray(got[0, 1]), trunk, rtol=3e-3)
    # symmetric in the sign of the load, and linear in the limit of a stiff plate
    assert float(softening_angle(jnp.asarray([-1e-3]), jnp.asarray(1e-3))[0]) == pytest.approx(
        -1e-3
    )
    lin = model_tilts(model, jnp.asarray([[k_root, k_stem]]), jnp.asarray(f))[0]
    far = chain_tilts(model, jnp.asarray([[k_root, k_stem]]), jnp.asarray(f), None,
                      soft=jnp.asarray([1e3]))[0]  # fmt: skip
    np.testing.assert_allclose(np.asarray(far), np.asarray(lin), rtol=1e-5)


def test_chain_tilts_adds_the_elements_to_creep_and_lag(model):
    """Every element enters through the same Jacobian: softening + creep + lag = the lagged
    creep chain plus the softening alone's extra tilt (and without elements, the elastic)."""
    t = np.arange(0.0, 60.0, 0.1)
    force = jnp.asarray(np.interp(t, [0, 20, 40, 45, 60], [0, 2500.0, 2500.0, 0.0, 0.0]))
    kp = jnp.asarray(KP[None])
    ratio, taus = jnp.asarray([[0.3, 0.2]]), jnp.asarray([[20.0, 30.0]])
    cf, tf = jnp.asarray([0.5]), jnp.asarray([0.4])
    ts = jnp.asarray([math.radians(1.0)])
    got = chain_tilts(model, kp, force, t, creep=(ratio, taus), lag=(cf, tf, "root"), soft=ts)[0]
    lagged = lagged_creep_tilts(model, kp, ratio, taus, cf, tf, force, t)[0]
    soft_only = chain_tilts(model, kp, force, t, soft=ts)[0]
    elastic = model_tilts(model, kp, force)[0]
    np.testing.assert_allclose(
        np.asarray(got), np.asarray(lagged + soft_only - elastic), rtol=1e-5, atol=1e-12
    )
    np.testing.assert_allclose(
        np.asarray(chain_tilts(model, kp, force, t, creep=(ratio, taus))[0]),
        np.asarray(creep_tilts(model, kp, ratio, taus, force, t)[0]),
        rtol=1e-6,
    )
    assert float(jnp.max(soft_only - elastic)) > 1e-4  # the softening is not nothing


@pytest.mark.slow  # about a minute of NUTS on the loaded 2-core box
def test_nuts_finds_the_softening_and_its_band_covers_the_held_out_ramp(model):
    """A ramp to 6 kN on a plate whose compliance doubles at 1 deg, fitted on its first half:
    the linear chain's band misses the held-out top, the softening chain's covers it and its
    theta_s interval holds the truth."""
    rng = np.random.default_rng(7)
    force = np.linspace(20.0, 6000.0, 160)
    truth = math.radians(1.0)
    kp = jnp.asarray(KP[None])
    clean = np.asarray(chain_tilts(model, kp, jnp.asarray(force), None,
                                   soft=jnp.asarray([truth]))[0][0])  # fmt: skip
    sigma = np.deg2rad([0.005, 0.01])
    y = clean + sigma[:, None] * rng.standard_normal(clean.shape)
    fit, held = slice(0, 80), slice(80, None)
    kw = dict(num_warmup=100, num_samples=150, num_chains=1, seed=1)
    soft = fit_pull_test(model, force[fit], y[:, fit], soft=True, **kw)
    lin = fit_pull_test(model, force[fit], y[:, fit], **kw)
    s = soft.summary()["soft_tilt_root"]
    assert SOFT_TILT_PRIOR[0] <= s["q2.5"] < truth < s["q97.5"] <= SOFT_TILT_PRIOR[1], s

    def coverage(post):
        band = predictive_band(model, post, force, n_draws=100)
        return ((y >= band["lo"]) & (y <= band["hi"]))[:, held].mean()

    assert coverage(soft) > 0.85
    assert coverage(lin) < 0.5


def test_gain_error_likelihood_equals_the_multivariate_normal():
    """The ``ar1+gain`` residuals' Kalman likelihood against scipy with the covariance
    ``diag(theta) K_g diag(theta) + K_a + sigma_w^2 I`` (irregular steps, a gap, missing
    samples); a wrong gain correlation time gives another density."""
    from scipy.stats import multivariate_normal

    from treeinfer.inference.pulltest import gain_ou_log_prob

    rng = np.random.default_rng(4)
    n = 70
    steps = rng.uniform(0.08, 0.3, n - 1)
    steps[30] = 4.0
    t = np.concatenate([[0.0], np.cumsum(steps)])
    theta = np.stack([np.linspace(0.001, 0.02, n), np.linspace(0.0, 0.05, n) ** 1.2])
    sw, sa, ta = np.array([2e-4, 5e-4]), np.array([3e-4, 1e-4]), np.array([1.0, 0.4])
    sg, tg = np.array([0.05, 0.2]), np.array([8.0, 20.0])

    def cov(i, sel, tau_g=None):
        tt, th = t[sel], theta[i, sel]
        lag = np.abs(tt[:, None] - tt[None, :])
        kg = sg[i] ** 2 * np.exp(-lag / (tau_g if tau_g is not None else tg[i]))
        ka = sa[i] ** 2 * np.exp(-lag / ta[i])
        return th[:, None] * kg * th[None, :] + ka + sw[i] ** 2 * np.eye(tt.size)

    every = np.ones(n, bool)
    resid = np.stack([multivariate_normal(np.zeros(n), cov(i, every)).rvs(random_state=rng)
                      for i in range(2)])  # fmt: skip
    mask = np.ones((2, n), bool)
    mask[0, [5, 6, 40]] = False
    mask[1, 60:] = False
    got = float(gain_ou_log_prob(resid, theta, mask, t, sw, sa, ta, sg, tg))
    want = sum(
        multivariate_normal(np.zeros(mask[i].sum()), cov(i, mask[i])).logpdf(resid[i, mask[i]])
        for i in range(2)
    )
    assert got == pytest.approx(want, abs=2e-3 * abs(want))
    other = float(gain_ou_log_prob(resid, theta, mask, t, sw, sa, ta, sg * 0.2, tg))
    assert abs(other - want) > 1.0


def test_band_with_a_gain_error_widens_with_the_tilt(model):
    """A posterior of one point (no parameter spread): the band's half-width is 1.96 times
    ``sqrt(sigma^2 + (sigma_g theta)^2)`` at each force, so it grows with the tilt."""
    from treeinfer.inference.pulltest import PullPosterior

    s = 4000
    sg = np.array([0.1, 0.05])
    sigma = np.deg2rad([0.002, 0.004])
    post = PullPosterior(
        joints=("root", "stem"),
        channels=("root", "trunk"),
        kp=np.tile(KP, (s, 1)),
        sigma=np.tile(sigma, (s, 1)),
        noise="ar1+gain",
        noise_params={"sigma_g": np.tile(sg, (s, 1)), "tau_g": np.full((s, 2), 10.0)},
    )
    force = np.linspace(0.0, 4000.0, 5)
    band = predictive_band(model, post, force, n_draws=s, seed=3)
    theta = np.asarray(model_tilts(model, jnp.asarray(KP[None]), jnp.asarray(force))[0][0])
    want = 1.96 * np.sqrt(sigma[:, None] ** 2 + (sg[:, None] * theta) ** 2)
    np.testing.assert_allclose((band["hi"] - band["lo"]) / 2, want, rtol=0.05)
    assert want[0, -1] > 3 * want[0, 0]  # the gain term dominates at the top: can fail


def test_gain_error_innovations_whiten_the_residuals():
    """The ``ar1+gain`` check's innovations: (1) exactly the Cholesky whitening ``L^-1 r`` of
    the residuals under the model's covariance (numpy, observed samples in time order); (2)
    on a long simulated record they are white and N(0, 1) under the true parameters, and
    correlated (the check fires) when the gain error is left out (sigma_g 100x too small);
    (3) ``residual_check`` reports them for an ``ar1+gain`` posterior."""
    from treeinfer.inference.pulltest import (
        LAG1_LIMIT,
        PullPosterior,
        gain_ou_innovations,
        lag1_autocorrelation,
        residual_check,
    )

    rng = np.random.default_rng(8)
    # (1) against the covariance, with missing samples and a gap
    n = 60
    steps = rng.uniform(0.08, 0.3, n - 1)
    steps[20] = 3.0
    t = np.concatenate([[0.0], np.cumsum(steps)])
    theta = np.linspace(0.002, 0.03, n)[None]
    sw, sa, ta = np.array([3e-4]), np.array([2e-4]), np.array([0.8])
    sg, tg = np.array([0.1]), np.array([10.0])
    lag = np.abs(t[:, None] - t[None, :])
    cov = (
        theta[0][:, None] * sg[0] ** 2 * np.exp(-lag / tg[0]) * theta[0][None, :]
        + sa[0] ** 2 * np.exp(-lag / ta[0])
        + sw[0] ** 2 * np.eye(n)
    )
    resid = (np.linalg.cholesky(cov) @ rng.standard_normal(n))[None]
    mask = np.ones((1, n), bool)
    mask[0, [7, 8, 33]] = False
    z = gain_ou_innovations(resid, theta, mask, t, sw, sa, ta, sg, tg)
    ok = mask[0]
    want = np.linalg.solve(np.linalg.cholesky(cov[np.ix_(ok, ok)]), resid[0, ok])
    np.testing.assert_allclose(z[0, ok], want, atol=2e-5)  # float32 filter
    assert np.isnan(z[0, ~ok]).all()
    # (2) a long record: the gain error dominates where the tilt is large
    n = 4000
    t = np.cumsum(rng.uniform(0.08, 0.14, n))
    theta = (0.02 * (1 + np.sin(t / 40.0)))[None]
    g, a = np.zeros(n), np.zeros(n)
    g[0], a[0] = sg[0] * rng.standard_normal(), sa[0] * rng.standard_normal()
    for i in range(1, n):
        rg, ra = np.exp(-(t[i] - t[i - 1]) / np.array([tg[0], ta[0]]))
        g[i] = rg * g[i - 1] + sg[0] * math.sqrt(1 - rg**2) * rng.standard_normal()
        a[i] = ra * a[i - 1] + sa[0] * math.sqrt(1 - ra**2) * rng.standard_normal()
    resid = (theta[0] * g + a + sw[0] * rng.standard_normal(n))[None]
    mask = np.ones((1, n), bool)
    z = gain_ou_innovations(resid, theta, mask, t, sw, sa, ta, sg, tg)
    assert abs(lag1_autocorrelation(z)[0]) < 0.06
    assert np.nanstd(z) == pytest.approx(1.0, abs=0.05)
    z_bad = gain_ou_innovations(resid, theta, mask, t, sw, sa, ta, sg / 100, tg)
    assert lag1_autocorrelation(z_bad)[0] > LAG1_LIMIT
    # (3) through residual_check, at a posterior of one point
    s = 5
    post = PullPosterior(
        joints=("root",),
        channels=("root",),
        kp=np.ones((s, 1)),
        sigma=np.ones((s, 1)),
        noise="ar1+gain",
        noise_params={
            k: np.tile(v, (s, 1))
            for k, v in dict(sigma_w=sw, sigma_a=sa, tau_ar=ta, sigma_g=sg, tau_g=tg).items()
        },
    )
    tilt = theta + resid
    check = residual_check(theta, tilt, post, time=t)
    np.testing.assert_allclose(check["lag1_innovations"], lag1_autocorrelation(z), atol=1e-4)
    assert check["ar1_enough"].all()
    assert check["needs_ar1"].all()  # the raw residuals are correlated (by design)


def test_gain_forecast_is_the_gaussian_conditional_of_the_gain():
    """The gain error's forecast from the fitted residuals against Gaussian conditioning on
    the full covariance (numpy): ``E[g(t) | r] = k' S^-1 r``, ``Var = sigma_g^2 - k' S^-1 k``
    with ``k_i = theta_i sigma_g^2 exp(-|t - t_i| / tau_g)``; right after the fitted part the
    forecast is much narrower than the stationary marginal, long after it is that marginal."""
    from treeinfer.inference.pulltest import gain_forecast

    rng = np.random.default_rng(11)
    n = 80
    t = np.concatenate([[0.0], np.cumsum(rng.uniform(0.08, 0.3, n - 1))])
    theta = np.stack([np.linspace(0.002, 0.03, n), np.linspace(0.01, 0.05, n)])
    sw, sa, ta = np.array([2e-4, 4e-4]), np.array([1e-4, 3e-4]), np.array([0.6, 1.5])
    sg, tg = np.array([0.1, 0.3]), np.array([12.0, 6.0])
    later = t[-1] + np.array([0.0, 0.5, 3.0, 10.0, 300.0])
    resid = np.empty((2, n))
    want_m, want_v = np.empty((2, later.size)), np.empty((2, later.size))
    for i in range(2):
        lag = np.abs(t[:, None] - t[None, :])
        kg = sg[i] ** 2 * np.exp(-lag / tg[i])
        cov = theta[i][:, None] * kg * theta[i][None, :] + sa[i] ** 2 * np.exp(-lag / ta[i])
        cov += sw[i] ** 2 * np.eye(n)
        resid[i] = np.linalg.cholesky(cov) @ rng.standard_normal(n)
        k = theta[i][:, None] * sg[i] ** 2 * np.exp(-np.abs(t[:, None] - later) / tg[i])
        want_m[i] = k.T @ np.linalg.solve(cov, resid[i])
        want_v[i] = sg[i] ** 2 - np.einsum("if,if->f", k, np.linalg.solve(cov, k))
    mask = np.ones((2, n), bool)
    m, v = gain_forecast(resid, theta, mask, t, sw, sa, ta, sg, tg, later)
    np.testing.assert_allclose(np.asarray(m), want_m, atol=2e-3 * sg.max())
    np.testing.assert_allclose(np.asarray(v), want_v, rtol=2e-3, atol=1e-6 * sg.max() ** 2)
    assert np.all(np.asarray(v)[:, 0] < 0.5 * sg**2)  # the fitted part constrains the gain
    np.testing.assert_allclose(np.asarray(v)[:, -1], sg**2, rtol=1e-3)


def test_band_with_the_gain_forecast_follows_the_fitted_part(model):
    """A posterior of one point; the fitted part's tilts read 20% above the model (a gain
    error of +0.2, sigma_g 0.3, tau_g 50 s): with ``fit_tilt`` the band just after the fitted
    part is centred near 1.2 times the model and narrower than the stationary band."""
    from treeinfer.inference.pulltest import PullPosterior

    s, n_fit = 300, 60
    params = dict(sigma_w=2e-6, sigma_a=1e-6, tau_ar=1.0, sigma_g=0.3, tau_g=50.0)
    post = PullPosterior(
        joints=("root", "stem"),
        channels=("root", "trunk"),
        kp=np.tile(KP, (s, 1)),
        sigma=np.full((s, 2), np.hypot(2e-6, 1e-6)),
        noise="ar1+gain",
        noise_params={k: np.full((s, 2), v) for k, v in params.items()},
    )
    force = np.linspace(100.0, 4000.0, 80)
    time = np.arange(80) * 0.1
    theta = np.asarray(model_tilts(model, jnp.asarray(KP[None]), jnp.asarray(force))[0][0])
    fit_tilt = 1.2 * theta[:, :n_fit]
    stat = predictive_band(model, post, force, n_draws=s, seed=1, time=time)
    fc = predictive_band(model, post, force, n_draws=s, seed=1, time=time, fit_tilt=fit_tilt)
    after = slice(n_fit, None)
    centre = (fc["lo"][:, after] + fc["hi"][:, after]) / 2
    np.testing.assert_allclose(centre / theta[:, after], 1.2, atol=0.02)
    np.testing.assert_allclose(fc["centre"][:, after] / theta[:, after], 1.2, atol=0.01)
    np.testing.assert_allclose(stat["centre"], stat["mean"])  # no forecast: the model's mean
    w_fc = (fc["hi"] - fc["lo"])[:, after]
    w_st = (stat["hi"] - stat["lo"])[:, after]
    assert np.all(w_fc < 0.3 * w_st)
    np.testing.assert_allclose(fc["lo"][:, :n_fit], stat["lo"][:, :n_fit])  # on the fit: same
