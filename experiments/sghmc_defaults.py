"""Which SGHMC settings actually move on the built-in examples? (issue 11, section 3)

For the two- and three-branch examples (clean synthetic pulls, kT = 0.05) SGHMC runs from the
uniform start with several (step size, friction, optimiser) settings; for each it reports the
mean distance travelled by a chain (in prior-box widths, averaged over parameters), the median
per-step move over the second half (a proposal-free mobility proxy: SGHMC has no acceptance
rate), the post-warm-up bulk ESS (all chains, first half discarded, arviz), R-hat, the share
of chains ending unstable, and the final mean log density.

    python -m experiments.sghmc_defaults --trees two_branch three_branch --iterations 300

Writes ``sghmc_defaults.json`` under ``--out`` if given.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

# (name, constructor kwargs); "adam" = the inference layer's defaults of today (Adam-driven drift)
CANDIDATES = {
    "today (eps 1e-4, alpha 0.1, adam 0.05)": {"step_size": 1e-4, "alpha": 0.1, "adam": 0.05},
    "eps 1e-3, alpha 1": {"step_size": 1e-3, "alpha": 1.0},
    "eps 3e-3, alpha 1": {"step_size": 3e-3, "alpha": 1.0},
    "eps 1e-2, alpha 1": {"step_size": 1e-2, "alpha": 1.0},
    "eps 1e-2, alpha 10": {"step_size": 1e-2, "alpha": 10.0},
}


def problem(tree_name: str):
    import jax
    import jax.numpy as jnp

    from treeinfer.data.trajectories import Trajectory
    from treeinfer.examples import example_path
    from treeinfer.inference import make_problem
    from treeinfer.sim import make_simulator, simulate
    from treeinfer.tree import load_tree

    tree = load_tree(example_path(tree_name))
    r = tree.n_inferred
    kp = np.geomspace(300.0, 60.0, r)[::-1]  # child first (columns follow parameter_labels)
    kd = np.geomspace(2.0, 0.33, r)[::-1]
    dt, n = 0.02, 50
    sim = make_simulator(tree, obs_dt=dt)
    t = np.arange(n) * dt
    forces = np.stack([np.clip(t / 0.4, 0.0, 1.0) * p for p in (5.0, 9.0)])
    roll = jax.jit(lambda a, b, f: simulate(sim, a, b, f))(
        jnp.asarray(kp[None]), jnp.asarray(kd[None]), jnp.asarray(forces)
    )
    trajs = [
        Trajectory(t, forces[b], np.asarray(roll.tau[0, b], float), None, f"p{b}") for b in range(2)
    ]
    return make_problem(tree, trajs, kT=0.05, sim=sim, nn_prior=False, likelihood="boltzmann")


def measure(prob, settings: dict, n_particles: int, n_iterations: int, seed: int) -> dict:
    import jax
    import optax

    from treeinfer.inference import initial_particles, mcmc_summary, samplers

    kw = dict(settings)
    adam = kw.pop("adam", None)
    if adam is not None:
        kw["optimizer"] = optax.adam(adam)
    alg = samplers.sghmc(prob.value_and_grad, **kw)
    theta0 = initial_particles(prob, n_particles, seed)
    t0 = time.perf_counter()
    res = samplers.run(alg, jax.random.key(seed), theta0, n_iterations, progress=False)
    tr = res.trace_positions  # [S, C, D]
    width = prob.upper - prob.lower
    travel = np.nanmean(np.abs(tr[-1] - tr[0]) / width)
    half = tr[tr.shape[0] // 2 :]
    step = np.nanmedian(np.linalg.norm(np.diff(half, axis=0) / width, axis=-1))
    summ = mcmc_summary(tr, prob.labels, warmup=0.5)
    d = summ["diagnostics"]
    ld = res.trace_logdensity[-1]
    return {
        "mean_travel_box_widths": float(travel),
        "median_step_box_widths": float(step),
        "ess_bulk_min": d["ess_bulk_min"],
        "rhat_max": d["rhat_max"],
        "frac_unstable": float(np.mean(~np.isfinite(ld))),
        "final_mean_log_density": float(np.nanmean(np.where(np.isfinite(ld), ld, np.nan))),
        "seconds": round(time.perf_counter() - t0, 1),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trees", nargs="+", default=["two_branch", "three_branch"])
    ap.add_argument("--particles", type=int, default=16)
    ap.add_argument("--iterations", type=int, default=300)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--only", nargs="*", default=None, help="candidate names to run")
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args(argv)
    out = {}
    for tree in a.trees:
        prob = problem(tree)
        for name, settings in CANDIDATES.items():
            if a.only and name not in a.only:
                continue
            m = measure(prob, settings, a.particles, a.iterations, a.seed)
            out[f"{tree} | {name}"] = {"settings": settings, **m}
            print(
                f"{tree:12s} {name:40s} travel {m['mean_travel_box_widths']:.3f} "
                f"step {m['median_step_box_widths']:.2e} ESS {m['ess_bulk_min']:.1f} "
                f"R-hat {m['rhat_max']:.2f} unstable {m['frac_unstable']:.2f} "
                f"logp {m['final_mean_log_density']:.4g} ({m['seconds']} s)",
                flush=True,
            )
    if a.out is not None:
        a.out.mkdir(parents=True, exist_ok=True)
        (a.out / "sghmc_defaults.json").write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
