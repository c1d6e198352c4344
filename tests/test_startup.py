"""Shape buckets (treeinfer.startup): padded observations leave the log density unchanged."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from treeinfer.errors import ConfigError
from treeinfer.examples import example_path
from treeinfer.inference import make_problem
from treeinfer.sim import make_simulator
from treeinfer.startup import bucket_observations, steps_bucket, trajectories_bucket
from treeinfer.trajectories import Trajectory, stack_trajectories
from treeinfer.tree import load_tree


def test_buckets():
    assert [trajectories_bucket(n) for n in (1, 2, 3, 4, 5, 9)] == [1, 2, 4, 4, 8, 16]
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
    padded = bucket_observations(obs)
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
