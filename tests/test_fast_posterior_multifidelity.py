"""Multi-fidelity fast posterior (issue 15, CPU): the rollout program with the simulation step
as an argument, and importance weights at the accurate step behind a fit at a coarse one.

References: ``problem.log_density`` of problems built with each step (the likelihood's own
program); the exact posterior at the accurate step by quadrature on a grid."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from treeinfer.data.trajectories import Trajectory
from treeinfer.errors import ConfigError
from treeinfer.inference.fast import BatchEvaluator, fast_posterior, resolve_coarse_substeps
from treeinfer.inference.problem import make_problem
from treeinfer.sim import make_simulator
from treeinfer.sim.reference import simulate_reference
from treeinfer.tree.generators import chain

FINE, COARSE = 8, 1


def _problem(tree, trajs, substeps):
    sim = make_simulator(tree, obs_dt=0.01, substeps=substeps)
    return make_problem(tree, trajs, sim=sim, nn_prior=False, kT=0.02, likelihood="boltzmann")


@pytest.fixture(scope="module")
def one_joint():
    tree = chain(1, lengths=0.7, radii=0.03, angles_deg=0.0, base_position=(0.0, 0.0, 1.5),
                 base_pitch_deg=20.0, levels=1, name="c1")  # fmt: skip
    kp, kd = np.array([40.0]), np.array([0.6])
    t = np.arange(60) * 0.01
    rng = np.random.default_rng(2)
    ref = make_simulator(tree, obs_dt=0.01, substeps=FINE)
    trajs = []
    for i, peak in enumerate((6.0, 3.0)):
        f = peak * np.clip(t / (0.1 + 0.1 * i), 0.0, 1.0) * (t < 0.35)
        tau, _ = simulate_reference(ref, kp, kd, f)
        trajs.append(Trajectory(t, f, tau + 1e-3 * rng.normal(size=tau.shape), None, f"p{i}"))
    return tree, trajs, np.log(np.concatenate([kp, kd]))


def _grid_moments(problem, center, sd):
    axes = [np.linspace(m - 7 * s, m + 7 * s, 101) for m, s in zip(center, sd)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 2)
    lp = np.asarray(jax.jit(problem.log_density)(jnp.asarray(grid, jnp.float32)), float)
    w = np.exp(lp - lp[np.isfinite(lp)].max())
    w = np.where(np.isfinite(w), w, 0.0)
    w /= w.sum()
    mean = w @ grid
    return mean, np.sqrt(w @ (grid - mean) ** 2)


def test_evaluator_takes_the_step_as_an_argument(one_joint):
    tree, trajs, truth = one_joint
    problem = _problem(tree, trajs, FINE)
    ev = BatchEvaluator(problem, chunk=4)
    assert ev.traced and ev.substeps == FINE
    theta = truth + np.random.default_rng(0).normal(size=(6, 2)) * [[0.3, 1.0]]
    for s in (FINE, COARSE, 3):
        want = np.asarray(
            jax.jit(_problem(tree, trajs, s).log_density)(jnp.asarray(theta, jnp.float32))
        )
        got = ev.log_density(theta, s)
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-3)
    assert ev.runs == {FINE: 2, COARSE: 2, 3: 2}  # one program, every step
    # the coarse step does change the density here (else the next test could not fail)
    assert np.max(np.abs(ev.log_density(theta, COARSE) - ev.log_density(theta))) > 1.0
    # the static program (the Pallas kernel's way) equals the traced one at its own step
    static = BatchEvaluator(problem, chunk=4, traced_substeps=False)
    np.testing.assert_allclose(static.log_density(theta), ev.log_density(theta), rtol=1e-5,
                               atol=1e-3)  # fmt: skip
    with pytest.raises(ConfigError, match="substeps"):
        static.evaluate(theta, COARSE)
    with pytest.raises(ConfigError, match="coarse_substeps"):
        resolve_coarse_substeps(static, COARSE)
    assert resolve_coarse_substeps(static, "auto") == FINE
    assert resolve_coarse_substeps(ev, None) == FINE
    assert resolve_coarse_substeps(ev, "auto") == FINE  # a given step: no stability choice


def test_multifidelity_weights_target_the_accurate_posterior(one_joint):
    tree, trajs, _ = one_joint
    problem = _problem(tree, trajs, FINE)
    res = fast_posterior(problem, 256, n_starts=3, n_draws=3000, seed=1, coarse_substeps=COARSE)
    st = res.settings
    assert st["fit_substeps"] == COARSE and st["substeps"] == FINE
    assert st["coarse_importance"]["rounds"] >= 1 and res.fit.settings["substeps"] == COARSE
    runs = st["program_runs_by_substeps"]
    assert runs[str(COARSE)] > 0 and runs[str(FINE)] > 0
    assert res.ok, res.reason
    w = np.exp(res.importance.log_weights)
    i_mean = w @ res.importance.draws
    i_sd = np.sqrt(w @ (res.importance.draws - i_mean) ** 2)
    sd0 = np.sqrt(np.diag(res.importance.cov))
    f_mean, f_sd = _grid_moments(problem, i_mean, sd0)
    c_mean, _ = _grid_moments(_problem(tree, trajs, COARSE), i_mean, sd0)
    se = f_sd / math.sqrt(res.importance.ess)
    # the coarse step's posterior is measurably elsewhere: the test can tell the two apart
    assert np.max(np.abs(c_mean - f_mean) / se) > 8, (c_mean, f_mean, se)
    # the weighted draws are the accurate step's posterior (Monte-Carlo error)
    assert np.all(np.abs(i_mean - f_mean) < 5 * se + 1e-3 * f_sd), (i_mean, f_mean, se)
    np.testing.assert_allclose(i_sd, f_sd, rtol=0.15)
    assert np.all(np.abs(res.theta.mean(0) - f_mean) < 0.3 * f_sd)


def test_fast_posterior_option_checks(one_joint):
    tree, trajs, _ = one_joint
    problem = _problem(tree, trajs, FINE)
    for bad in ({"coarse_substeps": 0}, {"coarse_substeps": "fast"}, {"coarse_rounds": -1},
                {"polish_iterations": 1.5}):  # fmt: skip
        with pytest.raises(ConfigError):
            fast_posterior(problem, 16, n_starts=1, **bad)
