"""An independent reference for the time-to-posterior benchmark: long Metropolis-Hastings.

``benchmarks/time_to_posterior.py`` judges a fast posterior by its 95% predictive band against
a reference posterior's. Its two references disagree: NNSVGD after 400 iterations (the paper's
sampler) gives a band 10-16% narrower than 16 384 Student-t importance draws. This script
settles which is right with a third method that shares neither's approximation: P random-walk
MH chains (:func:`treeinfer.inference.mh`, the library's sampler) on the same standard problem,
started from the importance draws, proposal ``2.38 / sqrt(D)`` times their covariance's
Cholesky factor, warm-up discarded, thinned; R-hat (ArviZ, rank-normalised split) over the
chains. Its band is reported the way the benchmark reports the importance reference's: the
mean over consecutive ``--particles``-draw subsets (the same KDE smoothing as a run's).

    python -m benchmarks.mh_reference [--chains 128] [--iterations 4000] [--thin 10]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--chains", type=int, default=128, help="MH chains (default 128)")
    p.add_argument("--iterations", type=int, default=4000, help="MH steps per chain")
    p.add_argument("--warmup", type=float, default=0.5, help="share of steps discarded")
    p.add_argument("--thin", type=int, default=10, help="keep every N-th step after warm-up")
    p.add_argument("--particles", type=int, default=128, help="draws per band subset")
    p.add_argument("--substeps", type=int, default=None, help="as time_to_posterior's")
    p.add_argument("--out", default=None, help="write the record here (JSON)")
    args = p.parse_args(argv)

    import jax

    from benchmarks._ttp_child import DT, N_STEPS
    from benchmarks.inference import EXAMPLES
    from benchmarks.time_to_posterior import reference_metrics, write_data
    from treeinfer.data.trajectories import Trajectory
    from treeinfer.inference import fast_posterior, infer, make_problem
    from treeinfer.inference.diagnostics import arviz_compat
    from treeinfer.sim import make_simulator
    from treeinfer.tree import load_tree

    t0 = time.time()
    with tempfile.TemporaryDirectory() as tmp:
        write_data(Path(tmp))
        data = dict(np.load(Path(tmp) / "data.npz"))
    tree = load_tree(EXAMPLES / "three_branch.yaml")
    t = np.arange(N_STEPS) * DT
    trajs = [
        Trajectory(t, f, x, v, f"pull{i}")
        for i, (f, x, v) in enumerate(
            zip(data["train_force"], data["train_tau"], data["train_tau_dot"])
        )
    ]
    problem = make_problem(tree, trajs, substeps=args.substeps, likelihood="boltzmann")
    start = fast_posterior(problem, args.chains, n_starts=8, seed=0)
    theta0 = np.asarray(start.theta, np.float64)
    cov = np.cov(theta0.T)
    scale = 2.38 / np.sqrt(theta0.shape[1]) * np.linalg.cholesky(cov)
    post = infer(
        problem,
        "mh",
        n_particles=args.chains,
        n_iterations=args.iterations,
        seed=1,
        progress=False,
        initial_theta=theta0.astype(np.float32),
        proposal_scale=scale,
    )
    run = post.run
    it = np.asarray(run.trace_iterations)
    keep = it > args.warmup * args.iterations
    pos = np.asarray(run.trace_positions)[keep][:: args.thin]  # [n, chains, D]
    rhat = arviz_compat.rhat(np.swapaxes(pos, 0, 1))
    rhat = np.asarray(rhat["x"])
    accept = float(np.nanmean(np.asarray(run.diagnostics.get("mean_acceptance_rate", np.nan))))
    draws = pos.reshape(-1, pos.shape[-1])
    rng = np.random.default_rng(0)
    draws = draws[rng.permutation(len(draws))]  # subsets mix chains and steps
    sim = make_simulator(tree, obs_dt=DT, accuracy="coarse")
    band = reference_metrics(sim, draws, data["test_force"], data["test_tau"], args.particles)
    record = {
        "command": "python -m benchmarks.mh_reference " + " ".join(argv or sys.argv[1:]),
        "chains": args.chains,
        "iterations": args.iterations,
        "warmup": args.warmup,
        "thin": args.thin,
        "n_draws": int(len(draws)),
        "rhat_max": float(np.max(rhat)),
        "rhat": rhat.tolist(),
        "acceptance": accept,
        "importance_start": {k: start.settings.get(k) for k in ("khat", "ess", "ok")},
        "band_mm": band["ci_width_m"] * 1e3,
        "pct_outside": band["pct_outside"],
        "n_subsets": band.get("n_subsets", 1),
        "seconds": time.time() - t0,
        "device": str(jax.devices()[0]),
    }
    print(
        f"MH reference: {record['n_draws']} draws ({args.chains} chains x {args.iterations} "
        f"steps, warm-up {args.warmup:g}, thin {args.thin}), R-hat max {record['rhat_max']:.3f}, "
        f"acceptance {accept:.2f}: band {record['band_mm']:.2f} mm, "
        f"{record['pct_outside']:.1f}% outside ({record['seconds']:.0f} s)"
    )
    if args.out:
        Path(args.out).write_text(json.dumps(record, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
