"""The inference front end on the built-in 2-branch tree (sim-to-sim).

Sizes are small so the file runs in a few minutes on a 2-core CPU; the shapes are shared
between tests so MJX compiles each program once.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from treeinfer.data.trajectories import Trajectory
from treeinfer.errors import ConfigError
from treeinfer.evaluation import metrics
from treeinfer.examples import example_path
from treeinfer.inference import samplers
from treeinfer.inference.problem import infer, make_problem, predict
from treeinfer.model.likelihood import gains_from_theta, theta_from_gains
from treeinfer.sim import make_simulator, simulate
from treeinfer.sim.program_cache import ProgramCache
from treeinfer.tree.description import load_tree

DT = 0.02
T = 50
KP_TRUE = np.array([40.0, 120.0])  # child, parent (N m/rad)
KD_TRUE = np.array([0.5, 1.5])  # child, parent (N m s/rad)
THETA_TRUE = theta_from_gains(KP_TRUE, KD_TRUE)


def _forces(peaks):
    t = np.arange(T) * DT
    return np.stack([np.clip(t / 0.5, 0.0, 1.0) * p for p in peaks])


@pytest.fixture(scope="module")
def setup():
    tree = load_tree(example_path("two_branch"))
    sim = make_simulator(tree, obs_dt=DT)
    forces = _forces([6.0, 10.0])
    r = jax.jit(lambda kp, kd, f: simulate(sim, kp, kd, f))(
        jnp.asarray(KP_TRUE[None]), jnp.asarray(KD_TRUE[None]), jnp.asarray(forces)
    )
    assert bool(np.asarray(r.stable).all())
    t = np.arange(T) * DT
    trajs = [
        Trajectory(t, forces[b], np.asarray(r.tau[0, b], float), None, f"train{b}")
        for b in range(2)
    ]
    problem = make_problem(tree, trajs, kT=0.05, sim=sim, likelihood="boltzmann")
    return tree, sim, trajs, problem


def test_truth_is_a_likelihood_maximum(setup):
    *_, problem = setup
    ll = np.asarray(
        jax.jit(problem.log_likelihood)(jnp.asarray(np.stack([THETA_TRUE, THETA_TRUE + 0.3])))
    )
    assert ll[0] > -0.5  # loss ~0 at the truth (float32 round-off only)
    assert ll[1] < ll[0] - 5.0


def test_one_simulator_call_per_gradient(setup, monkeypatch):
    """The FD gradient of all P particles and 2D perturbations is ONE batched simulate call."""
    tree, sim, trajs, _ = setup
    calls = []
    import treeinfer.model.boltzmann as lik  # where the Boltzmann likelihood calls simulate

    real = lik.simulate

    def counting(*args, **kwargs):
        calls.append(args[1].shape)
        return real(*args, **kwargs)

    monkeypatch.setattr(lik, "simulate", counting)
    problem = make_problem(tree, trajs, kT=0.05, sim=sim, likelihood="boltzmann")
    theta = jnp.tile(jnp.asarray(THETA_TRUE, jnp.float32), (5, 1))
    jax.make_jaxpr(problem.value_and_grad)(theta)
    assert len(calls) == 1
    assert calls[0] == (5 * (2 * 4 + 1), 2)  # P * (2D + 1) rows, R = 2 joints


def test_central_differences_match_mjx_autodiff(setup):
    """Black-box central differences agree with exact gradients through MJX (jax.grad)."""
    tree, sim, trajs, _ = setup
    short = [
        Trajectory(t.time[:25], t.force[:25], t.displacement[:25], None, t.source) for t in trajs
    ]
    fd = make_problem(
        tree,
        short,
        kT=0.05,
        sim=sim,
        nn_prior=False,
        gradient="fd",
        rel_step=1e-2,
        likelihood="boltzmann",
    )
    ad = make_problem(
        tree, short, kT=0.05, sim=sim, nn_prior=False, gradient="autodiff", likelihood="boltzmann"
    )
    theta = jnp.asarray(
        np.stack([THETA_TRUE + [0.2, -0.1, 0.1, -0.2], THETA_TRUE + [-0.3, 0.2, -0.2, 0.1]]),
        jnp.float32,
    )
    v_fd, g_fd = jax.jit(fd.value_and_grad)(theta)
    v_ad, g_ad = jax.jit(ad.value_and_grad)(theta)
    np.testing.assert_allclose(np.asarray(v_fd), np.asarray(v_ad), rtol=1e-5)
    g_fd, g_ad = np.asarray(g_fd), np.asarray(g_ad)
    # stated tolerance: 2% of the gradient's norm per particle
    err = np.linalg.norm(g_fd - g_ad, axis=1) / np.linalg.norm(g_ad, axis=1)
    assert np.all(err < 0.02), err


def test_nnsvgd_recovers_truth_and_covers_training_data(setup):
    tree, sim, trajs, problem = setup
    post = infer(
        problem,
        "nnsvgd",
        n_particles=16,
        n_iterations=80,
        seed=3,
        progress=False,
        learning_rate=0.1,
    )
    assert post.valid.all()
    check = metrics.posterior_vs_truth(post.theta, THETA_TRUE)
    assert check.in_joint is not False and bool(np.all(check.in_marginal)), check
    pred = predict(problem, post.theta, np.stack([t.force for t in trajs]))
    lo, hi, _ = metrics.predictive_interval(pred.tau, valid=np.asarray(pred.stable).all(1))
    gt = np.stack([t.displacement for t in trajs])
    outside = float(metrics.fraction_outside(lo, hi, jnp.asarray(gt)))
    assert outside < 0.05, outside
    # the particles respect the inequality prior mostly (parent at least as stiff as the child)
    kp, _ = gains_from_theta(post.theta, 2)
    assert np.mean(np.asarray(kp)[:, 1] >= np.asarray(kp)[:, 0]) > 0.8


def test_same_seed_same_particles(setup):
    """Same seed, same particles, with or without the caller's ProgramCache; with one, the runs
    of one problem share one algorithm object and its compiled sampler program."""
    *_, problem = setup
    programs = ProgramCache()
    kw = dict(n_particles=16, n_iterations=3, progress=False)
    a = infer(problem, "nnsvgd", seed=11, **kw)
    b = infer(problem, "nnsvgd", seed=11, cache=programs, **kw)
    c = infer(problem, "nnsvgd", seed=12, cache=programs, **kw)
    assert programs.builds == 2  # the algorithm and its compiled chunk: built once, used twice
    assert np.array_equal(a.theta, b.theta)
    assert not np.array_equal(a.theta, c.theta)
    assert a.settings["seed"] == 11 and a.settings["sampler"] == "nnsvgd"


def test_bad_arguments(setup):
    tree, sim, trajs, problem = setup
    with pytest.raises(ConfigError, match="kT"):
        make_problem(tree, trajs, kT=-1.0, sim=sim, likelihood="boltzmann")
    with pytest.raises(ConfigError, match="sampler"):
        infer(problem, "hmc", n_particles=4, n_iterations=1)
    with pytest.raises(ConfigError, match="n_particles"):
        infer(problem, "svgd", n_particles=0, n_iterations=1)
    with pytest.raises(ConfigError, match="ProgramCache"):
        infer(problem, "svgd", n_particles=4, n_iterations=1, cache={})
    with pytest.raises(ConfigError, match="grasp_fraction"):
        predict(problem, THETA_TRUE, trajs[0].force, grasp_fraction=1.5)
    with pytest.raises(ConfigError, match="columns"):
        predict(problem, THETA_TRUE[:3], trajs[0].force)
    with pytest.raises(ConfigError, match="positive"):
        theta_from_gains([-1.0, 2.0], [1.0, 1.0])
    assert samplers.REGISTRY.keys() >= {"nnsvgd", "svgd", "sgld", "sghmc", "mh"}
