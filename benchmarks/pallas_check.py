"""The Pallas whole-rollout kernel against the fused XLA step on the standard problem (GPU).

    python -m benchmarks.pallas_check [--particles 32]

Prints the largest difference of ``tau`` (m) and of the exact (jvp) likelihood gradients between
``backend="pallas"`` and ``backend="fused"``, the jvp gradient against central differences, and
the time of one batched rollout on each backend (the kernel compiled by Triton on a GPU).
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--particles", type=int, default=32)
    p.add_argument("--steps", type=int, default=300)
    args = p.parse_args(argv)

    import dataclasses

    import jax
    import jax.numpy as jnp

    from benchmarks import _common as C
    from benchmarks.gradient_cost import standard_likelihood
    from treeinfer.model import central_difference, jvp_value_and_grad
    from treeinfer.sim import simulate

    out = {"platform": jax.devices()[0].platform}
    loglik_f, truth = standard_likelihood(args.steps, "fused")
    loglik_p, _ = standard_likelihood(args.steps, "pallas")
    rng = np.random.default_rng(1)
    theta = jnp.asarray(truth + 0.3 * rng.normal(size=(args.particles, truth.size)), jnp.float32)
    # rollouts of the two backends on the same simulator settings
    from benchmarks.inference import make_standard_problem

    sim = make_standard_problem(n_steps=args.steps, backend="fused")[0].sim
    sim_p = dataclasses.replace(sim, backend="pallas")
    forces = jnp.asarray(rng.normal(size=(3, args.steps)).cumsum(axis=1) * 0.5, jnp.float32)
    r = truth.size // 2
    kp, kd = jnp.exp(theta[:, :r]), jnp.exp(theta[:, r:])
    times = {}
    ro = {}
    for name, s in (("fused", sim), ("pallas", sim_p)):
        fn = jax.jit(lambda a, b, f, s=s: simulate(s, a, b, f))
        ro[name] = C.block(fn(kp, kd, forces))
        t0 = time.perf_counter()
        for _ in range(5):
            C.block(fn(kp, kd, forces))
        times[name] = (time.perf_counter() - t0) / 5
    out["rollout_ms"] = {k: 1e3 * v for k, v in times.items()}
    out["max_abs_tau_diff_m"] = float(jnp.abs(ro["fused"].tau - ro["pallas"].tau).max())
    out["max_abs_tau_m"] = float(jnp.abs(ro["fused"].tau).max())
    out["stable_equal"] = bool(jnp.all(ro["fused"].stable == ro["pallas"].stable))
    print("PALLAS_CHECK rollout " + json.dumps(out), flush=True)
    grads = {}
    for name, fn in (
        ("jvp_pallas", jvp_value_and_grad(loglik_p)),
        ("fd_pallas", central_difference(loglik_p)),
        ("jvp_fused", jvp_value_and_grad(loglik_f)),
    ):
        t0 = time.perf_counter()
        grads[name] = C.block(jax.jit(fn)(theta))
        print(f"   {name}: compile + first call {time.perf_counter() - t0:.1f} s", flush=True)
    g_p, g_fd, g_f = (grads[k][1] for k in ("jvp_pallas", "fd_pallas", "jvp_fused"))
    out["max_abs_value_diff"] = float(jnp.abs(grads["jvp_fused"][0] - grads["jvp_pallas"][0]).max())
    out["max_abs_jvp_grad_diff_pallas_vs_fused"] = float(jnp.abs(g_f - g_p).max())
    out["max_abs_grad"] = float(jnp.abs(g_f).max())
    out["max_abs_grad_diff_jvp_vs_fd_pallas"] = float(jnp.abs(g_p - g_fd).max())
    print("PALLAS_CHECK " + json.dumps(out), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
