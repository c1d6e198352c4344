"""How long ``treeinfer.design.score_candidates`` takes to rank 100 candidate pulls.

    python -m benchmarks.suggest                  # 2-branch example, 100 candidates, 64 particles
    python -m benchmarks.suggest --tree three_branch --candidates 150 --particles 128 --repeats 5

Posterior particles: a fixed, seeded Gaussian cloud around mid-box gains (the timing does not
depend on their values, only on their number). Candidates: grasp fractions x peak forces of
ramp pulls (10 x 10 = 100 by default), 1 s at 0.02 s. Prints the first call (trace + compile +
run, as a fresh ``treeinfer suggest`` process pays without a warm compilation cache) and the
warm calls (median of ``--repeats``), for the Laplace EIG and, with ``--target``, the target
variant. Issue 16's target: under 10 s on the 2-core CPU for the 2-branch example.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m benchmarks.suggest", description=__doc__.split("\n")[0]
    )
    p.add_argument("--tree", default="two_branch", help="example name (default two_branch)")
    p.add_argument(
        "--candidates", type=int, default=100, help="number of candidates (a ~square grid)"
    )
    p.add_argument("--particles", type=int, default=64, help="posterior particles")
    p.add_argument(
        "--design-particles", type=int, default=32, help="particles the sensitivities are taken at"
    )
    p.add_argument("--duration", type=float, default=1.0)
    p.add_argument("--dt", type=float, default=0.02)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument(
        "--target", default=None, help="also time the target variant, e.g. grasp=0.5,peak=5"
    )
    p.add_argument(
        "--no-cache", action="store_true", help="do not use the persistent compilation cache"
    )
    args = p.parse_args(argv)

    t_start = time.perf_counter()
    import treeinfer

    if not args.no_cache:
        treeinfer.enable_compilation_cache()
    import jax

    from benchmarks._common import machine_info
    from treeinfer import make_simulator
    from treeinfer.design import candidate_grid, parse_target, score_candidates
    from treeinfer.tree import load_tree

    tree = load_tree(ROOT / "treeinfer" / "examples" / f"{args.tree}.yaml")
    sim = make_simulator(tree, obs_dt=args.dt, accuracy="coarse")
    lo, hi = (np.log(b) for b in tree.bounds_array())
    rng = np.random.default_rng(0)
    theta = (
        0.5 * (lo + hi) + 0.15 * (hi - lo) * rng.standard_normal((args.particles, len(lo)))
    ).astype(np.float32)
    n_g = int(np.ceil(np.sqrt(args.candidates)))
    n_f = int(np.ceil(args.candidates / n_g))
    cands = candidate_grid(np.linspace(0.1, 1.0, n_g), np.linspace(1.0, 10.0, n_f))[
        : args.candidates
    ]
    setup_s = time.perf_counter() - t_start
    info = machine_info()
    print(
        f"{info['device_kind']} ({info['host_cores']} cores, "
        f"load {info['load_average_at_start']}), "
        f"jax {info['jax']}, {sim.backend} backend, {sim.substeps} substeps"
    )
    print(
        f"{args.tree}: D = {theta.shape[1]}, {len(cands)} candidates, {args.particles} particles "
        f"({args.design_particles} for the sensitivities), T = {round(args.duration / args.dt)}; "
        f"setup {setup_s:.1f} s"
    )

    variants = [("eig", None)] + ([("target", parse_target(args.target))] if args.target else [])
    for name, target in variants:
        call = lambda seed, target=target: score_candidates(
            sim,
            theta,
            cands,
            0.002,
            args.duration,
            n_particles=args.design_particles,
            target=target,
            seed=seed,
        )
        t0 = time.perf_counter()
        s = call(0)
        first = time.perf_counter() - t0
        warm = []
        for r in range(args.repeats):
            t0 = time.perf_counter()
            call(r + 1)
            warm.append(time.perf_counter() - t0)
        print(
            f"{name:>6}: first call {first:.2f} s (trace + compile + run), "
            f"warm median {statistics.median(warm):.2f} s "
            f"over {args.repeats}; {s.settings['cost_rollouts']} rollouts per call; best {s.best}"
        )
    print(
        f"total process time {time.perf_counter() - t_start:.1f} s (jax devices: {jax.devices()})"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
