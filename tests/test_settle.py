"""The fused backend's converged settle (Newton until the step is below rounding) against the
fixed 30-iteration settle and against MuJoCo C's equilibrium (``settle_reference``, float64
finite-difference Newton); its implicit derivative against central differences of the C
equilibrium."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from treeinfer.examples import example_path
from treeinfer.sim import make_simulator
from treeinfer.sim.fused_backend import _settle_one
from treeinfer.sim.reference import _c_model, settle_reference
from treeinfer.tree.description import load_tree
from treeinfer.tree.generators import chain


def _trees():
    yield "three_branch", load_tree(example_path("three_branch"))
    yield (
        "chain6",
        chain(
            6,
            lengths=np.linspace(0.7, 0.4, 6).tolist(),
            radii=np.linspace(0.03, 0.012, 6).tolist(),
            angles_deg=[0.0] + [-10.0] * 5,
            base_position=(0.0, 0.0, 1.5),
            base_pitch_deg=20.0,
            levels=6,
            name="chain6",
        ),
    )


def _gains(tree, n, seed):
    lo, hi = tree.bounds_array()
    rng = np.random.default_rng(seed)
    theta = np.log(lo) + rng.uniform(size=(n, lo.size)) * (np.log(hi) - np.log(lo))
    r = tree.n_inferred
    return np.exp(theta[:, :r]), np.exp(theta[:, r:])


@pytest.mark.parametrize("name,tree", list(_trees()), ids=lambda x: x if isinstance(x, str) else "")
def test_converged_settle_matches_fixed_and_mujoco(name, tree):
    sim = make_simulator(tree, obs_dt=0.01, substeps=2)
    kp, kd = _gains(tree, 6, seed=3)
    with jax.enable_x64(True):
        f64 = jnp.float64
        conv = jax.jit(jax.vmap(lambda a, b: _settle_one(sim, a, b, f64)))
        fixed = jax.jit(jax.vmap(lambda a, b: _settle_one(sim, a, b, f64, converged=False)))
        q_c, ok_c = (np.asarray(x) for x in conv(jnp.asarray(kp), jnp.asarray(kd)))
        q_f, ok_f = (np.asarray(x) for x in fixed(jnp.asarray(kp), jnp.asarray(kd)))
    assert ok_c.all() and ok_f.all()
    np.testing.assert_allclose(q_c, q_f, atol=1e-12)
    for i in range(len(kp)):
        q_ref = settle_reference(_c_model(sim, kp[i], kd[i]))
        np.testing.assert_allclose(q_c[i], q_ref, atol=1e-9)
    # float32, the simulator's dtype: equal to the fixed settle to rounding
    f32 = jnp.float32
    conv32 = jax.vmap(lambda a, b: _settle_one(sim, a, b, f32))
    fixed32 = jax.vmap(lambda a, b: _settle_one(sim, a, b, f32, converged=False))
    q32, ok32 = conv32(jnp.asarray(kp, f32), jnp.asarray(kd, f32))
    q32f, _ = fixed32(jnp.asarray(kp, f32), jnp.asarray(kd, f32))
    assert np.asarray(ok32).all()
    np.testing.assert_allclose(np.asarray(q32), np.asarray(q32f), atol=2e-6)


def test_converged_settle_stops_early_and_flags_failures():
    tree = load_tree(example_path("three_branch"))
    sim = make_simulator(tree, obs_dt=0.01, substeps=2)
    kp, kd = _gains(tree, 1, seed=0)
    import dataclasses

    short = dataclasses.replace(sim, settle_iterations=2)
    with jax.enable_x64(True):
        _, ok = _settle_one(short, jnp.asarray(kp[0]), jnp.asarray(kd[0]), jnp.float64)
        assert not bool(ok)  # two clipped steps do not reach the equilibrium
        # a NaN gain (a singular solve) stops the loop and is flagged, not returned as settled
        _, ok = _settle_one(sim, jnp.full(3, jnp.nan), jnp.asarray(kd[0]), jnp.float64)
        assert not bool(ok)


def test_settle_derivative_is_the_implicit_one():
    """d q_rest / d log Kp in forward and reverse mode against central differences of the C
    equilibrium (which is an independent Newton solve in float64)."""
    tree = load_tree(example_path("three_branch"))
    sim = make_simulator(tree, obs_dt=0.01, substeps=2)
    kp, kd = _gains(tree, 1, seed=5)
    kp, kd = kp[0], kd[0]
    with jax.enable_x64(True):
        f = lambda lk: _settle_one(sim, jnp.exp(lk), jnp.asarray(kd), jnp.float64)[0]
        lk = jnp.log(jnp.asarray(kp))
        j_fwd = np.asarray(jax.jacfwd(f)(lk))
        j_rev = np.asarray(jax.jacrev(f)(lk))
    h = 1e-5
    j_ref = np.zeros_like(j_fwd)
    for k in range(len(kp)):
        e = np.zeros(len(kp))
        e[k] = h
        qp = settle_reference(_c_model(sim, kp * np.exp(e), kd), tol=1e-13)
        qm = settle_reference(_c_model(sim, kp * np.exp(-e), kd), tol=1e-13)
        j_ref[:, k] = (qp - qm) / (2 * h)
    np.testing.assert_allclose(j_fwd, j_ref, atol=1e-6 * np.abs(j_ref).max())
    np.testing.assert_allclose(j_rev, j_fwd, atol=1e-12)
