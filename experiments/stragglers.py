"""Stuck particles on a small tree, and the warm-up re-initialisation that removes them.

The two-branch example (2 pulls x 1 s at 50 Hz, clean data, kT = 0.05) sampled by SVGD from
the uniform start with few iterations: particles that start where the simulated displacement is
far from the data stay behind the bulk (log density tens to hundreds of nats lower).
:func:`treeinfer.inference.find_stragglers` counts them; the same run with
``reinit_stragglers=ReinitStragglers(until=...)`` in :func:`treeinfer.inference.run` moves them
next to the bulk during the warm-up, after which the run ends with none.

    python -m experiments.stragglers --seeds 0 1 2 --particles 32 --iterations 60

Prints one line per seed and writes ``stragglers.json`` under ``--out`` if given.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

DT = 0.02
T = 50
KP_TRUE = np.array([40.0, 120.0])  # child, parent (N m/rad)
KD_TRUE = np.array([0.5, 1.5])  # child, parent (N m s/rad)


def problem():
    import jax
    import jax.numpy as jnp

    from treeinfer.data.trajectories import Trajectory
    from treeinfer.examples import example_path
    from treeinfer.inference import make_problem
    from treeinfer.sim import make_simulator, simulate
    from treeinfer.tree import load_tree

    tree = load_tree(example_path("two_branch"))
    sim = make_simulator(tree, obs_dt=DT)
    t = np.arange(T) * DT
    forces = np.stack([np.clip(t / 0.5, 0.0, 1.0) * p for p in (6.0, 10.0)])
    r = jax.jit(lambda kp, kd, f: simulate(sim, kp, kd, f))(
        jnp.asarray(KP_TRUE[None]), jnp.asarray(KD_TRUE[None]), jnp.asarray(forces)
    )
    trajs = [
        Trajectory(t, forces[b], np.asarray(r.tau[0, b], float), None, f"train{b}")
        for b in range(2)
    ]
    return make_problem(tree, trajs, kT=0.05, sim=sim, nn_prior=False, likelihood="boltzmann")


def run(seeds, n_particles, n_iterations, until, out: Path | None) -> list[dict]:
    import jax

    from treeinfer.inference import ReinitStragglers, find_stragglers, initial_particles, samplers
    from treeinfer.sim.program_cache import ProgramCache

    prob = problem()
    alg = prob.sampler("svgd")
    programs = ProgramCache()  # one compiled chunk for every seed and policy
    rows = []
    for seed in seeds:
        theta0 = initial_particles(prob, n_particles, seed)
        row = {"seed": int(seed)}
        for name, pol in (
            ("plain", None),
            ("reinit", ReinitStragglers(until, prob.lower, prob.upper)),
        ):
            res = samplers.run(
                alg,
                jax.random.key(seed),
                theta0,
                n_iterations,
                progress=False,
                chunk_size=10,
                reinit_stragglers=pol,
                cache=programs,
            )
            ld = np.asarray(res.final_state.logdensity)
            rep = find_stragglers(
                ld, res.final_positions, prob.lower, prob.upper, labels=prob.labels
            )
            row[name] = {
                "n_stragglers": rep.n_stragglers,
                "log_density_range": [float(np.nanmin(ld)), float(np.nanmax(ld))],
                "n_reinitialised": int(res.diagnostics.get("n_reinitialised", np.zeros(1)).sum()),
                "warnings": rep.warnings,
            }
        rows.append(row)
        print(
            f"seed {seed}: plain run {row['plain']['n_stragglers']} of {n_particles} stuck "
            f"(log p {row['plain']['log_density_range'][0]:.4g} .. "
            f"{row['plain']['log_density_range'][1]:.4g}); with warm-up re-init "
            f"(moved {row['reinit']['n_reinitialised']}) {row['reinit']['n_stragglers']} "
            f"stuck (log p {row['reinit']['log_density_range'][0]:.4g} .. "
            f"{row['reinit']['log_density_range'][1]:.4g})",
            flush=True,
        )
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / "stragglers.json").write_text(
            json.dumps(
                {
                    "settings": {
                        "seeds": list(map(int, seeds)),
                        "n_particles": n_particles,
                        "n_iterations": n_iterations,
                        "reinit_until": until,
                    },
                    "runs": rows,
                },
                indent=1,
            )
        )
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--particles", type=int, default=32)
    ap.add_argument("--iterations", type=int, default=60)
    ap.add_argument("--until", type=int, default=30, help="last warm-up iteration re-initialising")
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args(argv)
    run(a.seeds, a.particles, a.iterations, a.until, a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
