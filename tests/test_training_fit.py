"""The run's training fit on the start pipeline's compiled rollout program
(:func:`treeinfer.evaluation.training_fit._training_fit` with ``evaluator``): the same particles'
predictions, bands and metrics as the prediction program's (the reference: ``predict``, the
simulator's own step), to float32 rounding; nothing compiled for it; the prediction program
where the residual program cannot stand in (unobserved points, no held program)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from treeinfer.data.trajectories import Trajectory, stack_trajectories
from treeinfer.evaluation.training_fit import _held_rollout, _training_fit
from treeinfer.examples import example_path
from treeinfer.inference import rollout as rollout_module
from treeinfer.inference.fast_evaluator import BatchEvaluator, held_evaluator
from treeinfer.inference.problem import make_problem
from treeinfer.sim import make_simulator
from treeinfer.sim.program_cache import ProgramCache
from treeinfer.tree.description import load_tree

CONFIG = {"options": {"grasp_fraction": None}}


def _trajectories(lengths, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for i, n in enumerate(lengths):
        t = np.arange(n) * 0.01
        f = (4.0 + i) * np.clip(t / 0.15, 0, 1)
        x = 0.01 * f / 5.0 + 1e-3 * rng.normal(size=n)
        out.append(Trajectory(t, f, x, None, f"p{i}"))
    return out


@pytest.fixture(scope="module")
def setup():
    tree = load_tree(example_path("two_branch"))
    sim = make_simulator(tree, obs_dt=0.01, substeps=4)
    obs = stack_trajectories(_trajectories((50, 50, 50)))
    problem = make_problem(tree, obs, sim=sim, nn_prior=False, kT=0.05, likelihood="gaussian")
    rng = np.random.default_rng(3)
    theta = np.log([60.0, 25.0, 0.8, 0.3, 2e-3]) + 0.2 * rng.normal(size=(24, 5))
    theta[5, 0] = 40.0  # Kp = e^40: an unstable rollout, left out of the bands
    post = SimpleNamespace(theta=theta, log_density=np.zeros(len(theta)))
    return tree, sim, problem, post


def test_held_evaluator_builds_nothing_and_finds_the_start_pipelines_program(setup):
    _, _, problem, _ = setup
    programs = ProgramCache()
    assert held_evaluator(problem, programs, 8) is None  # nothing held: nothing traced
    assert len(programs) == 0 and programs.builds == 0
    assert held_evaluator(problem, None, 8) is None
    BatchEvaluator(problem, 8, programs)  # the start pipeline's
    built = programs.builds  # its rollout program and the cache of its small programs
    ev = held_evaluator(problem, programs, 8)
    assert ev is not None and programs.builds == built  # found, not built again
    assert held_evaluator(problem, programs, 16) is None  # another batch: another program


def test_training_fit_on_the_held_program_equals_the_prediction(setup, monkeypatch):
    _, _, problem, post = setup
    want = _training_fit(problem, post, CONFIG)
    programs = ProgramCache()
    BatchEvaluator(problem, 8, programs)
    ev = held_evaluator(problem, programs, 8)

    def no_prediction(*a, **k):
        raise AssertionError("the training fit compiled a prediction of its own")

    monkeypatch.setattr(rollout_module, "predict", no_prediction)
    got = _training_fit(problem, post, CONFIG, ev)
    assert ev.calls == 3  # 24 particles in batches of 8
    pw, pg = want["prediction"], got["prediction"]
    assert pg.tau.shape == pw.tau.shape == (24, 3, 50) and pg.tau.dtype == pw.tau.dtype
    np.testing.assert_array_equal(got["stable"], want["stable"])
    assert not got["stable"][5] and got["stable"].sum() == 23
    for name in ("tau", "tau_dot", "lower", "upper", "mean", "predictive_lower"):
        w, g = getattr(pw, name), getattr(pg, name)
        scale = float(np.max(np.abs(w)))
        # the traced-step program against the static one: float32 rounding of the same loop
        np.testing.assert_allclose(g, w, atol=2e-5 * scale, err_msg=name)
    np.testing.assert_array_equal(pg.tau[5], 0.0)  # unstable: zeros, as a Rollout has them
    mw, mg = want["metrics"], got["metrics"]
    assert mg["n_points"] == mw["n_points"] and mg["n_particles"] == mw["n_particles"]
    for key in ("ci_width", "pct_outside", "predictive_nll", "posterior_nll"):
        np.testing.assert_allclose(mg[key], mw[key], rtol=1e-5, err_msg=key)


def test_unobserved_points_or_another_grasp_point_take_the_prediction(setup):
    tree, sim, problem, post = setup
    programs = ProgramCache()
    BatchEvaluator(problem, 8, programs)
    ev = held_evaluator(problem, programs, 8)
    assert _held_rollout(ev, problem, problem.obs, None, post.theta) is not None
    assert _held_rollout(ev, problem, problem.obs, 0.5, post.theta) is None  # another point
    assert _held_rollout(None, problem, problem.obs, None, post.theta) is None
    ragged = stack_trajectories(_trajectories((50, 47, 44)))  # padded steps: mask False
    other = make_problem(tree, ragged, sim=sim, nn_prior=False, kT=0.05, likelihood="gaussian")
    BatchEvaluator(other, 8, programs)
    ev2 = held_evaluator(other, programs, 8)
    assert ev2 is not None
    assert _held_rollout(ev2, other, other.obs, None, post.theta) is None
