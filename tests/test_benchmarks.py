"""Benchmarks of the CPU parts (pytest-benchmark), tiny shapes.

In the default suite they run once each (``--benchmark-disable`` in pyproject) and check the
numbers they time against the C reference; for figures run
``pytest tests/test_benchmarks.py --benchmark-enable``. Nothing here asserts a time.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from benchmarks.rollout import CRollout, bench_tree, c_pool, rollout_model, sample_gains
from treeinfer.data.trajectories import Trajectory
from treeinfer.inference.problem import make_problem
from treeinfer.sim import make_simulator, simulate
from treeinfer.sim.reference import simulate_reference

pytestmark = pytest.mark.benchmark

N_PARTICLES, N_STEPS, OBS_DT = 4, 12, 0.02


@pytest.fixture(scope="module")
def setup():
    tree = bench_tree(1)
    sim = make_simulator(tree, obs_dt=OBS_DT)
    kp, kd = sample_gains(tree, N_PARTICLES, seed=1)
    forces = np.linspace(0.0, 6.0, N_STEPS)[None]
    refs = [simulate_reference(sim, kp[i], kd[i], forces[0]) for i in range(N_PARTICLES)]
    return tree, sim, kp, kd, forces, refs


def test_batched_rollout_tiny_batch(benchmark, setup):
    _, sim, kp, kd, forces, refs = setup
    run = jax.jit(lambda a, b, f: simulate(sim, a, b, f))
    args = (
        jnp.asarray(kp, jnp.float32),
        jnp.asarray(kd, jnp.float32),
        jnp.asarray(forces, jnp.float32),
    )
    jax.block_until_ready(run(*args))  # compile outside the timing
    out = benchmark(lambda: jax.block_until_ready(run(*args)))
    benchmark.extra_info["particle_steps"] = N_PARTICLES * N_STEPS * sim.substeps
    assert np.all(np.asarray(out.stable))
    tau_ref = np.stack([r[0] for r in refs])
    np.testing.assert_allclose(np.asarray(out.tau[:, 0]), tau_ref, atol=1e-5)


def test_mujoco_rollout_tiny_batch(benchmark, setup):
    """The benchmark's native path (mujoco.rollout, grasp-point body) matches the reference."""
    tree, sim, kp, kd, forces, refs = setup
    m, bid = rollout_model(tree, sim)
    models, states, c_rest = c_pool(sim, m, kp, kd)
    crun = CRollout(sim, m, bid, models, states, forces, threads=2, chunk=N_PARTICLES)
    try:
        benchmark(lambda: crun.run(N_PARTICLES))
        pos = crun.sens_buf[:, :: sim.substeps, :3]
        tau = np.einsum("ptk,k->pt", pos - c_rest[:, None], sim.gravity_dir)
    finally:
        crun.close()
    tau_ref = np.stack([r[0] for r in refs])
    # the reference applies the lever-arm torque from the previous step's pose; the rollout's
    # grasp-point body has none: a small lag, far below the displacement itself
    np.testing.assert_allclose(tau, tau_ref, atol=1e-3 * np.max(np.abs(tau_ref)) + 1e-7)
    assert np.max(np.abs(tau_ref)) > 1e-3


def test_fd_gradient_evaluation(benchmark, setup):
    """One batched central-difference value-and-gradient (P * (2D + 1) rows, one simulator call);
    its value is checked against the Boltzmann likelihood of C-reference rollouts."""
    tree, sim, kp, kd, forces, refs = setup
    t = np.arange(N_STEPS) * OBS_DT
    tau0, vel0 = refs[0]
    problem = make_problem(
        tree,
        [Trajectory(t, forces[0], tau0, vel0, "pull")],
        sim=sim,
        nn_prior=False,
        kT=0.05,
        likelihood="boltzmann",
    )
    theta = jnp.asarray(
        np.log(np.stack([np.concatenate([kp[i], kd[i]]) for i in (1, 2)])), jnp.float32
    )
    vg = jax.jit(problem.value_and_grad)
    jax.block_until_ready(vg(theta))
    value, grad = benchmark(lambda: jax.block_until_ready(vg(theta)))
    benchmark.extra_info["simulated_rows"] = 2 * (2 * problem.dim + 1)
    expected = []
    for i in (1, 2):
        tau, vel = refs[i]
        loss = np.linalg.norm(tau - tau0) + np.linalg.norm(vel - vel0)
        expected.append(-loss / 0.05)
    expected = np.asarray(expected) + np.asarray(jax.jit(problem.log_prior)(theta))
    np.testing.assert_allclose(np.asarray(value), expected, rtol=2e-3)
    assert np.all(np.isfinite(np.asarray(grad))) and np.all(np.abs(np.asarray(grad)) > 0)
