"""The importance path's band over seeds at the default (accuracy-controlled) step, against the
exact reference: the standard problem's training pulls (``benchmarks/time_to_posterior.py``'s
data), :func:`treeinfer.inference.fast_posterior` with the options given as JSON, one line
per seed (program runs per step, rounds, ESS, k_hat, band and its deviation).

    python -m benchmarks.fast_posterior_seeds --seeds 0-9
    python -m benchmarks.fast_posterior_seeds --seeds 0-3 --options '{"coarse_substeps": null}'

The reference band (``--reference-mm``, default 8.65) is ``ref-is-cpu.json``'s (BENCHMARKS.md,
issue 15 sixth pass). One rollout program is compiled and shared by every seed.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--seeds", default="0-9", help="a-b or comma list")
    p.add_argument("--options", default="{}", help="fast_posterior keyword options (JSON)")
    p.add_argument("--substeps", type=int, default=None, help="default: accuracy-controlled")
    p.add_argument("--reference-mm", type=float, default=8.65)
    args = p.parse_args(argv)
    a, _, b = args.seeds.partition("-")
    seeds = list(range(int(a), int(b) + 1)) if b else [int(x) for x in args.seeds.split(",")]
    options = json.loads(args.options)

    from benchmarks._ttp_child import DT, N_STEPS
    from benchmarks.inference import EXAMPLES
    from benchmarks.time_to_posterior import band_metrics, write_data
    from treeinfer.data.trajectories import Trajectory
    from treeinfer.inference import BatchEvaluator, default_chunk, fast_posterior, make_problem
    from treeinfer.sim import make_simulator
    from treeinfer.tree import load_tree

    with tempfile.TemporaryDirectory() as tmp:
        write_data(Path(tmp))
        data = dict(np.load(Path(tmp) / "data.npz"))
    tree = load_tree(EXAMPLES / "three_branch.yaml")
    t = np.arange(N_STEPS) * DT
    trajs = [
        Trajectory(t, f, a, b, f"pull{i}")
        for i, (f, a, b) in enumerate(
            zip(data["train_force"], data["train_tau"], data["train_tau_dot"])
        )
    ]
    problem = make_problem(tree, trajs, substeps=args.substeps, likelihood="boltzmann")
    band_sim = make_simulator(tree, obs_dt=DT, accuracy="coarse")
    k = options.get("n_starts", 8) * (2 * problem.dim + 1)  # fast_posterior's own batch
    ev = BatchEvaluator(problem, default_chunk(k, options.get("n_draws", max(8 * k, 4 * 128))))
    devs = []
    for seed in seeds:
        ev.runs = {}
        t0 = time.perf_counter()
        res = fast_posterior(problem, 128, seed=seed, evaluator=ev, **options)
        wall = time.perf_counter() - t0
        m = band_metrics(band_sim, res.theta, data["test_force"], data["test_tau"])
        st = res.settings
        dev = 100 * (m["ci_width_m"] * 1e3 / args.reference_mm - 1)
        devs.append(dev)
        row = {
            "seed": seed,
            "wall_s": round(wall, 2),
            "runs_by_substeps": st["program_runs_by_substeps"],
            "rounds": st["importance_rounds"],
            "ess": round(st["ess"]),
            "khat": round(st["khat"], 2),
            "band_split": round(st["band_split"], 3),
            "ok": st["ok"],
            "band_mm": round(m["ci_width_m"] * 1e3, 2),
            "deviation_pct": round(dev, 1),
            "pct_outside": round(m["pct_outside"], 1),
        }
        print(json.dumps(row), flush=True)
    d = np.asarray(devs)
    print(f"band deviation: mean {d.mean():+.1f} %, sd {d.std(ddof=1) if len(d) > 1 else 0:.1f} "
          f"%, worst {np.abs(d).max():.1f} %")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
