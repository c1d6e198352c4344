"""Shape buckets (treeinfer.sim.startup): padded observations leave the log density unchanged."""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from treeinfer.data.trajectories import Trajectory, stack_trajectories
from treeinfer.errors import ConfigError
from treeinfer.examples import example_path
from treeinfer.inference.problem import make_problem
from treeinfer.sim import make_simulator
from treeinfer.sim.startup import bucket_observations, steps_bucket, trajectories_bucket
from treeinfer.tree.description import load_tree


def test_buckets():
    assert [trajectories_bucket(n) for n in (1, 2, 3, 4, 5, 7, 9, 13)] == [1, 2, 3, 4, 6, 8, 12, 16]
    for n in range(1, 200):  # at most 50% extra rows, never fewer
        assert n <= trajectories_bucket(n) <= 1.5 * n
    assert steps_bucket(10) == 64 and steps_bucket(64) == 64 and steps_bucket(65) == 80
    assert steps_bucket(300) == 320 and steps_bucket(287) == 320 and steps_bucket(321) == 384
    for n in range(64, 5000, 7):  # at most 25% extra steps, never fewer
        assert n <= steps_bucket(n) <= 1.25 * n
    with pytest.raises(ConfigError):
        trajectories_bucket(0)


@pytest.mark.parametrize("likelihood", ["boltzmann", "gaussian"])
def test_padded_trajectories_and_steps_give_the_same_log_density(likelihood):
    tree = load_tree(example_path("two_branch"))
    sim = make_simulator(tree, obs_dt=0.01, substeps=4)
    rng = np.random.default_rng(0)
    trajs = []
    for i, n in enumerate((50, 37, 44)):  # ragged: stacking already masks the shorter ones
        t = np.arange(n) * 0.01
        f = (4.0 + i) * np.clip(t / 0.15, 0, 1)
        x = 0.01 * f / 5.0 + 1e-3 * rng.normal(size=n)
        trajs.append(Trajectory(t, f, x, None, f"p{i}"))
    obs = stack_trajectories(trajs)
    assert bucket_observations(obs).force.shape == (3, 64)
    padded = bucket_observations(obs, 4, 64)  # a padded row as well
    assert padded.force.shape == (4, 64) and padded.mask.sum() == obs.mask.sum()
    kw = {"sim": sim, "nn_prior": False, "likelihood": likelihood, "kT": 0.05}
    if likelihood == "gaussian":
        kw = {**kw, "noise_displacement": 1e-3}
        kw.pop("kT")
    a, b = make_problem(tree, obs, **kw), make_problem(tree, padded, **kw)
    theta = jnp.asarray(
        np.log(np.array([[60.0, 25.0, 0.8, 0.3], [30.0, 40.0, 2.0, 0.1], [90.0, 9.0, 0.3, 1.0]])),
        jnp.float32,
    )
    # Gaussian (displacement only): equal to float32 rounding. Boltzmann: the simulated velocity
    # at the longest row's last real sample differs by ~2e-6 relative (the same in float64:
    # not rounding; a boundary effect of the simulator's velocity once a next step exists, which
    # ragged rows stacked by stack_trajectories already have); bounded here, not zero.
    rtol = 1e-6 if likelihood == "gaussian" else 1e-5
    la, lb = jax.jit(a.log_likelihood)(theta), jax.jit(b.log_likelihood)(theta)
    np.testing.assert_allclose(np.asarray(lb), np.asarray(la), rtol=rtol)
    (va, ga), (vb, gb) = jax.jit(a.value_and_grad)(theta), jax.jit(b.value_and_grad)(theta)
    np.testing.assert_allclose(np.asarray(vb), np.asarray(va), rtol=rtol)
    # central differences of a float32 log density of ~600: rounding noise ~ eps * 600 / h
    np.testing.assert_allclose(np.asarray(gb), np.asarray(ga), rtol=1e-3, atol=0.05)


def _pulls(lengths, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for i, n in enumerate(lengths):
        t = np.arange(n) * 0.01
        f = (5.0 + i) * np.clip(t / 0.1, 0, 1) * (t < 0.3)
        x = 0.01 * f / 5.0 + 1e-3 * rng.normal(size=n)
        out.append(Trajectory(t, f, x, None, f"p{i}"))
    return out


def _config(init="importance", problem=None, **options):
    o = {"kT": 0.05, "sampler": "svgd", "eta": 10.0, "grasp_fraction": None, "init": init}
    return {"options": {**o, **options}, **({"problem": problem} if problem else {})}


def test_shape_bucket_for_importance_runs_only():
    from treeinfer.runs.problem import shape_bucket_for

    obs = stack_trajectories(_pulls((50, 57, 44)))
    assert shape_bucket_for(_config(), obs) == [3, 64]
    assert shape_bucket_for(_config("uniform"), obs) is None  # the samplers' programs: as before
    assert shape_bucket_for(_config(shape_buckets="off"), obs) is None
    # a resumed run keeps what it recorded (runs from before buckets recorded none)
    assert shape_bucket_for(_config(problem={"substeps": 2}), obs) is None
    assert shape_bucket_for(_config(problem={"shape_bucket": [4, 80]}), obs) == [4, 80]
    with pytest.raises(ConfigError, match="shape_buckets"):
        shape_bucket_for(_config(shape_buckets="yes"), obs)


def test_two_data_sets_of_one_bucket_share_one_compiled_program():
    """Through the run layer (build_problem records the bucket, the importance path's evaluator
    pads to it): data sets of 57 and 60 steps compile one rollout program between them, and
    each gives the log density of its own unpadded problem."""
    from treeinfer.inference.fast import BatchEvaluator
    from treeinfer.runs import SimulatorCache
    from treeinfer.runs.problem import build_problem
    from treeinfer.sim.program_cache import ProgramCache
    from treeinfer.tree.generators import chain

    tree = chain(1, lengths=0.7, radii=0.03, angles_deg=0.0, base_position=(0.0, 0.0, 1.5),
                 base_pitch_deg=20.0, levels=1, name="c1")  # fmt: skip
    cache, programs = SimulatorCache(), ProgramCache()
    # recorded substeps (as a resumed run's): the same simulator for both, no step probes
    theta = jnp.asarray(np.log([[40.0, 0.6], [25.0, 1.5], [70.0, 0.2]]), jnp.float32)
    evaluators = []
    for lengths in ((50, 57), (60, 44)):
        config = _config(problem={"substeps": 2, "shape_bucket": [2, 64]})
        problem = build_problem(config, tree, _pulls(lengths), cache)
        assert problem.settings["shape_bucket"] == [2, 64]
        assert problem.obs.force.shape == (2, max(lengths))  # the run's data stay unpadded
        ev = BatchEvaluator(problem, 3, programs)
        got = ev.log_density(theta)
        want = np.asarray(jax.jit(problem.log_density)(theta), float)
        np.testing.assert_allclose(got, want, rtol=1e-5)
        r, _, _ = ev.evaluate(theta)
        assert r.shape == (3, 4, max(lengths))  # the data's rows and steps only
        evaluators.append(ev)
    a, b = evaluators
    # one rollout program, and one cache of the small programs around it (prior, noise density:
    # treeinfer.sim.args_program), shared by both data sets
    assert programs.builds == 2 and a._run is b._run
    assert a._run._cache_size() == 1  # one trace and compile for both data sets
    # without the bucket the two data sets have two shapes: two programs
    for lengths in ((50, 57), (60, 44)):
        config = _config(problem={"substeps": 2})
        BatchEvaluator(build_problem(config, tree, _pulls(lengths), cache), 3, programs)
    assert programs.builds == 4  # two more rollout programs


def test_cached_program_is_traced_once_per_machine(tmp_path, monkeypatch):
    """The serialized export is written on the first call and read by the next (no tracing of
    the function), with the same results as a plain jit; off with TREEINFER_JAX_CACHE=off."""
    from treeinfer.sim.startup import cached_program, export_path

    monkeypatch.setenv("TREEINFER_JAX_CACHE", str(tmp_path))
    traced = []

    def make():  # a fresh function each time, as in a new process (jax caches traces per object)
        def fn(x, y, n):
            traced.append(1)
            return jnp.sin(x) @ y + n, jnp.linalg.solve(y, x.T)

        return fn

    args = (jnp.ones((3, 4)) * 0.3, jnp.eye(4) * 2.0 + 0.1, jnp.asarray(5, jnp.int32))
    want = jax.jit(make())(*args)
    traced.clear()
    got1 = cached_program(make(), args, "test-key")(*args)
    assert len(traced) == 1
    path = export_path("test-key")
    assert path is not None and path.startswith(str(tmp_path)) and Path(path).is_file()
    got2 = cached_program(make(), args, "test-key")(*args)
    assert len(traced) == 1  # read from disk: fn not traced again
    for a, b, c in zip(want, got1, got2):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-6)
        np.testing.assert_array_equal(np.asarray(c), np.asarray(b))
    assert export_path("other-key") != path
    Path(path).write_bytes(b"not an export")  # unreadable: traced and written again
    third = cached_program(make(), args, "test-key")
    np.testing.assert_array_equal(np.asarray(third(*args)[0]), np.asarray(got1[0]))
    assert len(traced) == 2
    monkeypatch.setenv("TREEINFER_JAX_CACHE", "off")
    assert export_path("test-key") is None
    cached_program(make(), args, "test-key")(*args)
    assert len(traced) == 3
