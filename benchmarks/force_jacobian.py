"""Cost of the errors-in-variables force Jacobian ``J = d tau / d F`` (the default likelihood's
most repeated program: the reference, the bias slope's 2R forward differences, the training
fit's band), through the sensitivity rule and through the plain JVP of the step code.

    JAX_PLATFORMS=cpu python -m benchmarks.force_jacobian [--tree three_branch] [--samples 300]

The standard problem's shape by default: ``three_branch``, 3 pulls of ``--samples`` samples at
10 ms, the step ``infer`` picks for it (``--substeps``, 14), float32 as ``infer``. For each path
(``rule``: :data:`treeinfer.sim.fused_backend.SENSITIVITY_RULE` on, ``plain``: off; both read at
trace time) it prints the process CPU seconds of the first call (trace + compile + run) and the
median of ``--reps`` more calls, and the largest difference between the two Jacobians relative
to the largest entry. ``--tree`` also takes a tree file; ``--qsm FILE`` converts a QSM (the
chain from the shared sapling's grasp point, joints every ``--joint-spacing`` m), as
``benchmarks/qsm_compile.py`` does; ``--substeps 0``: the simulator's own step. No timed
assertions: figures for BENCHMARKS.md.

    python -m benchmarks.force_jacobian --qsm ../shared/data/qsm/treeqsm_QSM.mat \
        --samples 50 --substeps 0   # docs/qsm.md's measurement
"""

from __future__ import annotations

import argparse
import time


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tree", default="three_branch", help="built-in example name or tree file")
    ap.add_argument("--samples", type=int, default=300)
    ap.add_argument("--pulls", type=int, default=3)
    ap.add_argument("--substeps", type=int, default=14)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--paths", default="rule,plain")
    ap.add_argument("--qsm", help="a QSM file: the chain to the sapling's grasp point")
    ap.add_argument("--joint-spacing", type=float, default=1.0)
    args = ap.parse_args(argv)

    import jax
    import numpy as np

    from treeinfer.examples import example_path
    from treeinfer.model.force_noise import force_jacobian
    from treeinfer.sim import fused_backend as fb
    from treeinfer.sim import make_simulator
    from treeinfer.tree.description import load_tree

    if args.qsm:
        from benchmarks.qsm_compile import GRASP
        from treeinfer.tree import tree_from_qsm

        tree = tree_from_qsm(args.qsm, grasp_point=GRASP, joint_spacing=args.joint_spacing).tree
    else:
        try:
            tree = load_tree(example_path(args.tree))
        except Exception:  # noqa: BLE001 -- not an example name: a tree file
            tree = load_tree(args.tree)
    sim = make_simulator(tree, obs_dt=0.01, substeps=args.substeps or None)
    print(f"{sim.n_joints} joints, {sim.substeps} substeps, {args.pulls} x {args.samples} samples")
    t = np.arange(args.samples) * 0.01
    rng = np.random.default_rng(0)
    peak = rng.uniform(5.0, 15.0, args.pulls)
    forces = peak[:, None] * np.clip(t / (0.4 * t[-1]), 0, 1)[None] + rng.normal(
        0, 0.05, (args.pulls, args.samples)
    )
    lo, hi = (np.log(np.asarray(b, float)) for b in sim.prior_box)
    theta = 0.5 * (lo + hi)
    out, jacs = {}, {}
    for path in filter(None, args.paths.split(",")):
        fb.SENSITIVITY_RULE = path == "rule"
        jax.clear_caches()
        sim.derived.clear()  # the kept programs and Jacobians of the other path
        c0, w0 = time.process_time(), time.perf_counter()
        jacs[path] = force_jacobian(sim, theta, forces, keep=False)
        first = (time.process_time() - c0, time.perf_counter() - w0)
        runs = []
        for _ in range(args.reps):
            c0 = time.process_time()
            force_jacobian(sim, theta + 0.01 * len(runs), forces, keep=False)
            runs.append(time.process_time() - c0)
        out[path] = {"first_cpu_s": first[0], "first_wall_s": first[1], "call_cpu_s": runs}
        print(
            f"{path:6s} first call {first[0]:7.2f} CPU-s ({first[1]:.2f} s wall), then "
            f"{np.median(runs):.3f} CPU-s per call (median of {len(runs)})",
            flush=True,
        )
    if len(jacs) == 2:
        a, b = jacs.values()
        rel = float(np.max(np.abs(a - b)) / np.max(np.abs(b)))
        out["max_rel_difference"] = rel
        print(f"largest |J_rule - J_plain| / max|J_plain| = {rel:.2e}")
    fb.SENSITIVITY_RULE = True
    return out


if __name__ == "__main__":
    main()
