"""Compile time, peak memory and throughput of the fused simulator against the joint count.

    JAX_PLATFORMS=cpu python -m benchmarks.compile_scaling            # 1..200 joints, CPU
    JAX_PLATFORMS=cuda python -m benchmarks.compile_scaling --device cuda --machine h100

The trees are prefixes of one generated L-system tree (``F -> F[+F][-F]F``, 5 iterations, 683
branches, drawn parents first), so every size is a real branching tree and the big ones are the
issue's L-system trees; the first n branches keep their parents, the grasp is the n-th branch
and every joint on its path to the root is inferred (the others get the tree's fixed gains).

Each (joint count, layout) runs in a fresh subprocess, so its peak resident memory (``ru_maxrss``)
and its compile time are its own, with the persistent compilation cache off:

* ``compile_s``: ``jax.jit(simulate).lower(...).compile()`` for P parameter sets x 1 profile x T
  observation steps (tracing + XLA), wall seconds;
* ``peak_rss_mb``: the subprocess's peak resident memory after compiling and running;
* ``obs_steps_per_s``: P x T / wall seconds of one compiled call (median of ``--reps``), with a
  fixed ``--substeps`` physics steps per observation for every size (the stability step of
  L-system trees shrinks with their thinnest twigs, which would mix step cost and step count).

Layouts: ``auto`` (what the simulator uses), ``scalar`` (:mod:`treeinfer.sim.fused`, run up to
``--max-scalar-joints``) and ``levels`` (:mod:`treeinfer.sim.levels`). Results go to
``experiments/results/benchmarks/<machine>.json`` under ``compile_scaling``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

from benchmarks._common import RESULTS_DIR, default_machine_name, merge_results

DEFAULT_JOINTS = "1,3,6,12,25,50,100,120,200"


def tree_with_joints(n: int):
    """A prefix of n branches of the generated L-system tree (see the module docstring)."""
    from treeinfer.tree import generators as gen
    from treeinfer.tree import make_tree

    full = gen.lsystem("F", {"F": "F[+F][-F]F"}, 5, angle_deg=25, step_length=0.3)
    branches = list(full.branches[:n])
    parent = {b.name: b.parent for b in branches}
    depth, cur = 0, branches[-1].name
    while cur is not None:
        depth, cur = depth + 1, parent[cur]
    return make_tree(branches, grasp_branch=branches[-1].name, levels=depth, name=f"lsystem{n}")


def _child(args) -> dict:
    """Measure one (joints, layout) in this process; prints one JSON line."""
    import dataclasses
    import resource

    import jax
    import jax.numpy as jnp
    import numpy as np

    from treeinfer.sim import make_simulator, simulate
    from treeinfer.sim.fused_backend import uses_levels

    tree = tree_with_joints(args.joints)
    sim = make_simulator(tree, obs_dt=0.01, substeps=args.substeps)
    sim = dataclasses.replace(sim, step_layout=args.layout)
    r = tree.n_inferred
    rng = np.random.default_rng(0)
    kp = jnp.asarray(rng.uniform(50.0, 200.0, (args.particles, r)))
    kd = jnp.asarray(rng.uniform(0.5, 2.0, (args.particles, r)))
    t = np.arange(args.steps) * 0.01
    forces = jnp.asarray((np.clip(t / 0.5, 0.0, 1.0) * 5.0)[None])
    fn = jax.jit(lambda a, b, f: simulate(sim, a, b, f))
    c0, t0 = time.process_time(), time.perf_counter()
    lowered = fn.lower(kp, kd, forces)
    t1 = time.perf_counter()
    compiled = lowered.compile()
    t2, c2 = time.perf_counter(), time.process_time()
    out = compiled(kp, kd, forces)
    jax.block_until_ready(out)
    walls, cpus = [], []
    for _ in range(args.reps):
        s, c = time.perf_counter(), time.process_time()
        jax.block_until_ready(compiled(kp, kd, forces))
        walls.append(time.perf_counter() - s)
        cpus.append(time.process_time() - c)
    wall = float(np.median(walls))
    stable = float(np.mean(np.asarray(out.stable)))
    return {
        "joints": args.joints,
        "inferred": r,
        "layout": args.layout,
        "levels": bool(uses_levels(sim)),
        "depth": _depth(sim),
        "lower_s": t1 - t0,
        "compile_s": t2 - t0,
        "xla_compile_s": t2 - t1,
        "compile_cpu_s": c2 - c0,
        "call_cpu_s": float(np.median(cpus)),
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "call_s": wall,
        "obs_steps_per_s": args.particles * args.steps / wall,
        "physics_steps_per_s": args.particles * args.steps * args.substeps / wall,
        "stable_share": stable,
        "particles": args.particles,
        "steps": args.steps,
        "substeps": args.substeps,
        "platform": jax.devices()[0].platform,
        "load_average": os.getloadavg(),
    }


def _depth(sim) -> int:
    from treeinfer.sim.levels import layout

    return layout(sim.hinge_tree).depth


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--joints", default=DEFAULT_JOINTS, help="comma-separated joint counts")
    p.add_argument("--layouts", default="auto,scalar,levels")
    p.add_argument("--max-scalar-joints", type=int, default=25)
    p.add_argument("--particles", type=int, default=None, help="default: 64 CPU, 4096 GPU")
    p.add_argument("--steps", type=int, default=100)
    p.add_argument("--substeps", type=int, default=2)
    p.add_argument("--reps", type=int, default=3)
    p.add_argument("--timeout", type=float, default=900.0, help="s per subprocess")
    p.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    p.add_argument("--machine", default=None, help="results file name (default: from host)")
    p.add_argument("--no-save", action="store_true")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--layout", default="auto", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.particles is None:
        args.particles = 64 if args.device == "cpu" else 4096
    if args.child:
        args.joints = int(args.joints)
        print("RESULT " + json.dumps(_child(args)), flush=True)
        return 0
    env = dict(os.environ, JAX_PLATFORMS=args.device, TREEINFER_JAX_CACHE="off")
    env["JAX_ENABLE_COMPILATION_CACHE"] = "false"
    env.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    rows = []
    print(
        f"{'joints':>6} {'layout':>7} {'depth':>5} {'compile s':>9} {'(cpu s)':>8} "
        f"{'peak MB':>8} {'obs-steps/s':>12} {'load':>5}"
    )
    for n in [int(x) for x in args.joints.split(",")]:
        for layout in args.layouts.split(","):
            if layout == "scalar" and n > args.max_scalar_joints:
                continue
            cmd = [sys.executable, "-m", "benchmarks.compile_scaling", "--child"]
            cmd += ["--joints", str(n), "--layout", layout, "--device", args.device]
            for k in ("particles", "steps", "substeps", "reps"):
                cmd += [f"--{k}", str(getattr(args, k))]
            try:
                res = subprocess.run(
                    cmd, env=env, capture_output=True, text=True, timeout=args.timeout
                )
            except subprocess.TimeoutExpired:
                row = {"joints": n, "layout": layout, "timeout_s": args.timeout}
                rows.append(row)
                print(f"{n:>6} {layout:>7} timed out after {args.timeout:g} s", flush=True)
                continue
            lines = [x for x in res.stdout.splitlines() if x.startswith("RESULT ")]
            if res.returncode or not lines:
                print(f"{n:>6} {layout:>7} failed:\n{res.stderr[-2000:]}", flush=True)
                rows.append({"joints": n, "layout": layout, "error": res.stderr[-500:]})
                continue
            row = json.loads(lines[-1][7:])
            rows.append(row)
            print(
                f"{n:>6} {layout:>7} {row['depth']:>5} {row['compile_s']:>9.2f} "
                f"{row['compile_cpu_s']:>8.2f} {row['peak_rss_mb']:>8.0f} "
                f"{row['obs_steps_per_s']:>12.4g} "
                f"{row['load_average'][0]:>5.1f}",
                flush=True,
            )
    if not args.no_save:
        from benchmarks._common import machine_info

        name = args.machine or default_machine_name()
        results = {"machine": machine_info(), "settings": vars(args), "rows": rows}
        path = merge_results(RESULTS_DIR / f"{name}.json", "compile_scaling", results, {})
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
