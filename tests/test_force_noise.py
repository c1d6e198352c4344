"""The errors-in-variables force-noise term (treeinfer.model.force_noise) against independent
references: the MVN density against scipy.stats.multivariate_normal, the forward-mode force
Jacobian against central differences of the simulator, the linearised covariance against the
Monte-Carlo covariance of simulations driven by noisy forces, and the predictive band with the
term holding noisy points that it misses without it."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from treeinfer.data.trajectories import Trajectory, stack_trajectories
from treeinfer.errors import ConfigError
from treeinfer.evaluation import metrics
from treeinfer.examples import example_path
from treeinfer.model import force_noise as fn
from treeinfer.model.likelihood import (
    gains_from_theta,
    likelihood_terms,
    measurement_log_likelihood,
    theta_from_gains,
)
from treeinfer.sim import make_simulator, simulate
from treeinfer.tree.description import load_tree

DT = 0.02
T = 50
KP = np.array([40.0, 120.0])
KD = np.array([0.5, 1.5])
THETA = theta_from_gains(KP, KD)
SIGMA_X = 0.002


def _forces(peaks, n=T):
    t = np.arange(n) * DT
    return np.stack([np.clip(t / 0.5, 0.0, 1.0) * p for p in peaks])


@pytest.fixture(scope="module")
def sim():
    return make_simulator(load_tree(example_path("two_branch")), obs_dt=DT)


def _tau(sim, forces, theta=THETA):
    kp, kd = gains_from_theta(jnp.asarray(np.atleast_2d(theta), jnp.float32), sim.n_joints)
    ro = jax.jit(lambda f: simulate(sim, kp, kd, f))(jnp.asarray(forces, jnp.float32))
    return np.asarray(ro.tau, float)


def test_mvn_log_prob_matches_scipy_with_padding():
    """Exact MVN(0, C + sigma^2 I) over the real samples, C rank-deficient, one pull padded."""
    rng = np.random.default_rng(0)
    n_t = 7
    mask = np.ones((2, n_t), bool)
    mask[1, 5:] = False
    jac = np.tril(rng.normal(size=(2, n_t, n_t)), -1) * 1e-3  # strictly causal: row 0 is zero
    cov = fn.force_noise_covariance(jac, 0.7, mask)
    lam, u = np.linalg.eigh(cov)
    basis = fn.ForceNoiseBasis(u, np.clip(lam, 0, None), (~mask).sum(1))
    np.testing.assert_allclose(basis.covariance(), cov, atol=1e-12)
    resid = np.where(mask[None], rng.normal(scale=2e-3, size=(3, 2, n_t)), 0.0)
    sx = np.array([1e-3, 2e-3, 4e-3])
    got = np.asarray(fn.mvn_log_prob(jnp.asarray(resid), basis, jnp.asarray(sx)), float)
    ref = [
        sum(
            stats.multivariate_normal(
                np.zeros(mask[b].sum()),
                cov[b][np.ix_(mask[b], mask[b])] + s**2 * np.eye(mask[b].sum()),
            ).logpdf(resid[n, b][mask[b]])
            for b in range(2)
        )
        for n, s in enumerate(sx)
    ]
    np.testing.assert_allclose(got, ref, rtol=1e-5)


def test_force_jacobian_matches_central_differences(sim):
    forces = _forces([6.0, 10.0])
    jac = fn.force_jacobian(sim, THETA, forces)
    assert jac.shape == (2, T, T)
    assert np.abs(np.triu(jac, 1)).max() == 0.0  # causal
    h = 0.25  # N
    cols = [0, 7, 24, 40, T - 1]
    pert = []
    for b in range(2):
        for s in cols:
            for sign in (1.0, -1.0):
                f = forces[b].copy()
                f[s] += sign * h
                pert.append(f)
    tau = _tau(sim, np.stack(pert))[0].reshape(2, len(cols), 2, T)
    fd = (tau[:, :, 0] - tau[:, :, 1]) / (2 * h)  # [B, cols, T]
    for b in range(2):
        for k, s in enumerate(cols):
            scale = np.abs(jac[b, :, s]).max() + 1e-9
            assert np.abs(fd[b, k] - jac[b, :, s]).max() < 2e-2 * scale, (b, s)
    assert np.abs(jac).max() > 1e-4  # the check above is not vacuous


def test_covariance_matches_monte_carlo(sim):
    """C = sigma_F^2 J J^T (linearised at the truth) against the sample covariance of the
    displacement change of 1500 simulations driven by noisy forces (no linearisation)."""
    forces = _forces([8.0])
    sigma_f = 0.02 * 8.0
    basis = fn.force_noise_basis(sim, THETA, forces, sigma_f)
    cov = basis.covariance()[0]
    rng = np.random.default_rng(1)
    n = 1500
    noisy = forces + sigma_f * rng.standard_normal((n, T))
    tau = _tau(sim, np.concatenate([forces, noisy]))[0]
    d = tau[1:] - tau[0]
    mc = np.cov(d.T)
    assert np.sqrt(np.mean(np.diag(cov))) > 5e-4  # not negligible next to 2 mm
    rel = np.linalg.norm(mc - cov) / np.linalg.norm(cov)
    assert rel < 0.1, rel
    # the diagonal (the point-wise band's variance) to Monte-Carlo precision
    late = slice(10, None)
    np.testing.assert_allclose(np.diag(mc)[late], fn.point_variance(basis)[0][late], rtol=0.15)


def _coverage_case(sim, n_rep, seed):
    """Recordings (truth on clean forces + 2 mm) and simulations on the recorded (2% noisy)
    forces, at the truth: [2 n_rep, T] each, plus the recorded forces."""
    rng = np.random.default_rng(seed)
    forces = np.tile(_forces([6.0, 10.0]), (n_rep, 1))
    sf = 0.02 * 10.0
    rec_f = forces + sf * rng.standard_normal(forces.shape)
    tau = _tau(sim, np.concatenate([forces, rec_f]))[0]
    clean, simulated = tau[: 2 * n_rep], tau[2 * n_rep :]
    return clean + SIGMA_X * rng.standard_normal(clean.shape), simulated, rec_f, sf


def test_predictive_band_with_force_term_covers(sim):
    """At the truth, the 95% predictive band with sigma_x alone misses noisy points of pulls
    driven by 2% noisy forces; adding diag C of each pull's own recorded force fixes it."""
    rec, simulated, rec_f, sf = _coverage_case(sim, 20, seed=3)
    pred = simulated[None]
    var = fn.point_variance(fn.force_noise_basis(sim, THETA, rec_f, sf))

    def coverage(extra):
        lo, hi, _ = metrics.noisy_predictive_interval(pred, SIGMA_X, 0.95, extra_variance=extra)
        return 1.0 - float(metrics.fraction_outside(lo, hi, rec))

    without, with_term = coverage(None), coverage(var)
    print(f"coverage without {without:.3f}, with the force term {with_term:.3f}")
    assert without < 0.92
    assert 0.93 <= with_term <= 0.97


def test_predictive_draws_have_the_covariance(sim):
    forces = _forces([8.0])
    basis = fn.force_noise_basis(sim, THETA, forces, 0.16)
    pred = np.zeros((4000, 1, T))
    draws = np.asarray(fn.predictive_draws(jax.random.key(0), pred, 1e-3, basis), float)[:, 0]
    want = basis.covariance()[0] + 1e-6 * np.eye(T)
    assert np.linalg.norm(np.cov(draws.T) - want) / np.linalg.norm(want) < 0.1


def test_likelihood_with_force_term_matches_scipy(sim):
    """measurement_log_likelihood(force_basis=...) = sum_b MVN(x_b | tau_b, C_b + sigma_x^2 I)."""
    rec, _, rec_f, sf = _coverage_case(sim, 1, seed=5)
    trajs = [Trajectory(np.arange(T) * DT, rec_f[b], rec[b], None, f"p{b}") for b in range(2)]
    obs = stack_trajectories(trajs)
    basis = fn.force_noise_basis(sim, THETA, obs.force, sf)
    ll = measurement_log_likelihood(sim, obs, "gaussian", force_basis=basis)
    theta = np.stack([THETA, THETA + np.array([0.1, -0.1, 0.2, 0.0])])
    sx = np.array([0.002, 0.003])
    got = np.asarray(jax.jit(ll)(jnp.asarray(np.column_stack([theta, np.log(sx)]), jnp.float32)))
    tau = _tau(sim, obs.force, theta)
    cov = basis.covariance()
    ref = [
        sum(
            stats.multivariate_normal(tau[n, b], cov[b] + sx[n] ** 2 * np.eye(T)).logpdf(rec[b])
            for b in range(2)
        )
        for n in range(2)
    ]
    np.testing.assert_allclose(got, ref, rtol=2e-4)
    # the same through likelihood_terms with the given reference; unchanged without the option
    terms = likelihood_terms(sim, obs, "gaussian", noise_force=sf, force_noise_reference=THETA)
    got2 = np.asarray(
        jax.jit(terms.log_likelihood)(
            jnp.asarray(np.column_stack([theta, np.log(sx)]), jnp.float32)
        )
    )
    # ... plus the standardised bias correction (force_noise_bias): zero at the reference;
    # near it, each direction's residual weighed by the exact force variance at theta (J at
    # theta itself). (Far from it the first order is only indicative.)
    np.testing.assert_allclose(got2[0], ref[0], rtol=2e-4)
    step = np.array([0.1, -0.1, 0.2, 0.0]) / 20
    near = np.concatenate([THETA + step, [np.log(0.003)]])[None]
    got3 = float(jax.jit(terms.log_likelihood)(jnp.asarray(near, jnp.float32))[0])
    plain3 = float(jax.jit(ll)(jnp.asarray(near, jnp.float32))[0])
    c3 = fn.force_noise_basis(sim, THETA + step, obs.force, sf).covariance()
    z = np.einsum("bts,bt->bs", basis.vectors, rec - _tau(sim, obs.force, near[:, :4])[0])
    d3 = np.einsum("bts,btu,bus->bs", basis.vectors, c3, basis.vectors)
    s2 = 0.003**2
    exact = 0.5 * np.sum(z**2 * (1.0 / (basis.values + s2) - 1.0 / (d3 + s2)))
    assert abs(exact) > 0.005  # the term is not negligible at this step
    # atol: float32 rounding of two log densities of ~1e3 nats (a few 1e-4)
    np.testing.assert_allclose(got3 - plain3, exact, rtol=0.1, atol=1e-3)
    assert "corrected score" in terms.settings["noise_force_bias_correction"]
    assert terms.force_noise is not None and terms.settings["noise_force"] == sf
    plain = likelihood_terms(sim, obs, "gaussian")
    assert plain.force_noise is None and "noise_force" not in plain.settings


def test_auto_estimate_and_bad_values():
    rng = np.random.default_rng(0)
    forces = _forces([6.0, 10.0, 8.0], n=150)
    sf = 0.2
    trajs = [
        Trajectory(np.arange(150) * DT, f + sf * rng.standard_normal(150), f * 0.01, None, "p")
        for f in forces
    ]
    sigma, desc = fn.resolve_noise_force("auto", trajs)
    assert abs(sigma / sf - 1.0) < 0.15 and "estimated" in desc
    assert fn.resolve_noise_force("2%", trajs)[0] == pytest.approx(
        0.02 * np.abs(np.stack([t.force for t in trajs])).max()
    )
    assert fn.resolve_noise_force(0.3, trajs)[0] == 0.3
    for bad in (-0.1, 0.0, math.nan, math.inf, "150%", "-2%", "x", None):
        with pytest.raises(ConfigError, match="noise_force"):
            fn.resolve_noise_force(bad, trajs)
    with pytest.raises(ConfigError, match="noise_force.*largest recorded force"):
        fn.resolve_noise_force(50.0, trajs)  # absurd: above every recorded force
    short = [Trajectory(np.arange(8) * DT, np.ones(8), np.zeros(8), None, "s")]
    with pytest.raises(ConfigError, match="too short"):
        fn.resolve_noise_force("auto", short)
    with pytest.raises(ConfigError, match="noise_force.*gaussian"):
        likelihood_terms(None, stack_trajectories(trajs), "student_t", noise_force=0.1)


def test_bias_correction_is_unbiased_standardised_and_bounded():
    """The standardised correction (force_noise_bias docstring) weighs each direction's residual
    z_i by the force-induced variance at theta, d_i = L_i + slope_i . dth (first order, floored
    at 0), keeping the reference's normalisation:

    * its expectation over residuals drawn with the variance at theta is the same for every
      theta (no preference for gains with a large or small response to the force noise: the
      bias it corrects), checked by Monte Carlo against the closed form -1/2 sum(1 + log 2 pi
      (L + s^2));
    * to first order it equals the corrected score's 1/2 sum slope . dth / (L + s^2) at a typical
      residual (z_i^2 = L_i + s^2), and it rewards nothing for a zero residual (the corrected
      score's extra density for a large force response did, whatever the data: on chain2 it
      drew the posterior toward an undamped child);
    * beyond BIAS_TRUST log units it is held (a weakly identified gain far from the reference
      cannot buy density from the linear extrapolation)."""
    rng = np.random.default_rng(1)
    n_t, d = 6, 4
    lam = rng.uniform(1e-6, 4e-6, size=(1, n_t))
    u = np.linalg.qr(rng.normal(size=(n_t, n_t)))[0][None]
    slope = rng.normal(scale=1e-6, size=(1, n_t, d))
    ref = np.zeros(d)
    basis = fn.ForceNoiseBasis(u, lam, np.zeros(1, int), slope, ref)
    s2 = 1e-6
    sx = jnp.asarray([math.sqrt(s2)])

    def logp(z, dth):  # z [M, n_t] in the eigenbasis -> [M]
        r = np.einsum("ts,ms->mt", u[0], z)[:, None]  # [M, 1, n_t]
        th = np.broadcast_to(np.asarray(dth, float), (len(z), d))
        return np.asarray(
            fn.mvn_log_prob(jnp.asarray(r), basis, jnp.full(len(z), sx[0]), jnp.asarray(th)), float
        )

    def var_at(dth):
        dv = np.einsum("bsj,j->bs", slope, fn.BIAS_TRUST * np.tanh(np.asarray(dth) / fn.BIAS_TRUST))
        return np.maximum(lam + dv, 0.0)[0] + s2

    closed = -0.5 * np.sum(1.0 + np.log(2 * np.pi * (lam[0] + s2)))
    for dth in (np.zeros(d), np.array([0.3, -0.2, 0.1, 0.4]), np.array([2.0, -3.0, 1.0, 5.0])):
        z = rng.normal(size=(400, n_t)) * np.sqrt(var_at(dth))
        mc = logp(z, dth)
        assert abs(mc.mean() - closed) < 4 * mc.std() / math.sqrt(len(mc)) + 1e-3
    # first order at a typical residual: the corrected score's slope
    small = np.array([0.01, -0.02, 0.0, 0.015])
    typical = np.sqrt(lam[0] + s2)[None]
    linear = 0.5 * np.einsum("bsj->j", slope / (lam + s2)[..., None])
    got = logp(typical, small) - logp(typical, np.zeros(d))
    np.testing.assert_allclose(got, linear @ small, rtol=2e-2)
    zero = np.zeros((1, n_t))
    assert abs(logp(zero, small)[0] - logp(zero, np.zeros(d))[0]) < 1e-9
    # bounded: far moves change the density by no more than the saturated variance allows
    far = [logp(typical, k * np.array([1.0, -1.0, 1.0, -1.0]))[0] for k in (10.0, 1000.0)]
    np.testing.assert_allclose(far[0], far[1], rtol=1e-5)
