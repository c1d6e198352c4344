"""The dynamic model with each trajectory's own grasped branch and pull direction: the problem's
likelihood against MuJoCo C rollouts and scipy densities, and recovery of the truth."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats

from treeinfer.data import forces as F
from treeinfer.data.direction import pull_direction
from treeinfer.data.trajectories import Trajectory, stack_trajectories
from treeinfer.examples import example_path
from treeinfer.inference.problem import make_problem, predict
from treeinfer.inference.static import model_for
from treeinfer.sim import make_simulator
from treeinfer.sim.reference import simulate_reference
from treeinfer.tree.description import load_tree

DT = 0.02
KP, KD = np.array([40.0, 15.0]), np.array([0.6, 0.2])
SIGMA = 0.002  # m


@pytest.fixture(scope="module")
def case():
    """Two-branch example: a downward pull at the child's tip, a sideways push (in the
    hinges' plane) at the child's middle, and a diagonal push on the parent; simulated by
    MuJoCo C (an independent integrator) with 2 mm Gaussian noise."""
    tree = load_tree(example_path("two_branch"))
    sim = make_simulator(tree, obs_dt=DT, substeps=8)
    forces = np.stack(
        [
            F.ramp_hold(3.0, 0.3, 0.3, 0.2, 1.0, DT),
            F.ramp_hold(4.0, 0.3, 0.3, 0.2, 1.0, DT),
            F.ramp_hold(6.0, 0.3, 0.3, 0.2, 1.0, DT),
        ]
    )
    branches = ("child", "child", "parent")
    fractions = np.array([0.9, 0.5, 0.8])
    dirs = np.stack(
        [
            pull_direction(tree, "down"),
            pull_direction(tree, [1.0, 0.3, 0.0]),
            pull_direction(tree, [1.0, 0.0, -1.0]),
        ]
    )
    rng = np.random.default_rng(3)
    trajs, clean = [], []
    for b in range(3):
        tau, _ = simulate_reference(
            sim, KP, KD, forces[b], fractions[b], direction=dirs[b], grasp_branch=branches[b]
        )
        clean.append(tau)
        x = tau + SIGMA * rng.standard_normal(tau.shape)
        t = np.arange(len(x)) * DT
        trajs.append(Trajectory(t, forces[b], x, np.gradient(x, DT), f"pull_{b}.csv"))
    return tree, sim, trajs, branches, fractions, dirs, np.asarray(clean)


def test_problem_likelihood_is_the_per_pull_reference(case):
    """log p(D | truth) of the problem equals scipy's Gaussian density of the residuals of the
    model's rollout, and that rollout equals MuJoCo C's per pull (branch, point, direction)."""
    tree, sim, trajs, branches, fractions, dirs, clean = case
    problem = make_problem(
        tree,
        trajs,
        nn_prior=False,
        sim=sim,
        likelihood="gaussian",
        noise_displacement=SIGMA,
        grasp_fraction=fractions,
        direction=dirs,
        grasp_branch=branches,
    )
    assert problem.model is not None and problem.model.kind == "dynamic"
    assert problem.settings["pulls"]["grasp_branch"] == list(branches)
    theta = np.log(np.concatenate([KP, KD]))[None]
    tau = np.asarray(predict(problem, theta, problem.obs.force, fractions).tau[0])
    assert np.max(np.abs(clean)) > 5e-3
    np.testing.assert_allclose(tau, clean, atol=2e-4)
    obs = stack_trajectories(trajs)
    expected = scipy.stats.norm.logpdf(obs.displacement - tau, scale=SIGMA)[obs.mask].sum()
    got = float(np.asarray(problem.log_likelihood(jnp.asarray(theta)))[0])
    assert got == pytest.approx(expected, rel=1e-4)
    # the same data read as the paper's model (every pull down at the child's tip) fit worse
    paper = make_problem(
        tree, trajs, nn_prior=False, sim=sim, likelihood="gaussian", noise_displacement=SIGMA
    )
    assert paper.model is None
    assert float(np.asarray(paper.log_likelihood(jnp.asarray(theta)))[0]) < got - 100


def test_dynamic_model_recovers_the_truth_from_mixed_pulls(case):
    """The joint fit of all pulls peaks at the true stiffnesses: on a 2-D grid of (Kp parent,
    Kp child) (damping and noise at their truth) the posterior's maximum is the grid point
    nearest the truth, while reading the same data as the paper's pulls (down at the child's
    tip) puts it elsewhere."""
    tree, sim, trajs, branches, fractions, dirs, _ = case
    kw = dict(nn_prior=False, sim=sim, likelihood="gaussian", noise_displacement=SIGMA)
    own = make_problem(
        tree, trajs, grasp_fraction=fractions, direction=dirs, grasp_branch=branches, **kw
    )
    paper = make_problem(tree, trajs, **kw)
    steps = np.linspace(-0.4, 0.4, 9)  # log units around the truth, 0.1 apart
    a, b = np.meshgrid(steps, steps, indexing="ij")
    grid = np.tile(np.log(np.concatenate([KP, KD])), (a.size, 1))
    grid[:, 0] += a.ravel()
    grid[:, 1] += b.ravel()
    for problem, hits in ((own, True), (paper, False)):
        logp = np.asarray(problem.log_density(jnp.asarray(grid)))
        best = grid[int(np.argmax(logp)), :2]
        assert np.allclose(best, np.log(KP), atol=1e-6) == hits, np.exp(best)


def test_model_for_reads_the_tree_pull_direction():
    """A tree file's pull: {direction: ...} is honoured by the dynamic model too; 'down' keeps
    the paper's model (None in problems)."""
    import dataclasses

    tree = load_tree(example_path("two_branch"))
    assert model_for(tree, "dynamic").is_paper
    side = dataclasses.replace(tree, pull_direction=(1.0, 0.0, 0.0))
    m = model_for(side, "dynamic")
    assert not m.is_paper
    np.testing.assert_allclose(m.direction, [1.0, 0.0, 0.0])
