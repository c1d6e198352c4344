"""Generative likelihoods (gaussian, student_t, ar1; sigma_x given or inferred) with the static
model and with stiffness-only runs, each against an independent computation."""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats
from scipy.optimize import brentq

from treeinfer.data.trajectories import Trajectory
from treeinfer.inference.problem import infer, make_problem
from treeinfer.model.likelihood import measurement_log_likelihood
from treeinfer.sim import make_simulator
from treeinfer.tree.description import Bounds, Branch, make_tree

G = 9.81
KP, A, SIGMA = 40.0, 0.6, 0.004  # N m/rad, grasp distance m, noise m


def _horizontal_branch():
    return make_tree(
        [Branch("b", None, 0.8, 0.02)],
        grasp_branch="b",
        grasp_fraction=A / 0.8,
        bounds=Bounds(kp=(5.0, 500.0), kd=(0.05, 10.0)),
    )


@pytest.fixture(scope="module")
def static_case():
    """A horizontal one-joint branch pulled down at A under slow forces, its exact equilibrium
    ``Kp psi = (m g c + F A) cos psi`` solved by scipy's brentq (independent of treeinfer's
    Newton solver), with Gaussian noise."""
    tree = _horizontal_branch()
    sim = make_simulator(tree, obs_dt=0.5, backend="fused")
    m = float(sim.mj_model.body_mass[1])
    c = float(sim.mj_model.body_ipos[1][0])
    forces = np.linspace(0.0, 6.0, 41)

    def tau(kp):
        def psi(f):
            return brentq(lambda p: kp * p - (m * G * c + f * A) * math.cos(p), -1.5, 1.5)

        p0 = psi(0.0)
        return np.array([A * (math.sin(psi(f)) - math.sin(p0)) for f in forces])

    x = tau(KP) + SIGMA * np.random.default_rng(0).standard_normal(len(forces))
    t = 0.5 * np.arange(len(forces))
    traj = Trajectory(t, forces, x, np.gradient(x, 0.5), "push.csv")
    return tree, sim, traj, tau


def test_static_gaussian_posterior_matches_quadrature(static_case):
    """Static model, Gaussian noise of known sigma: the log-likelihood equals scipy's density
    of the residuals to the brentq equilibria, and MH's posterior mean and std of log Kp match
    a quadrature of likelihood x flat (log-uniform, far from the box edges) prior."""
    tree, sim, traj, tau = static_case
    problem = make_problem(
        tree,
        [traj],
        nn_prior=False,
        sim=sim,
        model_kind="static",
        likelihood="gaussian",
        noise_displacement=SIGMA,
    )
    assert problem.labels == ("Kp[b]",)
    grid = np.log(KP) + np.linspace(-0.3, 0.3, 241)
    ref = np.array(
        [
            scipy.stats.norm.logpdf(traj.displacement - tau(math.exp(g)), scale=SIGMA).sum()
            for g in grid
        ]
    )
    got = np.asarray(problem.log_likelihood(jnp.asarray(grid[:, None])), float)
    np.testing.assert_allclose(got[::40], ref[::40], rtol=1e-4, atol=1e-3)
    w = np.exp(ref - ref.max())
    w /= w.sum()
    mean = float(w @ grid)
    std = float(np.sqrt(w @ (grid - mean) ** 2))
    assert 0.01 < std < 0.05  # a proper, narrow posterior well inside the grid
    # chains started dispersed (5x the posterior std) around an off-centre point
    start = mean + 0.1 + 5 * std * np.random.default_rng(1).standard_normal((128, 1))
    post = infer(
        problem,
        "mh",
        n_particles=128,
        n_iterations=200,
        seed=1,
        progress=False,
        initial_theta=start,
        proposal_scale=0.01,
    )
    th = post.theta[:, 0]
    assert float(th.mean()) == pytest.approx(mean, abs=0.2 * std)
    assert float(th.std()) == pytest.approx(std, rel=0.15)


def test_static_student_t_with_inferred_sigma(static_case):
    """Student-t with sigma_x inferred: theta = [log Kp, log sigma_x]; the likelihood is
    scipy's t density (df 4 unless changed) and the sigma prior flat in log sigma_x over
    [resolution, data range] (issue 27), so two points inside it have the same prior."""
    from treeinfer.model import noise

    tree, sim, traj, tau = static_case
    problem = make_problem(
        tree, [traj], nn_prior=False, sim=sim, model_kind="static", likelihood="student_t"
    )
    assert problem.labels == ("Kp[b]", "sigma_x")
    theta = np.array([[np.log(KP), np.log(0.003)], [np.log(50.0), np.log(0.01)]])
    got = np.asarray(problem.log_likelihood(jnp.asarray(theta)), float)
    df = noise.DEFAULT_STUDENT_T_DF
    for row, g in zip(theta, got):
        r = traj.displacement - tau(math.exp(row[0]))
        want = scipy.stats.t.logpdf(r, df, scale=math.exp(row[1])).sum()
        assert g == pytest.approx(want, rel=1e-4)
    lp = np.asarray(problem.log_prior(jnp.asarray(theta)), float)
    lo, hi = problem.lower[1], problem.upper[1]
    assert lo < theta[:, 1].min() and theta[:, 1].max() < hi
    assert math.exp(hi) == pytest.approx(np.ptp(traj.displacement))  # the data's range
    assert lp[0] == pytest.approx(lp[1], abs=1e-6)  # same box value for Kp, flat in sigma


@pytest.mark.parametrize("kind", ["gaussian", "ar1"])
def test_stiffness_only_generative_equals_the_full_model_at_fixed_damping(kind):
    """inference: {parameters: [kp]} with a generative likelihood: theta = [log Kp, noise
    columns]; its log-likelihood is the full [log Kp, log Kd] model's (treeinfer.model.likelihood,
    the paper's layout) at the tree's own Kd."""
    tree = dataclasses.replace(
        make_tree([Branch("b", None, 0.5, 0.01, kd=0.3)], grasp_branch="b", grasp_fraction=1.0),
        parameters=("kp",),
    )
    dt, n = 0.02, 25
    t = dt * np.arange(n)
    force = np.clip(t / 0.2, 0, 1) * 2.0
    x = 0.01 * np.clip(t / 0.2, 0, 1) + 1e-3 * np.sin(37 * t)
    traj = Trajectory(t, force, x, np.gradient(x, dt), "syn.csv")
    problem = make_problem(tree, [traj], nn_prior=False, backend="fused", likelihood=kind)
    noise_cols = ("sigma_x",) if kind == "gaussian" else ("sigma_x", "sigma_c", "rho")
    assert problem.labels == ("Kp[b]",) + noise_cols
    full = measurement_log_likelihood(problem.sim, problem.obs, kind, black_box=False)
    extra = [np.log(0.002)] + ([np.log(0.001), 1.0] if kind == "ar1" else [])
    theta = np.array([[np.log(5.0)] + extra, [np.log(20.0)] + extra])
    got = np.asarray(problem.log_likelihood(jnp.asarray(theta)))
    kd = np.log(0.3) * np.ones((2, 1))
    want = np.asarray(full(jnp.asarray(np.concatenate([theta[:, :1], kd, theta[:, 1:]], axis=1))))
    np.testing.assert_allclose(got, want, rtol=1e-5)
    assert got[0] != pytest.approx(got[1])
    if kind == "gaussian":  # value_and_grad: central-difference JVP through the simulator
        _, g = problem.value_and_grad(jnp.asarray(theta))
        assert np.all(np.isfinite(np.asarray(g)))


def test_tied_layout_is_the_free_model_at_scaled_stiffness(static_case):
    """One stiffness scale (Kp = s * shape): the problem's log-likelihood at [log s, log sigma]
    equals the free-stiffness problem's at [log(s * shape), log sigma]; the box is the scale's."""
    from treeinfer.inference.static import model_for, tied_layout

    tree, sim, traj, _ = static_case
    model = model_for(tree, "static")
    tied = model._replace(layout=tied_layout(tree, [2.0], (1.0, 300.0)))
    kw = dict(nn_prior=False, sim=sim, likelihood="gaussian")
    p_tied = make_problem(tree, [traj], model=tied, **kw)
    p_free = make_problem(tree, [traj], model_kind="static", **kw)
    assert p_tied.labels == ("Kp_scale", "sigma_x")
    assert p_tied.settings["kp_shape"] == [2.0]
    np.testing.assert_allclose(p_tied.lower[0], np.log(1.0))
    s = np.array([10.0, 25.0])
    sig = np.log([0.004, 0.006])
    got = np.asarray(p_tied.log_likelihood(jnp.asarray(np.stack([np.log(s), sig], 1))))
    want = np.asarray(p_free.log_likelihood(jnp.asarray(np.stack([np.log(2 * s), sig], 1))))
    np.testing.assert_allclose(got, want, rtol=1e-5)


def test_exact_laplace_of_a_static_model_matches_an_independent_fit(static_case):
    """:func:`treeinfer.inference.static.exact_laplace` (autodiff through the equilibrium): MAP and
    covariance of [log Kp, log sigma_x] against a fit of the same posterior built from brentq
    equilibria and scipy densities (flat in log Kp inside the box, the problem's recorded
    Normal prior on log sigma_x), its Hessian by central differences in float64."""
    from scipy.optimize import minimize

    from treeinfer.inference.static import exact_laplace

    tree, sim, traj, tau = static_case
    problem = make_problem(
        tree,
        [traj],
        nn_prior=False,
        sim=sim,
        model_kind="static",
        likelihood="gaussian",
        gradient="autodiff",
    )
    assert problem.labels == ("Kp[b]", "sigma_x")
    lo_s, hi_s = problem.lower[1], problem.upper[1]

    def logp(th):  # the sigma prior is flat in log sigma inside [lo_s, hi_s] (issue 27)
        lk, ls = th
        assert lo_s < ls < hi_s
        lik = scipy.stats.norm.logpdf(traj.displacement - tau(math.exp(lk)), scale=math.exp(ls))
        return lik.sum()

    ref = minimize(
        lambda th: -logp(th),
        [math.log(KP), math.log(SIGMA)],
        method="Nelder-Mead",
        options={"xatol": 1e-7, "fatol": 1e-9, "maxiter": 4000},
    ).x
    h = np.array([2e-3, 2e-2])
    hess = np.zeros((2, 2))
    for i in range(2):
        for j in range(2):
            ei, ej = h[i] * np.eye(2)[i], h[j] * np.eye(2)[j]
            hess[i, j] = (
                logp(ref + ei + ej)
                - logp(ref + ei - ej)
                - logp(ref - ei + ej)
                + logp(ref - ei - ej)
            ) / (4 * h[i] * h[j])
    cov_ref = np.linalg.inv(-hess)
    lap = exact_laplace(problem, n_starts=16, n_local=1)
    sd = np.sqrt(np.diag(cov_ref))
    np.testing.assert_allclose(lap.theta, ref, atol=0.05 * sd.min())
    np.testing.assert_allclose(np.sqrt(np.diag(lap.cov)), sd, rtol=0.03)
    corr = lambda c: c[0, 1] / np.sqrt(c[0, 0] * c[1, 1])  # noqa: E731
    assert corr(lap.cov) == pytest.approx(corr(cov_ref), abs=0.03)


def test_init_laplace_of_a_static_run_with_exact_gradients_uses_the_exact_fit(static_case):
    """``infer --model-kind static --gradients jvp --init laplace``: the run layer's start is
    :func:`treeinfer.inference.static.exact_laplace` (its particles centre on that MAP and say
    so)."""
    from treeinfer.inference.static import exact_laplace
    from treeinfer.runs.start import _model_laplace_start

    tree, sim, traj, _ = static_case
    problem = make_problem(
        tree, [traj], nn_prior=False, sim=sim, model_kind="static", likelihood="gaussian",
        gradient="autodiff",
    )  # fmt: skip
    said = []
    theta0 = _model_laplace_start(problem, {"seed": 0, "particles": 400, "gradients": "jvp"},
                                  said.append)  # fmt: skip
    assert "exact derivatives" in said[0]
    lap = exact_laplace(problem, seed=0)
    sd = np.sqrt(np.diag(lap.cov))
    assert np.all(np.abs(np.mean(np.asarray(theta0), axis=0) - lap.theta) < 0.3 * sd)
    generic = []
    _model_laplace_start(problem, {"seed": 0, "particles": 8, "gradients": "fd"}, generic.append)
    assert "generic fit" in generic[0]
