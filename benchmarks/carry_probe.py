"""Probe: does carrying the joint state as tuples of scalars (one multi-output fusion) instead of
stacked arrays change the fused step's speed? 200 steps of the 3- and 6-branch chains."""

import sys
import time

import jax
import jax.numpy as jnp

from benchmarks.rollout import bench_tree
from treeinfer.sim import fused as hd
from treeinfer.sim import make_simulator


def main(batches):
    for nb in [3, 6]:
        sim = make_simulator(bench_tree(nb), obs_dt=0.01, accuracy="coarse")
        t, nv = sim.hinge_tree, sim.mj_model.nv

        def step_tuple(q, v, kp):
            out = hd.step(
                t,
                q,
                v,
                [kp] * nv,
                [0.5] * nv,
                [0.0] * nv,
                sim.sim_dt,
                sim.grasp_body,
                (0.5, 0.0, 0.0),
                (0.0, 0.0, -5.0),
                (0.1, 0.0, 0.0),
            )
            return out.qpos, out.qvel

        def step_stack(q, v, kp):
            qn, vn = step_tuple(tuple(q[i] for i in range(nv)), tuple(v[i] for i in range(nv)), kp)
            return jnp.stack(qn), jnp.stack(vn)

        for n in batches:
            kp = jnp.full((n,), 50.0)
            for name, fn, q0 in [
                ("stack", step_stack, jnp.zeros((n, nv)) + 0.1),
                ("tuple", step_tuple, tuple(jnp.zeros(n) + 0.1 for _ in range(nv))),
            ]:
                roll = jax.jit(
                    lambda q, v, kp, fn=fn: jax.lax.fori_loop(
                        0, 1200, lambda i, s: jax.vmap(fn)(s[0], s[1], kp), (q, v)
                    )
                )
                c = roll.lower(q0, q0, kp).compile()
                jax.block_until_ready(c(q0, q0, kp))
                t0 = time.perf_counter()
                for _ in range(5):
                    jax.block_until_ready(c(q0, q0, kp))
                dt = (time.perf_counter() - t0) / 5
                print(
                    f"{nb} joints N={n:>6} {name}: {dt * 1e3:.2f} ms per 1200 steps, "
                    f"{n * 1200 / dt / 1e9:.2f} G steps/s",
                    flush=True,
                )


if __name__ == "__main__":
    main([int(x) for x in (sys.argv[1] if len(sys.argv) > 1 else "4992,131072").split(",")])
