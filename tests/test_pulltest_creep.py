"""The viscoelastic pulling model and the AR(1) residuals (treeinfer.inference.pulltest.creep,
.residuals): the creep element against the standard linear solid's closed forms and scipy's
linear-system simulation, the chain's long-term creep against a softer elastic chain, the
continuous-time AR(1) likelihood against scipy's multivariate normal with its covariance, and
NUTS recovering a synthetic creep test (the residual check telling elastic from viscoelastic)."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
import pytest
from scipy import signal
from scipy.stats import multivariate_normal

from treeinfer.data import PullSetup
from treeinfer.inference.pulltest import (
    creep_states,
    creep_tilts,
    fit_pull_test,
    lag1_autocorrelation,
    model_tilts,
    ou_white_innovations,
    ou_white_log_prob,
    predictive_band,
    pull_model,
    residual_check,
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


def sls_ramp_hold(t, rate, t1, c, tau):
    """Creep angle of ``dq/dt = (c u - q) / tau`` for ``u = rate * min(t, t1)``: on the ramp
    ``c r (t - tau (1 - exp(-t/tau)))``, then relaxing to ``c r t1`` with ``tau``."""
    ramp = c * rate * (t - tau * (1 - np.exp(-t / tau)))
    x1 = c * rate * (t1 - tau * (1 - np.exp(-t1 / tau)))
    hold = c * rate * t1 + (x1 - c * rate * t1) * np.exp(-(t - t1) / tau)
    return np.where(t <= t1, ramp, hold)


def test_creep_of_a_ramp_and_hold_matches_the_closed_form():
    rng = np.random.default_rng(0)
    # an irregular time base (steps of 0.05-0.3 s and one 5 s gap), the ramp's end on a sample
    steps = rng.uniform(0.05, 0.3, 600)
    steps[300] = 5.0
    t = np.concatenate([[0.0], np.cumsum(steps)])
    t1 = t[200]
    rate, c, tau = 1e-4, np.array([0.4, 0.1]), np.array([7.0, 60.0])
    drive = rate * np.minimum(t, t1)
    got = np.asarray(creep_states(jnp.asarray(np.stack([drive, drive])), t, c, tau))
    want = np.stack([sls_ramp_hold(t, rate, t1, c[i], tau[i]) for i in range(2)])
    np.testing.assert_allclose(got, want, rtol=2e-4, atol=1e-10)
    # and the long-term compliance: (1 + c) times the elastic deflection
    assert got[0, -1] == pytest.approx(c[0] * rate * t1, rel=1e-3)


def test_creep_of_a_ramp_hold_release_matches_scipy_lsim():
    """The joint's total deflection ``q_e + q_c`` for a moment history is the standard linear
    solid's creep compliance ``1/K + 1/(K2 (1 + tau s))``: scipy's linear simulation (exact for
    piecewise-linear inputs) of that transfer function gives the same."""
    k, k2, tau = 4.0e5, 1.0e6, 12.0
    t = np.arange(0.0, 200.0, 0.1)
    m = np.interp(t, [0, 60, 120, 130, 200], [0, 3000.0, 2600.0, 0.0, 0.0])  # N m
    m = m + 40.0 * np.sin(t)  # winch steps, roughly
    qe = m / k
    qc = np.asarray(creep_states(jnp.asarray(qe[None]), t, np.array([k / k2]), np.array([tau])))
    # 1/K + 1/(K2 (1 + tau s)) = (tau s / K + 1/K + 1/K2) / (tau s + 1)
    sys = signal.lti([tau / k, 1 / k + 1 / k2], [tau, 1.0])
    _, want, _ = signal.lsim(sys, m, t)
    np.testing.assert_allclose(qe + qc[0], want, rtol=1e-3, atol=1e-9)
    # the release leaves a residual tilt that recovers with tau (not a purely elastic return)
    i = np.searchsorted(t, 131.0)
    assert qc[0, i] > 0.3 * qc[0].max()


def test_chain_creeps_to_the_softer_elastic_chain(model):
    """A force applied in one step and held for 50 relaxation times: the viscoelastic chain
    first reads the elastic chain's tilts, and ends at those of springs ``Kp / (1 + c)`` (the
    long-term stiffness of the standard linear solid)."""
    t = np.linspace(0.0, 500.0, 801)
    force = np.where(t > 0, 2500.0, 0.0)
    c = np.array([0.5, 0.2])
    tau = np.array([10.0, 5.0])
    tilt, ok = creep_tilts(
        model, jnp.asarray(KP[None]), jnp.asarray(c[None]), jnp.asarray(tau[None]), force, t
    )
    assert bool(ok[0])
    elastic = np.asarray(model_tilts(model, jnp.asarray(KP[None]), jnp.asarray([2500.0]))[0])
    soft = np.asarray(
        model_tilts(model, jnp.asarray((KP / (1 + c))[None]), jnp.asarray([2500.0]))[0]
    )
    tilt = np.asarray(tilt[0])
    # the first loaded sample is 0.625 s in: creep has begun, by at most c (1 - exp(-dt/tau))
    np.testing.assert_allclose(tilt[:, 1], elastic[0, :, 0], rtol=0.05)
    np.testing.assert_allclose(tilt[:, -1], soft[0, :, 0], rtol=5e-3)
    assert not np.allclose(soft, elastic, rtol=0.1)  # the two limits are far apart


def ou_covariance(t, sigma_w, sigma_a, tau):
    return sigma_a**2 * np.exp(-np.abs(t[:, None] - t[None, :]) / tau) + sigma_w**2 * np.eye(t.size)


def test_ar1_likelihood_equals_the_multivariate_normal():
    rng = np.random.default_rng(1)
    n = 60
    steps = rng.uniform(0.08, 0.3, n - 1)
    steps[20] = 3.0  # a gap
    t = np.concatenate([[0.0], np.cumsum(steps)])
    sw, sa, tau = np.array([0.002, 0.01]), np.array([0.02, 0.005]), np.array([1.5, 0.3])
    resid = np.stack(
        [multivariate_normal(np.zeros(n), ou_covariance(t, sw[i], sa[i], tau[i])).rvs(
            random_state=rng
        ) for i in range(2)]
    )  # fmt: skip
    mask = np.ones((2, n), bool)
    mask[0, [3, 4, 30]] = False
    mask[1, 50:] = False
    got = float(ou_white_log_prob(resid, mask, t, sw, sa, tau))
    want = 0.0
    for i in range(2):
        m = mask[i]
        cov = ou_covariance(t[m], sw[i], sa[i], tau[i])
        want += multivariate_normal(np.zeros(m.sum()), cov).logpdf(resid[i, m])
    assert got == pytest.approx(want, abs=2e-3 * abs(want))
    # a wrong correlation time gives another density: the test can fail
    other = float(ou_white_log_prob(resid, mask, t, sw, sa, tau * 3))
    assert abs(other - want) > 1.0


def test_lag1_autocorrelation():
    rng = np.random.default_rng(2)
    white = rng.standard_normal((1, 4000))
    ar = np.zeros((1, 4000))
    for i in range(1, 4000):
        ar[0, i] = 0.8 * ar[0, i - 1] + rng.standard_normal()
    ar[0, 100] = np.nan
    assert abs(lag1_autocorrelation(white)[0]) < 0.05
    assert lag1_autocorrelation(ar)[0] == pytest.approx(0.8, abs=0.03)


def synthetic_pull(model, rng):
    """A winch pull: a stepped 60 s ramp to 3 kN, a 60 s hold, a 10 s release, 30 s of rest,
    at 0.5 s; the chain creeps (c 0.3 / 0.2, tau 15 / 30 s); white noise 0.004 deg."""
    t = np.arange(0.0, 160.0, 0.5)
    ramp = 3000.0 * np.floor(np.minimum(t, 60.0) / 4.0) / 15.0  # a step every 4 s
    force = np.where(t <= 120, ramp, np.maximum(3000.0 * (130.0 - t) / 10.0, 0.0))
    truth = {"kp": KP, "ratio": np.array([0.3, 0.2]), "tau": np.array([15.0, 30.0])}
    clean, _ = creep_tilts(
        model,
        jnp.asarray(KP[None]),
        jnp.asarray(truth["ratio"][None]),
        jnp.asarray(truth["tau"][None]),
        force,
        t,
    )
    sigma = np.deg2rad(0.004)
    y = np.asarray(clean[0]) + sigma * rng.standard_normal((2, t.size))
    return t, force, y, truth


@pytest.mark.slow  # about a minute of NUTS on the loaded 2-core box
def test_nuts_recovers_synthetic_creep_and_the_check_tells_the_models_apart(model):
    rng = np.random.default_rng(4)
    t, force, y, truth = synthetic_pull(model, rng)
    kw = dict(time=t, num_warmup=200, num_samples=200, num_chains=1, seed=3)
    ve = fit_pull_test(model, force, y, creep=True, **kw)
    s = ve.summary()
    for j, name in enumerate(("root", "stem")):
        for key, val in (("kp", truth["kp"][j]), ("creep_ratio", truth["ratio"][j])):
            assert s[f"{key}_{name}"]["q2.5"] < val < s[f"{key}_{name}"]["q97.5"], (key, s)
        assert s[f"creep_tau_{name}"]["q2.5"] < truth["tau"][j] < s[f"creep_tau_{name}"][
            "q97.5"
        ], s  # fmt: skip
    band = predictive_band(model, ve, force, n_draws=100, time=t)
    inside = (y >= band["lo"]) & (y <= band["hi"])
    assert inside.mean() > 0.9
    assert not residual_check(band["mean"], y)["needs_ar1"].any()
    # the elastic model leaves slow, correlated residuals: the check calls for more
    el = fit_pull_test(model, force, y, **kw)
    el_band = predictive_band(model, el, force, n_draws=100, time=t)
    assert residual_check(el_band["mean"], y)["needs_ar1"].all()
    inside_el = (y >= el_band["lo"]) & (y <= el_band["hi"])
    assert inside_el.mean() < inside.mean()
    assert math.isfinite(ve.diagnostics["divergences"])


def test_ar1_innovations_are_white_under_the_model_and_not_under_another():
    rng = np.random.default_rng(6)
    n = 3000
    t = np.cumsum(rng.uniform(0.08, 0.14, n))
    sw, sa, tau = np.array([0.002]), np.array([0.01]), np.array([1.0])
    # simulate the continuous-time AR(1) exactly on the irregular grid, plus white noise
    a = np.zeros(n)
    a[0] = sa[0] * rng.standard_normal()
    for i in range(1, n):
        rho = math.exp(-(t[i] - t[i - 1]) / tau[0])
        a[i] = rho * a[i - 1] + sa[0] * math.sqrt(1 - rho**2) * rng.standard_normal()
    resid = (a + sw[0] * rng.standard_normal(n))[None]
    mask = np.ones((1, n), bool)
    z = ou_white_innovations(resid, mask, t, sw, sa, tau)
    assert abs(lag1_autocorrelation(z)[0]) < 0.06
    assert np.nanstd(z) == pytest.approx(1.0, abs=0.05)
    assert lag1_autocorrelation(resid)[0] > 0.8  # the raw residuals are not white
    # a model with too short a correlation time leaves correlated innovations
    z_bad = ou_white_innovations(resid, mask, t, sw, sa, tau / 20)
    assert lag1_autocorrelation(z_bad)[0] > 0.3


def test_root_lag_is_a_generalised_kelvin_solid_against_scipy_lsim(model):
    """The root joint with the fast lag element and the slow creep element in series with its
    spring: its deflection under a moment history is the generalised Kelvin solid's creep
    compliance ``1/K + c_f/(K (1 + tau_f s)) + c/(K (1 + tau s))`` (scipy's linear simulation);
    the stem joint, without a lag, stays the standard linear solid."""
    from treeinfer.inference.pulltest import lagged_creep_tilts

    t = np.arange(0.0, 120.0, 0.1)
    m = np.interp(t, [0, 40, 80, 85, 120], [0, 3000.0, 3000.0, 0.0, 0.0])
    m = m + 200.0 * (np.floor(t / 3.0) % 2)  # winch steps
    k, c, tau, cf, tf = 4.0e5, 0.3, 20.0, 0.6, 0.4
    qe = m / k
    qc = np.asarray(creep_states(jnp.asarray(qe[None]), t, np.array([c]), np.array([tau])))[0]
    qf = np.asarray(creep_states(jnp.asarray(qe[None]), t, np.array([cf]), np.array([tf])))[0]
    parts = [signal.lti([1.0 / k], [1.0]), signal.lti([c / k], [tau, 1.0]),
             signal.lti([cf / k], [tf, 1.0])]  # fmt: skip
    want = sum(signal.lsim(p, m, t)[1] for p in parts)
    np.testing.assert_allclose(qe + qc + qf, want, rtol=2e-3, atol=1e-9)
    # in the chain: the lag adds to the root's creep alone, through the tilts' Jacobian
    force = np.where(t > 1.0, 2500.0, 0.0)
    ratio, taus = jnp.asarray([[0.3, 0.2]]), jnp.asarray([[20.0, 30.0]])
    base, _ = creep_tilts(model, jnp.asarray(KP[None]), ratio, taus, force, t)
    got, ok = lagged_creep_tilts(
        model, jnp.asarray(KP[None]), ratio, taus, jnp.asarray([cf]), jnp.asarray([tf]), force, t
    )
    assert bool(ok[0])
    # a step held for 30 lag times: the root's extra creep is cf times its elastic deflection
    root_only = creep_tilts(model, jnp.asarray(KP[None]), jnp.asarray([[cf, 0.0]]),
                            jnp.asarray([[tf, 30.0]]), force, t)[0]  # fmt: skip
    elastic = model_tilts(model, jnp.asarray(KP[None]), force)[0]
    np.testing.assert_allclose(
        np.asarray(got - base), np.asarray(root_only - elastic), rtol=1e-5, atol=1e-12
    )
    assert float(np.max(np.abs(got - base))) > 1e-4  # the lag is not nothing


@pytest.mark.slow  # about a minute of NUTS on the loaded 2-core box
def test_nuts_with_a_root_lag_runs_and_reports_it(model):
    rng = np.random.default_rng(5)
    t, force, y, truth = synthetic_pull(model, rng)
    post = fit_pull_test(model, force, y, time=t, creep=True, lag=True, noise="ar1",
                         num_warmup=60, num_samples=60, num_chains=1, seed=1)  # fmt: skip
    s = post.summary()
    assert {"lag_ratio_root", "lag_tau_root"} <= set(s)
    assert 0.05 <= s["lag_tau_root"]["q2.5"] and s["lag_tau_root"]["q97.5"] <= 5.0
    assert s["creep_tau_root"]["q2.5"] >= 5.0  # the slow element keeps to its own range
    band = predictive_band(model, post, force, n_draws=50, time=t)
    assert ((y >= band["lo"]) & (y <= band["hi"])).mean() > 0.8
    with pytest.raises(Exception, match="lag"):
        fit_pull_test(model, force, y, time=t, lag=True, num_warmup=2, num_samples=2)


def test_a_lag_on_every_joint_is_each_joints_extra_creep(model):
    """``joint=None``: a fast element on each joint, the same as creep with the two ratios and
    time constants added through the tilts' Jacobian (each joint's own)."""
    from treeinfer.inference.pulltest import lagged_creep_tilts

    t = np.arange(0.0, 60.0, 0.1)
    force = np.interp(t, [0, 20, 40, 45, 60], [0, 2500.0, 2500.0, 0.0, 0.0])
    kp = jnp.asarray(KP[None])
    ratio, taus = jnp.asarray([[0.3, 0.2]]), jnp.asarray([[20.0, 30.0]])
    cf, tf = jnp.asarray([[0.5, 0.8]]), jnp.asarray([[0.4, 1.5]])
    got, ok = lagged_creep_tilts(model, kp, ratio, taus, cf, tf, force, t, joint=None)
    base = creep_tilts(model, kp, ratio, taus, force, t)[0]
    fast = creep_tilts(model, kp, cf, tf, force, t)[0]
    elastic = model_tilts(model, kp, force)[0]
    assert bool(ok[0])
    np.testing.assert_allclose(np.asarray(got), np.asarray(base + fast - elastic), rtol=1e-5,
                               atol=1e-12)  # fmt: skip
    with pytest.raises(Exception, match="lag"):
        fit_pull_test(model, force, np.zeros((2, t.size)), time=t, creep=True, lag="stem")
