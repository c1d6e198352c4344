"""The batched MJX simulator against MuJoCo's C stepping, settling, stability and batching."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from treeinfer.errors import ConfigError, SimulationError
from treeinfer.examples import example_path
from treeinfer.sim import (
    check_stable_share,
    make_simulator,
    settle,
    simulate,
)
from treeinfer.sim.reference import _c_model, settle_reference, simulate_reference
from treeinfer.tree.description import load_tree

T = 60
DT = 0.02


@pytest.fixture(scope="module", params=["fused", "levels", "mjx"])
def three(request):
    """Every test below runs on both backends: the fused hinge-tree step (in its scalar and its
    level layout) and mjx.step."""
    tree = load_tree(example_path("three_branch"))
    backend = "fused" if request.param == "levels" else request.param
    sim = make_simulator(tree, obs_dt=DT, backend=backend)
    if request.param == "levels":
        sim = dataclasses.replace(sim, step_layout="levels")
    assert sim.backend == backend
    # simulate is jitted by simulator content and shapes: every call below with the rollout's
    # shapes reuses one compiled program per backend (test_backends_agree_with_each_other's
    # other backend too); a jit around it would compile a second program of its own
    run = lambda kp, kd, f, g: simulate(sim, kp, kd, f, g)
    return tree, sim, run


def _forces():
    t = np.arange(T) * DT
    return np.stack([np.clip(t / 0.6, 0, 1) * 12.0, np.clip(t / 0.3, 0, 1) * 6.0 * (t < 0.8)])


# Three parameter sets across the prior box (soft and light, middle, stiff and damped) and one
# that is far outside it (unstable for this step).
KP = np.array([[10.0, 20.0, 40.0], [50.0, 150.0, 300.0], [480.0, 450.0, 400.0], [2e6, 2e6, 2e6]])
KD = np.array([[0.06, 0.06, 0.06], [0.5, 1.0, 2.0], [9.0, 9.0, 9.0], [0.05, 0.05, 0.05]])


@pytest.fixture(scope="module")
def rollout(three):
    _, _, run = three
    return run(jnp.asarray(KP), jnp.asarray(KD), jnp.asarray(_forces()), jnp.asarray([1.0, 0.6]))


def test_batched_rollout_matches_mujoco_c(three, rollout):
    """Either backend (float32, vmapped) and plain mujoco.mj_step (float64) agree within 1e-4 m."""
    _, sim, _ = three
    forces = _forces()
    for p in range(3):
        for b, frac in enumerate([1.0, 0.6]):
            tau_c, tau_dot_c = simulate_reference(sim, KP[p], KD[p], forces[b], grasp_fraction=frac)
            assert np.max(np.abs(tau_c)) > 0.01  # the branch really moves
            np.testing.assert_allclose(np.asarray(rollout.tau[p, b]), tau_c, atol=1e-4)
            np.testing.assert_allclose(np.asarray(rollout.tau_dot[p, b]), tau_dot_c, atol=2e-3)


def test_output_shapes_and_rest(rollout):
    assert rollout.tau.shape == (4, 2, T)
    assert rollout.tau_dot.shape == (4, 2, T)
    assert rollout.stable.shape == (4, 2)
    # tau is measured from the settled rest: it starts at zero
    np.testing.assert_allclose(np.asarray(rollout.tau[:3, :, 0]), 0.0, atol=1e-6)


def test_unstable_entry_is_flagged_and_isolated(rollout):
    stable = np.asarray(rollout.stable)
    assert stable[:3].all()
    assert not stable[3].any()
    assert np.all(np.asarray(rollout.tau[3]) == 0.0)
    assert np.all(np.isfinite(np.asarray(rollout.tau)))
    with pytest.raises(SimulationError, match="unstable"):
        check_stable_share(stable, 0.1)
    check_stable_share(stable, 0.5)


def test_softer_branch_sags_more_and_settled_state_is_at_rest(three):
    """The static solve balances gravity: zero torque there, zero motion when released."""
    import mujoco

    _, sim, _ = three
    q, ok = settle(sim, jnp.asarray(KP[:3]), jnp.asarray(KD[:3]))
    assert np.asarray(ok).all()
    q = np.asarray(q)
    # the soft set sags more at every inferred joint than the stiff set
    assert np.all(np.abs(q[0, sim.joint_ids]) > np.abs(q[2, sim.joint_ids]))
    for p in range(3):
        m = _c_model(sim, KP[p], KD[p])
        q_ref = settle_reference(m)
        np.testing.assert_allclose(q[p], q_ref, atol=2e-5)
        d = mujoco.MjData(m)
        d.qpos[:] = q_ref
        mujoco.mj_forward(m, d)
        assert np.max(np.abs(d.qacc)) < 1e-6  # at rest: no acceleration
        start = d.site_xpos[sim.grasp_site].copy()
        for _ in range(200):
            mujoco.mj_step(m, d)
        assert np.max(np.abs(d.site_xpos[sim.grasp_site] - start)) < 1e-8


def test_zero_force_keeps_rest(three):
    """No force: every stable set stays at its settled rest (the rollout's shapes: no compile)."""
    _, _, run = three
    r = run(jnp.asarray(KP), jnp.asarray(KD), jnp.zeros((2, T)), jnp.asarray([1.0, 0.6]))
    assert np.asarray(r.stable[:3]).all()
    assert np.max(np.abs(np.asarray(r.tau[:3]))) < 1e-5


def test_grasp_fraction_changes_lever_arm(rollout):
    """The same kind of pull nearer the joint moves the grasp point less."""
    assert np.max(np.asarray(rollout.tau[1, 0])) > np.max(np.asarray(rollout.tau[1, 1]))


def test_bad_options():
    tree = load_tree(example_path("two_branch"))
    with pytest.raises(ConfigError, match="obs_dt"):
        make_simulator(tree, obs_dt=-0.01)
    with pytest.raises(ConfigError, match="substeps"):
        make_simulator(tree, obs_dt=0.01, substeps=0)
    with pytest.raises(ConfigError, match="backend"):
        make_simulator(tree, obs_dt=0.01, backend="warp")


def test_backends_agree_with_each_other(three, rollout):
    """The fused step and mjx.step integrate the same MuJoCo model: the three stable parameter
    sets of the rollout, both backends. The other backend's rollout has the same simulator
    content and shapes as its own fixture's, so it is compiled once in the module."""
    tree, sim, _ = three
    if sim.backend == "fused":
        # fused vs mjx is the [mjx] case and fused vs levels the [levels] case: comparing again
        # here would compile the MJX rollout a second time (about 2 min of the 2-core suite)
        pytest.skip("fused is compared with mjx and levels in the other two cases")
    other = make_simulator(tree, obs_dt=DT, backend="fused")
    f = jnp.asarray(_forces())
    b = simulate(other, jnp.asarray(KP), jnp.asarray(KD), f, jnp.asarray([1.0, 0.6]))
    a_tau = np.asarray(rollout.tau[:3])
    assert np.max(np.abs(a_tau)) > 0.01
    np.testing.assert_array_equal(np.asarray(rollout.stable), np.asarray(b.stable))
    np.testing.assert_allclose(a_tau, np.asarray(b.tau[:3]), atol=2e-5)


def test_substeps_follow_the_stiffest_prior_corner():
    """A stiffer prior box needs a smaller simulation step."""
    from dataclasses import replace

    from treeinfer.tree.description import Bounds

    tree = load_tree(example_path("two_branch"))
    # the stability step (accuracy="coarse"); the default refines it further for accuracy
    soft = make_simulator(tree, obs_dt=DT, accuracy="coarse")
    stiff_tree = replace(tree, bounds={n: Bounds(kp=(5.0, 50000.0)) for n in tree.inferred})
    stiff = make_simulator(stiff_tree, obs_dt=DT, accuracy="coarse")
    assert stiff.substeps > soft.substeps
    assert (
        stiff.sim_dt <= 1.5 / 1000.0
    )  # omega_max * dt <= 1.5; omega_max > 1000 rad/s at 2 x 50000 N m/rad


def test_second_simulate_call_does_not_recompile():
    """``simulate`` is compiled once per simulator content and shapes: new values, and a
    simulator rebuilt from the same tree, reuse the program (no trace, no XLA compile)."""
    import treeinfer.sim as ts

    tree = load_tree(example_path("two_branch"))
    forces = jnp.asarray(_forces()[:, :20])
    kp, kd = jnp.asarray([[40.0, 60.0]]), jnp.asarray([[0.5, 0.5]])
    kp2 = jnp.asarray([[80.0, 60.0]])  # made here: an eager op compiles a program of its own
    sim = make_simulator(tree, obs_dt=DT, substeps=2)
    compiles = []

    def listener(event, duration, **kw):
        if event == "/jax/core/compile/backend_compile_duration":
            compiles.append(duration)

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        before = ts.TRACES
        first = simulate(sim, kp, kd, forces)
        assert ts.TRACES == before + 1
        n_traces, n_compiles = ts.TRACES, len(compiles)
        again = simulate(sim, kp2, kd, forces)
        rebuilt = make_simulator(tree, obs_dt=DT, substeps=2)
        assert rebuilt is not sim and rebuilt == sim
        third = simulate(rebuilt, kp, kd, forces)
        assert ts.TRACES == n_traces and len(compiles) == n_compiles
        # another step is another program
        simulate(make_simulator(tree, obs_dt=DT, substeps=3), kp, kd, forces)
        assert ts.TRACES == n_traces + 1
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)
    np.testing.assert_array_equal(np.asarray(first.tau), np.asarray(third.tau))
    assert not np.allclose(np.asarray(first.tau), np.asarray(again.tau))


@pytest.mark.parametrize("n_pulls", [1, 2])
def test_one_parameter_set_runs_without_a_vmap_to_the_same_values(monkeypatch, n_pulls):
    """One parameter set (the force Jacobian's) skips its vmap level (``treeinfer.sim._vmap``:
    the while-loop batching rule traced it again for every loop, 40% of the Jacobian program's
    trace) and gives the values of the vmap of one row to the bit."""
    import treeinfer.sim as sim_pkg
    from treeinfer.sim import _simulate, _vmap

    seen = []

    def fn(a, b):
        seen.append((a.shape, b.shape))
        return a + b, a * b

    out = _vmap(fn, jnp.ones((1, 3)), jnp.full((1, 3), 2.0))
    assert seen == [((3,), (3,))]  # called on the row itself, not under vmap
    assert out[0].shape == (1, 3) and float(out[1][0, 0]) == 2.0
    out = _vmap(fn, jnp.ones((2, 3)), jnp.full((2, 3), 2.0))
    assert seen[-1] == ((3,), (3,)) and out[0].shape == (2, 3)  # traced once under vmap

    sim = make_simulator(load_tree(example_path("two_branch")), obs_dt=0.01, substeps=4)
    t = np.arange(60) * 0.01
    f = np.stack([5.0 * np.clip(t / 0.2, 0, 1), 3.0 * np.clip(t / 0.1, 0, 1)])[:n_pulls]
    kp, kd = np.array([[60.0, 25.0]]), np.array([[0.8, 0.3]])

    def run():  # a new jit each time: the patched _vmap is traced
        return jax.jit(lambda a, b, c: _simulate(sim, a, b, c))(kp, kd, f)

    one = run()
    monkeypatch.setattr(sim_pkg, "_vmap", lambda fn, *a: jax.vmap(fn)(*a))  # as before
    before = run()
    assert one.tau.shape == (1, n_pulls, 60) and bool(np.all(one.stable))
    for a, b in zip(one, before):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
