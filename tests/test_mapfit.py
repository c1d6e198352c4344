"""The fast start (treeinfer.inference.mapfit): MAP by Levenberg–Marquardt and the Laplace
approximation.

References: closed-form posteriors of linear-Gaussian toys (where MAP and Laplace are exact),
the least-squares point of a sum-of-norms toy, and the known truth of a two-joint tree whose
data were made by the MuJoCo C reference (MAP within the Laplace std, the noise-limited error).
"""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from treeinfer.data.trajectories import Trajectory, read_trajectory_dir
from treeinfer.errors import ConfigError
from treeinfer.examples import example_path
from treeinfer.inference.mapfit import (
    ResidualModel,
    fit_map,
    fit_problem,
    laplace_particles,
    latin_hypercube,
    norm_loss_covariance,
    problem_with_gradients,
)
from treeinfer.inference.problem import make_problem
from treeinfer.sim import make_simulator
from treeinfer.sim.reference import simulate_reference
from treeinfer.tree.description import load_tree


def _linear_toy(seed=0, n=30, dim=3, sigma=0.2):
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(n, dim))
    truth = rng.normal(size=dim)
    y = a @ truth + sigma * rng.normal(size=n)
    return a, y, sigma


def _gaussian_prior(mean, cov):
    prec = np.linalg.inv(cov)

    def log_prior(theta):  # [P, D] -> [P]
        d = theta - jnp.asarray(mean, theta.dtype)
        return -0.5 * jnp.einsum("pd,de,pe->p", d, jnp.asarray(prec, theta.dtype), d)

    return log_prior


@pytest.mark.parametrize("jacobian", ["jvp", "fd"])
def test_linear_gaussian_map_and_laplace_are_exact(jacobian):
    a, y, sigma = _linear_toy()
    m0, s0 = np.array([0.5, -0.5, 0.0]), np.diag([0.5, 2.0, 1.0])
    prec = a.T @ a / sigma**2 + np.linalg.inv(s0)
    post_cov = np.linalg.inv(prec)
    post_mean = post_cov @ (a.T @ y / sigma**2 + np.linalg.solve(s0, m0))
    with jax.enable_x64(True):
        model = ResidualModel(
            lambda th: (((jnp.asarray(a) @ th - y) / sigma)[None], True), "gaussian"
        )
        fit = fit_map(
            model,
            _gaussian_prior(m0, s0),
            -3 * np.ones(3),
            3 * np.ones(3),
            n_starts=4,
            jacobian=jacobian,
        )
        draws = np.asarray(laplace_particles(jax.random.key(0), fit, 40000, box_precision=False))
    assert fit.converged.all()
    np.testing.assert_allclose(fit.theta, post_mean, atol=1e-7)
    np.testing.assert_allclose(fit.finals, np.tile(post_mean, (4, 1)), atol=1e-6)
    np.testing.assert_allclose(fit.cov, post_cov, rtol=1e-6 if jacobian == "jvp" else 1e-4)
    se = np.sqrt(np.diag(post_cov) / len(draws))
    assert np.all(np.abs(draws.mean(0) - post_mean) < 5 * se)
    np.testing.assert_allclose(np.cov(draws.T), post_cov, rtol=0.05, atol=0.02 * post_cov.max())


def test_unknown_sigma_map_is_the_closed_form():
    a, y, _ = _linear_toy(seed=1, n=50, sigma=0.3)
    beta = np.linalg.lstsq(a, y, rcond=None)[0]
    rss = float(np.sum((a @ beta - y) ** 2))
    with jax.enable_x64(True):
        model = ResidualModel(
            lambda th: ((jnp.asarray(a) @ th - y)[None], True),
            "gaussian_log_sigma",
            n_obs=len(y),
            log_sigma_guess=0.0,
        )
        fit = fit_map(model, None, -3 * np.ones(3), 3 * np.ones(3), n_starts=3)
    # flat priors on theta and log sigma: MAP at least squares with sigma^2 = RSS / N
    np.testing.assert_allclose(fit.theta[:3], beta, atol=1e-6)
    np.testing.assert_allclose(np.exp(fit.theta[3]), np.sqrt(rss / len(y)), rtol=1e-6)
    # Laplace variance of log sigma at the mode: 1 / (2N)
    assert fit.cov[3, 3] == pytest.approx(1.0 / (2 * len(y)), rel=1e-6)
    assert fit.n_model == 3 and fit.theta.shape == (4,)


def test_sum_of_norms_minimum_is_least_squares():
    a, y, _ = _linear_toy(seed=2)
    beta = np.linalg.lstsq(a, y, rcond=None)[0]
    with jax.enable_x64(True):
        model = ResidualModel(
            lambda th: ((jnp.asarray(a) @ th - y)[None], True), "norm", scale=0.05
        )
        fit = fit_map(model, None, -3 * np.ones(3), 3 * np.ones(3), n_starts=3)
    np.testing.assert_allclose(fit.theta, beta, atol=1e-6)
    assert np.all(np.linalg.eigvalsh(fit.hessian) > 0)


def test_norm_loss_covariance_against_quadrature():
    """One group, zero residual, D = 2: the covariance of exp(-||J d|| / kT), integrated on a
    grid, is (D + 1) kT^2 (J^T J)^-1; the variational fixed point is D kT^2 (J^T J)^-1."""
    jac = np.array([[2.0, 0.5], [0.3, 1.0], [0.0, 0.7]])
    kT = 0.3
    gram = jac.T @ jac
    grid = np.linspace(-6, 6, 1201)
    d = np.stack(np.meshgrid(grid, grid, indexing="ij"), -1).reshape(-1, 2)
    w = np.exp(-np.linalg.norm(d @ jac.T, axis=1) / kT)
    exact = (d * w[:, None]).T @ d / w.sum()
    np.testing.assert_allclose(exact, 3 * kT**2 * np.linalg.inv(gram), rtol=2e-3, atol=1e-5)
    cov = norm_loss_covariance(gram[None], np.zeros(1), kT)
    np.testing.assert_allclose(cov, 2 * kT**2 * np.linalg.inv(gram), rtol=1e-6)


def test_boltzmann_fit_draws_the_norm_matched_gaussian():
    """Sum-of-norms toy with residuals left at the mode: ``fit.norm_cov`` satisfies its fixed
    point, agrees with the Laplace ``H^-1`` where the loss is smooth, and ``laplace_particles``
    draws it."""
    a, y, _ = _linear_toy(seed=3)
    groups = [slice(0, 15), slice(15, 30)]
    kT = 0.05
    with jax.enable_x64(True):
        model = ResidualModel(
            lambda th: (jnp.stack([(jnp.asarray(a) @ th - y)[g] for g in groups]), True),
            "norm",
            scale=kT,
        )
        fit = fit_map(model, None, -3 * np.ones(3), 3 * np.ones(3), n_starts=3)
        draws = np.asarray(laplace_particles(jax.random.key(2), fit, 40000, box_precision=False))
        lap = np.asarray(
            laplace_particles(jax.random.key(2), fit, 4, box_precision=False, covariance="laplace")
        )
    gram = np.stack([a[g].T @ a[g] for g in groups])
    r2 = np.array([np.sum((a[g] @ fit.theta - y[g]) ** 2) for g in groups])
    s = np.sqrt(r2 + np.einsum("gde,ed->g", gram, fit.norm_cov))
    np.testing.assert_allclose(
        np.linalg.inv(fit.norm_cov), np.einsum("gde,g->de", gram, 1 / (kT * s)), rtol=1e-6
    )
    # residuals dominate here (the loss is smooth at the mode): matched Gaussian ~ Laplace
    assert abs(np.trace(fit.norm_cov) / np.trace(fit.cov) - 1) < 0.1
    np.testing.assert_allclose(np.cov(draws.T), fit.norm_cov, rtol=0.05, atol=1e-3 * s.max())
    assert lap.shape == (4, 3)
    with pytest.raises(ConfigError):
        laplace_particles(jax.random.key(0), fit, 4, covariance="bogus")


def test_lm_agree_stops_early_once_starts_agree():
    a, y, _ = _linear_toy(seed=4)
    with jax.enable_x64(True):
        model = ResidualModel(lambda th: ((jnp.asarray(a) @ th - y)[None], True), "gaussian")
        full = fit_map(model, None, -3 * np.ones(3), 3 * np.ones(3), n_starts=6, agree=None)
        early = fit_map(model, None, -3 * np.ones(3), 3 * np.ones(3), n_starts=6, agree=2)
    np.testing.assert_allclose(early.theta, full.theta, atol=1e-6)
    assert early.converged.sum() >= 2 and early.iterations <= full.iterations
    with pytest.raises(ConfigError):
        fit_map(model, None, -3 * np.ones(3), 3 * np.ones(3), agree=0)


def test_latin_hypercube_covers_every_stratum():
    pts = latin_hypercube(10, [0.0, -1.0], [1.0, 1.0], seed=3)
    assert pts.shape == (10, 2)
    strata = np.floor((pts - [0.0, -1.0]) / ([1.0, 2.0]) * 10).astype(int)
    assert all(sorted(strata[:, d]) == list(range(10)) for d in range(2))


def test_bad_options_are_refused():
    model = ResidualModel(lambda th: (th[None], True), "gaussian")
    with pytest.raises(ConfigError, match="jacobian"):
        fit_map(model, None, [0.0], [1.0], jacobian="bfgs")
    with pytest.raises(ConfigError, match="upper > lower"):
        fit_map(model, None, [1.0], [0.0])
    with pytest.raises(ConfigError, match="kind"):
        fit_map(model._replace(kind="cauchy"), None, [0.0], [1.0])


def _two_joint_problem(noise, n_steps=80):
    tree = load_tree(example_path("two_branch"))
    sim = make_simulator(tree, obs_dt=0.01)
    kp, kd = np.array([60.0, 25.0]), np.array([0.8, 0.3])
    t = np.arange(n_steps) * 0.01
    rng = np.random.default_rng(5)
    trajs = []
    for i, peak in enumerate((8.0, 4.0, 6.0)):
        f = peak * np.clip(t / (0.1 + 0.15 * i), 0.0, 1.0) * (t < 0.5 + 0.1 * i)
        tau, _ = simulate_reference(sim, kp, kd, f)
        tau = tau + noise * rng.normal(size=tau.shape)
        trajs.append(Trajectory(t, f, tau, None, f"p{i}"))
    problem = make_problem(tree, trajs, sim=sim, nn_prior=False, likelihood="boltzmann")
    return problem, np.log(np.concatenate([kp, kd]))


def test_two_joint_tree_map_recovers_truth_within_noise_limited_error():
    sigma = 1e-3
    problem, truth = _two_joint_problem(sigma)
    fit = fit_problem(problem, "gaussian", sigma=sigma, n_starts=4, seed=0)
    std = np.sqrt(np.diag(fit.cov))
    assert fit.converged.any()
    # the Laplace std is the Cramer-Rao bound here: the MAP lies within 4 of them of the truth
    assert np.all(np.abs(fit.theta - truth) < 4 * std), (fit.theta, truth, std)
    assert np.all(std < 0.5)  # and the data do identify every gain (the box is ~4.6 wide)
    # particles start around it, inside the region the sampler needs
    parts = np.asarray(laplace_particles(jax.random.key(1), fit, 64))
    assert parts.shape == (64, 4) and np.all(np.isfinite(parts))
    assert np.all(np.abs(np.median(parts, 0) - fit.theta) < 0.5 * std + 1e-3)


def test_two_joint_tree_boltzmann_map_and_jvp_problem():
    problem, truth = _two_joint_problem(0.0, n_steps=60)
    fit = fit_problem(problem, "boltzmann", n_starts=3, seed=1, jacobian="fd")
    # noise-free data: the loss vanishes at the truth, up to the simulators' float32 agreement
    assert np.all(np.abs(fit.theta - truth) < 0.05), (fit.theta, truth)
    jp = problem_with_gradients(problem, "jvp")
    assert jp.settings["gradient"] == "jvp" and problem.settings["gradient"] == "fd"
    # at the MAP both programs see residuals of float32 round-off: the loss nearly vanishes
    # (0.01 nats = 0.5 mm of summed residual norms at kT 0.05), and its gradient is that of
    # |r| at r ~ 0, the norm's kink, where FD and forward-mode slopes have no common value
    # (with the accuracy-controlled default step, 53 substeps here, they differed by 40 nats
    # per log unit on one column). So the programs' values and gradients are compared off the
    # kink: a step from the MAP and a point 0.2 from the truth.
    v_map = jax.jit(jp.log_density)(jnp.asarray(fit.theta, jnp.float32)[None])
    v_map_fd = jax.jit(problem.log_density)(jnp.asarray(fit.theta, jnp.float32)[None])
    assert float(v_map[0]) > -0.01 and float(v_map_fd[0]) > -0.01, (v_map, v_map_fd)
    off = np.array([0.05, -0.05, 0.05, -0.05])
    theta = jnp.asarray(np.stack([fit.theta + off, truth + 0.2]), jnp.float32)
    v, g = jax.jit(jp.value_and_grad)(theta)
    v_fd, g_fd = jax.jit(problem.value_and_grad)(theta)
    np.testing.assert_allclose(v, v_fd, rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(g, g_fd, rtol=0.05, atol=0.05 * np.abs(np.asarray(g_fd)).max())


def _laplace_cli_data(tmp_path):
    """(tree file, folder of two noise-free pulls of the 2-branch example at 0.02 s)."""
    from treeinfer.data.trajectories import write_trajectory

    tree_file = example_path("two_branch")
    sim = make_simulator(load_tree(tree_file), obs_dt=0.02)
    t = np.arange(40) * 0.02
    data = tmp_path / "data"
    data.mkdir()
    for i, peak in enumerate((6.0, 3.0)):
        f = peak * np.clip(t / 0.3, 0.0, 1.0)
        tau, tau_dot = simulate_reference(sim, [60.0, 25.0], [0.8, 0.3], f)
        write_trajectory(data / f"p{i}.csv", Trajectory(t, f, tau, tau_dot, f"p{i}"))
    return tree_file, data


# A whole CLI inference: under -m slow. The default run keeps what it checks: test_cli_infer's
# run folder is an `infer --init laplace` from the CLI (its "Laplace start" line, init recorded,
# the default gradient recorded in the problem and not in the options), and
# test_gradient_choice_reaches_the_problem_and_bad_names_are_refused below.
@pytest.mark.slow
def test_cli_infer_with_laplace_init_and_gradient_choice_recorded(tmp_path, capsys):
    from treeinfer.cli import main

    tree_file, data = _laplace_cli_data(tmp_path)
    out = tmp_path / "run"
    rc = main(
        [
            "infer",
            "--tree",
            str(tree_file),
            "--data",
            str(data),
            "--out",
            str(out),
            "--particles",
            "4",
            "--iterations",
            "2",
            "--checkpoint-every",
            "0",
            "--no-progress",
            "--init",
            "laplace",
        ]
    )
    err = capsys.readouterr().err
    assert rc == 0, err
    assert "Laplace start" in err
    config = json.loads((out / "config.json").read_text())
    assert config["options"]["init"] == "laplace" and "gradients" not in config["options"]
    assert config["problem"]["gradient"] == "fd"


def test_gradient_choice_reaches_the_problem_and_bad_names_are_refused(tmp_path, capsys):
    from treeinfer.cli import main
    from treeinfer.runs import infer_config
    from treeinfer.runs.service import build_problem

    tree_file, data = _laplace_cli_data(tmp_path)
    tree = load_tree(tree_file)
    # --gradients jvp reaches the problem (and is recorded); the defaults stay out of the options
    cfg = infer_config(
        tree_file,
        data,
        tmp_path / "other",
        sampler="svgd",
        particles=4,
        iterations=2,
        kT=0.05,
        seed=0,
        eta=10.0,
        grasp_fraction=None,
        max_unstable_share=0.5,
        checkpoint_every=0,
        gradients="jvp",
    )
    assert cfg["options"]["gradients"] == "jvp" and "init" not in cfg["options"]
    problem = build_problem(cfg, tree, read_trajectory_dir(data))
    assert problem.settings["gradient"] == "jvp"
    rc = main(
        [
            "infer",
            "--tree",
            str(tree_file),
            "--data",
            str(data),
            "--out",
            str(tmp_path / "run"),
            "--gradients",
            "adjoint",
        ]
    )
    assert rc == 2 and "--gradients" in capsys.readouterr().err


def test_lm_core_is_exact_on_least_squares_and_batches_data_sets_independently():
    """treeinfer.inference.lm.levenberg_marquardt (the loop of fit_map and
    batch_posteriors.map_fits): on ``||A theta - y||^2 / 2`` it reaches the least-squares point
    (numpy.linalg.lstsq); two data sets stacked as one batch of points give, point for point, what
    each gives alone (as map_fits runs many data sets' starts together); extras follow the accepted
    points."""
    from treeinfer.inference.lm import levenberg_marquardt

    sets = [_linear_toy(seed=s)[:2] for s in (0, 1)]

    def evaluate_for(rows):  # rows: the data set of each point
        def evaluate(theta):
            r = np.stack([sets[k][0] @ t - sets[k][1] for k, t in zip(rows, theta)])
            a = np.stack([sets[k][0] for k in rows])
            g = np.einsum("pnd,pn->pd", a, r)
            return 0.5 * np.sum(r**2, 1), g, np.einsum("pnd,pne->pde", a, a), np.sum(r**2, 1)

        return evaluate

    starts = latin_hypercube(3, -3 * np.ones(3), 3 * np.ones(3), seed=4)
    kw = dict(max_iterations=60, tolerance=1e-10, max_step=1.0, n_extras=1)
    both = levenberg_marquardt(evaluate_for([0] * 3 + [1] * 3), np.vstack([starts, starts]), **kw)
    for k, (a, y) in enumerate(sets):
        alone = levenberg_marquardt(evaluate_for([k] * 3), starts, **kw)
        part = slice(3 * k, 3 * k + 3)
        np.testing.assert_array_equal(both.theta[part], alone.theta)
        np.testing.assert_array_equal(both.values[part], alone.values)
        exact = np.linalg.lstsq(a, y, rcond=None)[0]
        np.testing.assert_allclose(alone.theta, np.tile(exact, (3, 1)), atol=1e-6)
        assert alone.converged.all()
        np.testing.assert_allclose(alone.extras[0], 2 * alone.values, rtol=1e-12)
    with pytest.raises(ConfigError, match="extra"):
        levenberg_marquardt(evaluate_for([0] * 3), starts, 5, 1e-6, 1.0, n_extras=0)
