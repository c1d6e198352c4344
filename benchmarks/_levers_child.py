"""Child-process side of ``benchmarks/levers.py``: the standard inputs and the measurements
each precision / XLA-flag variant runs in a fresh process (``python -c "from benchmarks.levers
import precision_child; ..."``). Re-exported by :mod:`benchmarks.levers`."""

from __future__ import annotations

import time

import numpy as np

from benchmarks import _common as C


def _standard_inputs(n_steps: int):
    from benchmarks.inference import EXAMPLES
    from treeinfer.data import profile_set
    from treeinfer.sim.synthetic import default_true_params
    from treeinfer.tree import load_tree

    tree = load_tree(EXAMPLES / "three_branch.yaml")
    forces = profile_set("mixed", n=3, duration=n_steps * 0.01, dt=0.01, seed=0)[:, :n_steps]
    kp_true, kd_true = default_true_params(tree, np.random.default_rng(0))
    return tree, forces, kp_true, kd_true


def precision_child(batch: int, n_steps: int, n_check: int, reps: int) -> dict:
    """Errors against C and the rollout time at this process's JAX precision settings.

    The first ``n_check`` parameter sets are checked inside the large batch (that is where XLA
    picks its large-batch kernels) and again as a batch of their own (batch-size consistency)."""
    import jax
    import jax.numpy as jnp

    from benchmarks.rollout import sample_gains
    from treeinfer.sim import make_simulator, simulate
    from treeinfer.sim.reference import simulate_reference

    tree, forces, _, _ = _standard_inputs(n_steps)
    sim = make_simulator(tree, obs_dt=0.01, accuracy="coarse")
    kp, kd = sample_gains(tree, max(batch, n_check), seed=11)
    dtype = jnp.float64 if jax.config.jax_enable_x64 else jnp.float32
    run = jax.jit(lambda a, b, f: simulate(sim, a, b, f))
    f = jnp.asarray(forces, dtype)
    a, b_ = jnp.asarray(kp[:batch], dtype), jnp.asarray(kd[:batch], dtype)
    t0 = time.perf_counter()
    compiled = run.lower(a, b_, f).compile()
    t_compile = time.perf_counter() - t0
    big = C.block(compiled(a, b_, f))
    small = run(jnp.asarray(kp[:n_check], dtype), jnp.asarray(kd[:n_check], dtype), f)
    err_tau, err_vel, scale = 0.0, 0.0, 0.0
    for i in range(n_check):
        for j in range(forces.shape[0]):
            tau, vel = simulate_reference(sim, kp[i], kd[i], forces[j])
            err_tau = max(err_tau, float(np.max(np.abs(np.asarray(big.tau[i, j], float) - tau))))
            err_vel = max(
                err_vel, float(np.max(np.abs(np.asarray(big.tau_dot[i, j], float) - vel)))
            )
            scale = max(scale, float(np.max(np.abs(tau))))
    batch_diff = float(
        np.max(np.abs(np.asarray(big.tau[:n_check], float) - np.asarray(small.tau, float)))
    )
    tm = C.time_calls(lambda: compiled(a, b_, f), reps=reps, min_time_s=1.0)
    steps = batch * forces.shape[0] * n_steps * sim.substeps
    return {
        "dtype": str(np.dtype(dtype)),
        "matmul_precision": str(jax.config.jax_default_matmul_precision),
        "max_abs_tau_error_m": err_tau,
        "max_abs_tau_dot_error_m_s": err_vel,
        "max_abs_tau_m": scale,
        "n_checked": n_check * forces.shape[0],
        "batch": batch,
        "max_abs_tau_diff_batch_vs_alone_m": batch_diff,
        "rollout_s": tm["median_s"],
        "steps_per_s": steps / tm["median_s"],
        "compile_s": t_compile,
        "all_stable": bool(np.all(np.asarray(big.stable[:n_check]))),
    }


def rollout_time_child(batch: int, n_steps: int, reps: int) -> dict:
    """Compile and time the library's ``simulate`` on the 3-branch example (for flag variants)."""
    import jax
    import jax.numpy as jnp

    from benchmarks.rollout import sample_gains
    from treeinfer.sim import make_simulator, simulate

    tree, forces, _, _ = _standard_inputs(n_steps)
    sim = make_simulator(tree, obs_dt=0.01, accuracy="coarse")
    kp, kd = sample_gains(tree, batch, seed=5)
    a, b, f = (jnp.asarray(x, jnp.float32) for x in (kp, kd, forces))
    fn = jax.jit(lambda x, y, z: simulate(sim, x, y, z))
    t0 = time.perf_counter()
    compiled = fn.lower(a, b, f).compile()
    t_compile = time.perf_counter() - t0
    C.block(compiled(a, b, f))
    tm = C.time_calls(lambda: compiled(a, b, f), reps=reps, min_time_s=1.0)
    steps = batch * forces.shape[0] * n_steps * sim.substeps
    return {
        "compile_s": t_compile,
        "rollout_s": tm["median_s"],
        "steps_per_s": steps / tm["median_s"],
        "us_per_step": 1e6 * tm["median_s"] / (n_steps * sim.substeps),
    }
