"""Where the time to a posterior goes: the standard problem's start-up, phase by phase.

Runs the standard problem (three-branch example, R = 3, 128 particles, 3 trajectories of 300
steps, NNSVGD, 200 iterations) once, in a fresh process, and prints wall seconds for each phase:
imports, simulator build, synthetic data, the NN prior (trained, or loaded from its cache),
problem set-up, then ``infer`` split into compilation (every XLA compile, from JAX's own
compile log) and the rest. Run it twice to see the warm-cache figures (``--compile-cache DIR``
turns on JAX's persistent compilation cache; ``TREEINFER_CACHE`` holds the NN prior)::

    python -m benchmarks.startup --compile-cache /tmp/jaxcache --out results.json   # cold
    python -m benchmarks.startup --compile-cache /tmp/jaxcache --out results.json   # warm
"""

from __future__ import annotations

import argparse
import json
import logging
import re
import sys
import time

T0 = time.perf_counter()


class CompileLog(logging.Handler):
    """Collects 'Finished XLA compilation of <name> in <s> sec' lines from JAX's logger."""

    pattern = re.compile(r"Finished XLA compilation of (.+) in ([0-9.e+-]+) sec")

    def __init__(self):
        super().__init__(logging.DEBUG)
        self.entries: list[tuple[str, float]] = []

    def emit(self, record):
        m = self.pattern.search(record.getMessage())
        if m:
            self.entries.append((m.group(1), float(m.group(2))))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--particles", type=int, default=128)
    p.add_argument("--iterations", type=int, default=200)
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--backend", default="fused", choices=["fused", "mjx"])
    p.add_argument("--compile-cache", default=None, help="JAX persistent compilation cache folder")
    p.add_argument("--out", default=None, help="append this run's phases to a JSON list here")
    args = p.parse_args(argv)

    phases: dict[str, float] = {}
    mark = [time.perf_counter()]

    def phase(name):
        now = time.perf_counter()
        phases[name] = now - mark[0]
        mark[0] = now

    import jax

    import treeinfer
    from benchmarks.inference import EXAMPLES
    from treeinfer.inference import infer, make_problem

    phases["imports_before_main"] = mark[0] - T0
    phase("imports")
    if args.compile_cache:
        treeinfer.enable_compilation_cache(args.compile_cache)
    log = CompileLog()
    logging.getLogger("jax").addHandler(log)
    logging.getLogger("jax").setLevel(logging.DEBUG)
    jax.config.update("jax_log_compiles", True)

    import numpy as np

    from treeinfer.data import profile_set
    from treeinfer.data.trajectories import Trajectory
    from treeinfer.sim import make_simulator
    from treeinfer.sim.reference import simulate_reference
    from treeinfer.sim.synthetic import default_true_params
    from treeinfer.tree import load_tree

    tree = load_tree(EXAMPLES / "three_branch.yaml")
    sim = make_simulator(tree, obs_dt=0.01, backend=args.backend, accuracy="coarse")
    phase("make_simulator")
    kp, kd = default_true_params(tree, np.random.default_rng(0))
    forces = profile_set("mixed", n=3, duration=args.steps * 0.01, dt=0.01, seed=0)[:, : args.steps]
    t = np.arange(args.steps) * 0.01
    trajs = [
        Trajectory(t, f, *simulate_reference(sim, kp, kd, f), f"pull{i}")
        for i, f in enumerate(forces)
    ]
    phase("synthetic_data_c_reference")
    from treeinfer.inference import nn_inequality_prior

    nn_inequality_prior(tree)
    phase("nn_prior_train_or_load")
    n_before = len(log.entries)
    problem = make_problem(tree, trajs, sim=sim, likelihood="boltzmann")
    phase("make_problem")
    posterior = infer(
        problem,
        "nnsvgd",
        n_particles=args.particles,
        n_iterations=args.iterations,
        seed=0,
        progress=False,
    )
    phase("infer")
    compiles = log.entries[n_before:]
    compile_s = sum(s for _, s in compiles)
    top = sorted(compiles, key=lambda e: -e[1])[:6]
    total = sum(v for k, v in phases.items())
    result = {
        "backend": sim.backend,
        "device": str(jax.devices()[0].device_kind),
        "phases_s": phases,
        "total_s": total,
        "time_to_posterior_s_excluding_imports_and_data": total
        - phases["imports_before_main"]
        - phases["imports"]
        - phases["synthetic_data_c_reference"],
        "infer_compile_s": compile_s,
        "infer_compiles": len(compiles),
        "infer_largest_compiles": [{"name": n, "s": s} for n, s in top],
        "finite_particles": int(np.isfinite(posterior.log_density).sum()),
        "compile_cache": args.compile_cache,
    }
    for k, v in phases.items():
        print(f"{k:>30}: {v:7.2f} s")
    print(
        f"{'infer: XLA compilation':>30}: {compile_s:7.2f} s in {len(compiles)} compiles; largest: "
        + ", ".join(f"{n[:40]} {s:.2f}s" for n, s in top[:3])
    )
    print(
        f"{'total':>30}: {total:7.2f} s; without imports and data generation: "
        f"{result['time_to_posterior_s_excluding_imports_and_data']:.2f} s"
    )
    if args.out:
        from pathlib import Path

        path = Path(args.out)
        runs = json.loads(path.read_text()) if path.is_file() else []
        runs.append(result)
        path.write_text(json.dumps(runs, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
