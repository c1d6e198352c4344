"""NNSVGD step time with particles sharded over all local devices, against one device.

    python -m benchmarks.sharded --particles 128,1024,4096
    # CPU cores as devices:
    XLA_FLAGS=--xla_force_host_platform_device_count=2 python -m benchmarks.sharded

The standard problem (``benchmarks.inference``); for each particle count, one jitted step on
the default device alone (unsharded) and one with particles (and their finite-difference rows)
sharded over all devices (``treeinfer.inference.sharding``); after timing, ``--check-steps`` steps
from the same start in both ways give the largest difference of the particles. (With Adam, a first
step moves each coordinate by about the learning rate times the sign of its update, so a coordinate
whose Stein update is near zero can flip by ~2 x lr from rounding alone: compare
``value_and_grad_check``, the batched value and gradient evaluated both ways on the same
particles, for accuracy.)
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from benchmarks import _common as C


def main(argv=None) -> int:
    import jax

    from benchmarks.inference import make_standard_problem, step_time
    from treeinfer.inference import sharding

    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument(
        "--particles", type=lambda t: [int(x) for x in t.split(",")], default=[128, 1024, 4096]
    )
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--reps", type=int, default=3)
    p.add_argument("--check-steps", type=int, default=3)
    p.add_argument("--method", default="gspmd", choices=["shard_map", "gspmd"])
    p.add_argument("--machine", default=None)
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    n_dev = jax.device_count()
    record = {"machine": C.machine_info(), "settings": vars(args), "n_devices": n_dev, "rows": []}
    print(f"machine: {record['machine']}", flush=True)
    out = args.out or (C.RESULTS_DIR / f"{args.machine or C.default_machine_name()}.json")
    problem = make_standard_problem(n_steps=args.steps)[0]
    every = sharding.particle_mesh()
    # the batched value and gradient itself, sharded vs not, on the same particles
    from treeinfer.inference import initial_particles

    theta = initial_particles(problem, args.particles[0], seed=0)
    v0, g0 = jax.jit(problem.value_and_grad)(theta)
    sp = sharding.shard_problem(problem, every, args.method)
    v1, g1 = jax.jit(sp.value_and_grad)(sharding.shard_particles(theta, every))
    v0, g0, v1, g1 = (np.asarray(x, float) for x in (v0, g0, v1, g1))
    ok = np.isfinite(v0) & np.isfinite(v1)
    record["value_and_grad_check"] = {
        "n_particles": args.particles[0],
        "finite_both": int(ok.sum()),
        "finite_differ": int((np.isfinite(v0) != np.isfinite(v1)).sum()),
        "max_rel_value_diff": float(
            np.max(np.abs(v0[ok] - v1[ok]) / np.maximum(np.abs(v0[ok]), 1.0))
        ),
        "max_grad_diff_over_grad_norm": float(
            np.max(
                np.linalg.norm(g0[ok] - g1[ok], axis=1)
                / np.maximum(np.linalg.norm(g0[ok], axis=1), 1e-12)
            )
        ),
        "bitwise_equal": bool(np.array_equal(v0, v1) and np.array_equal(g0, g1)),
    }
    print(f"   value_and_grad, P={args.particles[0]}: {record['value_and_grad_check']}", flush=True)
    for n in args.particles:
        a = step_time(
            problem, n, args.reps, mesh=None, min_time_s=0.0, n_final=args.check_steps
        )  # plain, device 0
        b = step_time(
            problem,
            n,
            args.reps,
            mesh=every,
            min_time_s=0.0,
            n_final=args.check_steps,
            method=args.method,
        )
        fa, fb = a.pop("final_positions"), b.pop("final_positions")
        row = {
            "n_particles": n,
            "one_device": a,
            "all_devices": b,
            "speedup": a["step_ms"] / b["step_ms"],
            "max_abs_diff_after_steps": float(np.max(np.abs(fa - fb))),
            "bitwise_equal": bool(np.array_equal(fa, fb)),
        }
        record["rows"].append(row)
        C.merge_results(out, f"sharding_{args.method}", record, {})
        print(
            f"   P={n:>5}: 1 device {a['step_ms']:.1f} ms, {n_dev} devices {b['step_ms']:.1f} ms "
            f"(x{row['speedup']:.2f}); compile {a['compile_s']:.1f} / {b['compile_s']:.1f} s; "
            f"max |diff| after {args.check_steps} steps {row['max_abs_diff_after_steps']:.1e}"
            f"{' (bitwise equal)' if row['bitwise_equal'] else ''}",
            flush=True,
        )
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
