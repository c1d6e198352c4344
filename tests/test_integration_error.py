"""The integration-error floor (issue 27, clean data; :mod:`treeinfer.model.integration_error`).

Against an independent reference: the data come from the planar Lagrangian chain integrated by
scipy (:mod:`treeinfer.sim.planar_reference`, no code shared with treeinfer's MuJoCo step), so the
residual at the true gains IS the simulator's discretisation error, which the step-doubling
estimate must reproduce. Then: the floor changes nothing measurable on 2 mm noise, and on a
small clean case the start pipeline's posterior covers the truths (without the floor its
importance weights fail, k_hat 4.1, and the MAP is 26-47 posterior std off the truth)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from experiments._planar_cases import make_case
from treeinfer.data.trajectories import Trajectory
from treeinfer.inference.integration_floor import (
    applies,
    floor_for_run,
    measure_integration_error,
)
from treeinfer.inference.problem import make_problem
from treeinfer.model.integration_error import IntegrationError
from treeinfer.model.likelihood import likelihood_terms
from treeinfer.sim import simulate


@pytest.fixture(scope="module")
def clean():
    """chain2 of the calibration study (seed 0), its 3 clean pulls of 3 s, and its problem at the
    run's accuracy-controlled step (0.1 mm over the prior box)."""
    case = make_case("chain2", 0, n_test=1)
    t = np.arange(case.train_force.shape[1]) * case.dt
    trajs = [
        Trajectory(t, f, x, None, f"p{i}")
        for i, (f, x) in enumerate(zip(case.train_force, case.train_tau))
    ]
    problem = make_problem(case.tree, trajs, likelihood="gaussian", sim_tolerance=1e-4)
    truth = np.log(np.concatenate([case.kp, case.kd]))
    return case, trajs, problem, truth


def _rms(x):
    return float(np.sqrt(np.mean(np.square(x))))


def test_step_doubling_matches_the_difference_to_the_independent_integration(clean):
    case, _, problem, truth = clean
    ie = measure_integration_error(problem, truth)
    sim = problem.sim
    tau = simulate(sim, jnp.asarray(case.kp[None]), jnp.asarray(case.kd[None]), case.train_force)
    actual = np.asarray(tau.tau[0], float) - case.train_tau  # simulated minus exact, [B, T]
    # measured: 1.4 micron either way, correlation 1.000 (3 s pulls: rms ratio 1.00)
    assert 1e-7 < ie.rms < 1e-5
    assert ie.rms / _rms(actual) == pytest.approx(1.0, abs=0.1)
    corr = np.sum(ie.shape * actual) / np.sqrt(np.sum(ie.shape**2) * np.sum(actual**2))
    assert corr > 0.99
    # with the measured error removed, what is left of the residual is a few percent of it
    assert _rms(actual - ie.shape) < 0.1 * _rms(actual)
    # the worst case over the prior box (the step choice's estimate) is far above it: the
    # floor that was tried and reverted
    assert problem.sim.step_info["estimated_error"] > 20 * ie.rms


def test_the_likelihood_takes_the_floor_and_offset_everywhere(clean):
    """The problem's likelihood, its padded data-argument twin and the start pipeline's residual
    density agree; the settings and the description say the floor's size."""
    case, trajs, problem, truth = clean
    ie = measure_integration_error(problem, truth)
    obs = problem.obs
    terms = likelihood_terms(problem.sim, obs, "gaussian", integration_error=ie)
    assert terms.settings["integration_error"]["rms_m"] == pytest.approx(ie.rms)
    assert "integration error" in terms.description and "floor" in terms.description
    theta = np.array([[*truth, np.log(1e-6)], [*(truth + 0.01), np.log(3e-6)]], np.float32)
    direct = np.asarray(terms.log_likelihood(jnp.asarray(theta)), float)
    b, t = np.shape(obs.force)
    data = terms.data_of(obs, (b + 1, t + 37))  # a shape bucket: padded rows and steps
    padded = np.asarray(terms.loglik_of(data)(jnp.asarray(theta)), float)
    np.testing.assert_allclose(padded, direct, rtol=1e-4)
    kp, kd = jnp.exp(theta[:, :2]), jnp.exp(theta[:, 2:4])
    ro = simulate(problem.sim, kp, kd, jnp.asarray(obs.force))
    dx = jnp.asarray(obs.displacement)[None] - ro.tau
    host = np.asarray(terms.residual_loglik(dx, None, jnp.asarray(theta)), float)
    np.testing.assert_allclose(host, direct, rtol=1e-4)
    # by hand: offset and floor in a Gaussian of numpy's own
    sx = np.sqrt(np.exp(theta[:, 4].astype(float)) ** 2 + ie.rms**2)
    r = np.asarray(dx, float) + ie.shape[None]
    ref = -0.5 * (r / sx[:, None, None]) ** 2 - np.log(sx[:, None, None] * np.sqrt(2 * np.pi))
    np.testing.assert_allclose(direct, ref.sum((-2, -1)), rtol=1e-4)
    # without the floor the truth's density is far lower: the error is the whole residual
    plain = likelihood_terms(problem.sim, obs, "gaussian")
    assert float(plain.log_likelihood(jnp.asarray(theta[:1]))[0]) < direct[0] - 100.0


def test_the_floor_changes_nothing_measurable_on_noisy_data(clean):
    """2 mm noise: the log-likelihood with and without the floor differs by a near constant: over
    +-0.03 log units of the gains (1-3 posterior std at 2 mm) and +-10% in sigma_x it changes by
    less than 0.1 nats (measured 0.05: the offset's tilt, the white floor adds ~1e-4), so the
    posterior density is reweighted by < 10% across its bulk and its mean moves by a few
    percent of its std."""
    case, _, problem, truth = clean
    ie = measure_integration_error(problem, truth)
    rng = np.random.default_rng(1)
    obs = problem.obs._replace(
        displacement=problem.obs.displacement + 2e-3 * rng.standard_normal(case.train_tau.shape)
    )
    with_floor = likelihood_terms(problem.sim, obs, "gaussian", integration_error=ie)
    plain = likelihood_terms(problem.sim, obs, "gaussian")
    # the posterior's bulk on 2 mm: a few percent in the gains, sigma_x around 2 mm
    theta = np.array(
        [[*(truth + d), np.log(s)] for d in (0.0, 0.03, -0.03) for s in (1.8e-3, 2.2e-3)],
        np.float32,
    )
    a = np.asarray(with_floor.log_likelihood(jnp.asarray(theta)), float)
    b = np.asarray(plain.log_likelihood(jnp.asarray(theta)), float)
    assert np.ptp(a - b) < 0.1
    assert np.all(np.abs(a - b) < 0.1)


def test_on_a_small_clean_case_the_intervals_cover_the_truths(clean):
    """The run layer's path: the MAP, the floor measured there, the problem rebuilt with it; the
    start pipeline's importance weights then pass (k_hat < 0.7, no sampler) and every truth lies
    inside its 95% interval. Measured: k_hat 0.02, intervals 0.03-0.5% wide, sigma_x at the
    prior's 1 micron end (the floor 1.4 micron carries the rest)."""
    from treeinfer.inference.start_pipeline import auto_start

    case, trajs, problem, truth = clean
    assert applies(problem, "auto") and not applies(problem, "uniform")
    logs = []

    def make(ie):
        return make_problem(
            case.tree, trajs, likelihood="gaussian", sim=problem.sim, integration_error=ie
        )

    floored = floor_for_run(problem, make, "auto", None, 0, log=logs.append)
    rec = floored.settings["integration_error"]
    assert any("integration error" in m for m in logs)
    assert 1e-7 < rec["rms_m"] < 1e-5 and floored.start_hint is not None
    assert not applies(floored, "auto")  # measured once
    # a resumed run takes it again at the reference it recorded: the same floor
    again = floor_for_run(problem, make, "auto", {"integration_error": rec}, 0)
    assert again.settings["integration_error"]["rms_m"] == pytest.approx(rec["rms_m"], rel=1e-3)
    post, theta0 = auto_start(floored, 64, 0, log=print)
    assert post is not None, "importance weights not trusted"
    th = np.asarray(post.theta, float)
    lo, hi = np.quantile(th[:, :4], [0.025, 0.975], axis=0)
    assert np.all((lo <= truth) & (truth <= hi)), (lo, truth, hi)
    assert np.all(hi - lo < 0.05)  # still informative: a few per mille, not the prior


def test_a_wrong_shape_is_refused(clean):
    from treeinfer.errors import ConfigError

    _, _, problem, truth = clean
    ie = IntegrationError(np.zeros((5, 7)), 1e-6, 10, truth)
    with pytest.raises(ConfigError, match="integration_error"):
        likelihood_terms(problem.sim, problem.obs, "gaussian", integration_error=ie)


def test_the_predictive_band_carries_the_floor():
    """An unseen pull's rollout is not corrected for the error, so the band adds it in
    quadrature (runs without a floor: unchanged)."""
    from treeinfer.evaluation.predictive import noise_for

    theta = np.array([[3.0, 4.0, -1.0, 0.0, np.log(1e-6)], [3.0, 4.0, -1.0, 0.0, np.log(2e-3)]])
    plain, kind = noise_for(theta, 2, {"likelihood": "gaussian"})
    floored, _ = noise_for(
        theta, 2, {"likelihood": "gaussian", "integration_error": {"rms_m": 1.5e-6}}
    )
    assert kind == "gaussian"
    np.testing.assert_allclose(plain, [1e-6, 2e-3], rtol=1e-5)  # float32 inside
    np.testing.assert_allclose(floored, [np.hypot(1e-6, 1.5e-6), np.hypot(2e-3, 1.5e-6)], rtol=1e-5)


def test_with_the_force_noise_term_the_floor_is_offset_and_quadrature():
    """The default's noisy path (errors-in-variables term, small two-branch case): the floored
    likelihood is the force-noise MVN of the corrected residual with sigma_x^2 + rms^2 (scipy
    with the dense covariance), and on 2 mm noise it differs from the plain one by a near
    constant."""
    from scipy import stats

    from treeinfer.data.trajectories import stack_trajectories
    from treeinfer.examples import example_path
    from treeinfer.model.likelihood import theta_from_gains
    from treeinfer.sim import make_simulator
    from treeinfer.tree.description import load_tree

    dt, n = 0.02, 50
    sim = make_simulator(load_tree(example_path("two_branch")), obs_dt=dt)
    theta0 = theta_from_gains(np.array([40.0, 120.0]), np.array([0.5, 1.5]))
    t = np.arange(n) * dt
    f = np.stack([np.clip(t / 0.5, 0.0, 1.0) * p for p in (3.0, 6.0)])
    kp, kd = jnp.exp(jnp.asarray(theta0[None, :2])), jnp.exp(jnp.asarray(theta0[None, 2:]))
    tau = np.asarray(simulate(sim, kp, kd, jnp.asarray(f, jnp.float32)).tau[0], float)
    x = tau + 2e-3 * np.random.default_rng(3).standard_normal(tau.shape)
    obs = stack_trajectories([Trajectory(t, f[b], x[b], None, f"p{b}") for b in range(2)])
    e = 1.5e-6 * np.sin(np.pi * t / t[-1])[None] * np.array([[1.0], [2.0]])
    ie = IntegrationError(e, float(np.sqrt(np.mean(e**2))), sim.substeps, theta0)
    kw = dict(noise_force=0.05, force_noise_reference=theta0)
    floored = likelihood_terms(sim, obs, "gaussian", integration_error=ie, **kw)
    plain = likelihood_terms(sim, obs, "gaussian", **kw)
    th = np.array([[*theta0, np.log(2e-3)], [*(theta0 + 0.05), np.log(2.5e-3)]], np.float32)
    a = np.asarray(floored.log_likelihood(jnp.asarray(th)), float)
    b = np.asarray(plain.log_likelihood(jnp.asarray(th)), float)
    assert np.all(np.abs(a - b) < 0.1)  # measured 0.004 and 0.085 (130 nats below the first)
    # at the reference the bias correction is zero: the MVN of the corrected residual
    cov = floored.force_noise.basis(sim, np.asarray(obs.force), np.asarray(obs.mask)).covariance()
    s2 = 2e-3**2 + ie.rms**2
    ref = sum(
        stats.multivariate_normal(tau[j] - e[j], cov[j] + s2 * np.eye(n)).logpdf(x[j])
        for j in range(2)
    )
    np.testing.assert_allclose(a[0], ref, rtol=2e-4)
