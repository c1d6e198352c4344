"""Programs that now run at the shape bucket (issue 15 item 4): same values as at the data's own
shape, and one program for data sets of one bucket (and, with the step traced, of any step)."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import jax.numpy as jnp
import numpy as np
import pytest

from treeinfer.data.trajectories import Trajectory, stack_trajectories
from treeinfer.evaluation.training_fit import _training_fit
from treeinfer.examples import example_path
from treeinfer.inference.problem import _predict_traced, make_problem, predict
from treeinfer.sim import accuracy, make_simulator
from treeinfer.sim.startup import bucket_observations
from treeinfer.tree.description import load_tree


@pytest.fixture(scope="module")
def tree():
    return load_tree(example_path("two_branch"))


def _forces(n_rows: int, n_steps: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.arange(n_steps) * 0.01
    peak = rng.uniform(3.0, 7.0, size=(n_rows, 1))
    return peak * np.clip(t / 0.2, 0, 1) * (t < 0.45)


def _identity(forces, frac, dirs, gb):
    return forces, frac, dirs, gb


def test_step_check_pads_to_the_bucket_and_chooses_as_before(tree, monkeypatch):
    sim = make_simulator(tree, obs_dt=0.01)
    f = _forces(3, 57)
    padded, *_ = accuracy._bucketed(f, None, None, None)
    assert padded.shape == (3, 64)
    np.testing.assert_array_equal(padded[:, :57], f)
    np.testing.assert_array_equal(padded[:, 57:], np.repeat(f[:, -1:], 7, axis=1))
    got = accuracy.choose_substeps_for_accuracy(sim, f, tol=2e-4)
    monkeypatch.setattr(accuracy, "_bucketed", _identity)  # the data's own shape, as before
    want = accuracy.choose_substeps_for_accuracy(sim, f, tol=2e-4)
    assert got == want  # the same step and the same estimate, to the last bit


def test_step_check_pads_per_profile_inputs_with_their_rows(tree):
    sim = make_simulator(tree, obs_dt=0.01)
    f = _forces(5, 40, seed=1)  # 5 rows -> 6, 40 steps -> 64
    frac = jnp.asarray([0.5, 0.6, 0.7, 0.8, 0.9])
    dirs = jnp.asarray(np.tile([0.0, 0.0, -1.0], (5, 1)) + [[0.1 * i, 0, 0] for i in range(5)])
    padded, pf, pd, _ = accuracy._bucketed(f, frac, dirs, None)
    assert padded.shape == (6, 64) and pf.shape == (6,) and pd.shape == (6, 3)
    kp, kd = accuracy.prior_box_params(*sim.prior_box, max_params=5, n_interior=1)
    s = jnp.int32(sim.substeps)
    args = (jnp.asarray(kp, jnp.float32), jnp.asarray(kd, jnp.float32))
    t_pad, ok_pad = accuracy._rollout_tau(sim, *args, jnp.asarray(padded, jnp.float32), pf, pd,
                                          None, s)  # fmt: skip
    t_own, ok_own = accuracy._rollout_tau(sim, *args, jnp.asarray(f, jnp.float32), frac, dirs,
                                          None, s)  # fmt: skip
    np.testing.assert_array_equal(np.asarray(t_pad)[:, :5, :40], np.asarray(t_own))
    np.testing.assert_array_equal(np.asarray(ok_pad)[:, :5], np.asarray(ok_own))
    # a shared direction [3] and grasp point stay shared
    _, pf, pd, _ = accuracy._bucketed(f, jnp.asarray(0.7), jnp.asarray([0.0, 0, -1]), None)
    assert pf.shape == () and pd.shape == (3,)


def test_traced_step_prediction_matches_and_is_one_program_for_any_step(tree):
    a = make_simulator(tree, obs_dt=0.01, substeps=6)
    b = make_simulator(tree, obs_dt=0.01, substeps=11)
    theta = np.log([[60.0, 25.0, 0.8, 0.3], [30.0, 40.0, 2.0, 0.1]])
    f = _forces(2, 64)
    for sim in (a, b):
        want = predict(sim, theta, f)
        got = predict(sim, theta, f, traced_substeps=True)
        scale = float(np.max(np.abs(np.asarray(want.tau))))
        np.testing.assert_allclose(np.asarray(got.tau), np.asarray(want.tau), atol=1e-5 * scale)
        np.testing.assert_array_equal(np.asarray(got.stable), np.asarray(want.stable))
    args = (jnp.ones((2, 2)), jnp.ones((2, 2)), jnp.asarray(f, jnp.float32), None, jnp.int32(6))
    text = [_predict_traced.lower(sim, *args).as_text() for sim in (a, b)]
    assert text[0] == text[1]  # one XLA program: the persistent cache serves both steps
    static = [predict.__globals__["_predict_jit"].lower(sim, *args[:4]).as_text() for sim in (a, b)]
    assert static[0] != static[1]  # the static step is a constant of the program (the reason)


def _trajectories(lengths, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for i, n in enumerate(lengths):
        t = np.arange(n) * 0.01
        f = (4.0 + i) * np.clip(t / 0.15, 0, 1)
        x = 0.01 * f / 5.0 + 1e-3 * rng.normal(size=n)
        out.append(Trajectory(t, f, x, None, f"p{i}"))
    return out


@pytest.mark.parametrize("grasp", [None, [0.9, 0.7, 0.8]])  # per-row grasp points: padded too
def test_training_fit_at_the_bucket_equals_the_fit_at_the_data_shape(tree, grasp):
    obs = stack_trajectories(_trajectories((50, 47, 44)))
    sim = make_simulator(tree, obs_dt=0.01, substeps=4)
    problem = make_problem(
        tree, obs, sim=sim, nn_prior=False, kT=0.05, grasp_fraction=grasp, likelihood="boltzmann"
    )
    assert grasp is None or problem.settings.get("grasp_fraction") == grasp
    bucket = [4, 64]  # a padded row as well as padded steps
    assert bucket_observations(obs, *bucket).mask.sum() == obs.mask.sum()
    padded = dataclasses.replace(
        problem, settings={**problem.settings, "shape_bucket": bucket}
    )  # fmt: skip
    rng = np.random.default_rng(3)
    theta = np.log([60.0, 25.0, 0.8, 0.3]) + 0.2 * rng.normal(size=(24, 4))
    post = SimpleNamespace(theta=theta, log_density=np.zeros(len(theta)))
    config = {"options": {"grasp_fraction": None}}
    want, got = _training_fit(problem, post, config), _training_fit(padded, post, config)
    pw, pg = want["prediction"], got["prediction"]
    assert pg.tau.shape == pw.tau.shape == (24, 3, 50)
    np.testing.assert_array_equal(got["stable"], want["stable"])
    for name in ("tau", "tau_dot", "lower", "upper", "mean", "predictive_lower"):
        w, g = getattr(pw, name), getattr(pg, name)
        if w is None:
            assert g is None
            continue
        scale = float(np.max(np.abs(w)))
        np.testing.assert_allclose(g, w, atol=2e-5 * scale, err_msg=name)
    mw, mg = want["metrics"], got["metrics"]
    assert mg["n_points"] == mw["n_points"] and mg["n_particles"] == mw["n_particles"]
    # float32 sums over more (masked, zero) entries: equal to rounding. The posterior NLL needs
    # the one-sided velocity at each row's last real sample (a central difference there moved it
    # by 2e-6 relative, which this tolerance catches)
    for key in ("ci_width", "pct_outside", "predictive_nll", "posterior_nll"):
        np.testing.assert_allclose(mg[key], mw[key], rtol=5e-7, err_msg=key)


def test_traced_rollout_program_key_leaves_out_only_the_step(tree):
    import jax

    from treeinfer.inference.fast_evaluator import _rollout_residuals

    a = make_simulator(tree, obs_dt=0.01, substeps=4, backend="fused")
    b = make_simulator(tree, obs_dt=0.01, substeps=9, backend="fused")
    b.mj_model.opt.timestep = 0.01 / 9  # make_simulator may share one model: each its own step
    own = b.mj_model.opt.timestep
    assert a.program_key(True) == b.program_key(True)
    assert b.mj_model.opt.timestep == own  # restored
    assert a.program_key(False) != b.program_key(False)  # the static step is in the program
    # the reason the key may leave the step out: the traced program is the same XLA program
    f = jnp.zeros((2, 64))
    args = (jnp.zeros((3, 4)), f, f, f, jnp.ones((2, 64), bool), jnp.int32(64), jnp.int32(4))
    text = [jax.jit(_rollout_residuals(s, None, True)).lower(*args).as_text() for s in (a, b)]
    assert text[0] == text[1]
    other = make_simulator(load_tree(example_path("three_branch")), obs_dt=0.01, substeps=4)
    assert other.program_key(True) != a.program_key(True)  # another tree: another program


@pytest.mark.parametrize("backend", ["fused", "pallas"])
def test_step_check_is_one_stored_program_for_any_step(tree, tmp_path, monkeypatch, backend):
    """The step check's program is kept as one jax.export artifact whatever the step, on the
    fused backend and on the Pallas kernel (whose traced step count is a runtime operand): a new
    recording whose accurate step differs loads it instead of tracing the simulator again."""
    from treeinfer.sim import _simulate

    monkeypatch.setenv("TREEINFER_JAX_CACHE", str(tmp_path))
    a = make_simulator(tree, obs_dt=0.01, substeps=4, backend=backend)
    b = make_simulator(tree, obs_dt=0.01, substeps=9, backend=backend)
    assert a.program_key(True) == b.program_key(True)
    assert a.program_key(False) != b.program_key(False)
    kp, kd = (jnp.asarray(x, jnp.float32) for x in accuracy.prior_box_params(*a.prior_box, 5, 1))
    f = jnp.asarray(_forces(2, 64), jnp.float32)
    for sim in (a, b):
        s = np.int32(sim.substeps)
        got_tau, got_ok = accuracy._rollout_tau(sim, kp, kd, f, None, None, None, s)
        want = _simulate(sim, kp, kd, f, substeps=jnp.int32(s))
        np.testing.assert_array_equal(np.asarray(got_ok), np.asarray(want.stable))
        scale = float(np.max(np.abs(np.asarray(want.tau))))  # float32 rounding of another build
        np.testing.assert_allclose(np.asarray(got_tau), np.asarray(want.tau), atol=1e-5 * scale)
    exports = list(tmp_path.rglob("*.jaxexport"))
    assert len(exports) == 1, exports  # b loaded a's program
