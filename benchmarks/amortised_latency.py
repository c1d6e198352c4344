"""Latency of an amortised posterior on the CPU (issue 31 §2 target: a new recording's
posterior in < 100 ms on the 2-core CPU after training).

Loads a model (``--model``, written by ``treeinfer amortise`` or
``experiments/amortised_calibration.py``; without it, trains a small one for a 1-joint chain
first, not timed), simulates ``--recordings`` recordings of its tree and layout from its
training distribution, and times per recording: the summary features plus ``--draws`` flow
draws with their log densities (what ``infer --amortised`` prints before its check), after one
untimed call (compilation, or a load from the persistent compile cache, which is timed
separately as ``first_call_ms``), and the model's load.

With ``--check K`` it also times, on the first K recordings, the on-the-spot check against the
simulator (:func:`treeinfer.amortised.check.amortised_start`'s start): building the run's
problem (``make_problem``), the first evaluation of its density on the rollout program
(compiled in the first recording's, then reused), and the check itself (importance weights
of the flow's draws and the refinement rounds), each recording's outcome with it, and the XLA
compilations (and persistent-cache loads) of the check: the programs live with the model
(:mod:`treeinfer.amortised.programs`), so from the second recording of a shape there are
none. Prints a table and, with ``--json``, writes the figures with the machine.

    JAX_PLATFORMS=cpu python -m benchmarks.amortised_latency [--model M] [--draws 1024] [--check 5]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def _small_model(folder: Path) -> Path:
    from treeinfer.amortised import AmortiseConfig, PullLayout, TrainConfig, save, train
    from treeinfer.tree.generators import chain

    tree = chain(1, lengths=0.7, radii=0.03, name="chain1")
    cfg = AmortiseConfig(
        PullLayout(n_pulls=3, duration=1.0),
        TrainConfig(simulations=2048, epochs=30, width=32, flow_layers=3),
    )
    path = folder / "model"
    save(train(tree, cfg), path)
    return path


def _time_check(am, tree, trajs, particles: int = 64) -> dict:
    """Seconds of the check on one recording: the problem, its density's first call, the
    check (importance weights and refinement rounds) with the density compiled."""
    import treeinfer as ti
    from treeinfer.amortised import check
    from treeinfer.sim.compile_stats import compile_stats

    force, disp = am.check_recordings(trajs)
    t0 = time.perf_counter()
    problem = ti.make_problem(tree, trajs)
    t1 = time.perf_counter()
    mark = compile_stats().mark()
    ev = check._evaluator(problem, am.programs)  # the model's programs: compiled once per shape
    draws = am.draw(force, disp, 64)[0]
    ev.log_density(draws) if ev is not None else check._log_density(problem, draws)
    t2 = time.perf_counter()
    start, report = check.amortised_start(am, force, disp)
    post = start(problem, {"options": {"particles": particles, "seed": 0}}, lambda m: None)
    compiles = compile_stats().since(mark)
    return {
        "xla_compiles": compiles["xla_compiles"],
        "cache_loads": compiles["cache_hits"],
        "problem_s": round(t1 - t0, 3),
        "compile_s": round(t2 - t1, 3),
        "check_s": round(time.perf_counter() - t2, 3),
        "used": post is not None,
        "khat": report.get("khat", float("nan")),
        "rounds": report.get("rounds"),
        "reason": report.get("reason", ""),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, default=None, help="an amortised model folder")
    ap.add_argument("--draws", type=int, default=1024, help="flow draws per recording")
    ap.add_argument("--recordings", type=int, default=50)
    ap.add_argument("--check", type=int, default=0, metavar="K", help="time the check on K")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)

    import treeinfer as ti
    from treeinfer.amortised import load

    ti.enable_compilation_cache()
    with tempfile.TemporaryDirectory() as tmp:
        path = args.model or _small_model(Path(tmp))
        t0 = time.perf_counter()
        am = load(path)
        load_s = time.perf_counter() - t0
        lay = am.config.layout
        from treeinfer.amortised.simulations import simulate_recordings
        from treeinfer.tree.description import tree_from_dict

        tree = tree_from_dict(am.meta["tree"])
        recs = simulate_recordings(tree, lay, am.config.train, args.recordings, seed=7)
        arrays = [am.check_recordings(trajs) for _, _, trajs in recs]
        t0 = time.perf_counter()
        am.draw(*arrays[0], args.draws)
        first = time.perf_counter() - t0
        times = []
        for i, (f, x) in enumerate(arrays):
            t0 = time.perf_counter()
            am.draw(f, x, args.draws, seed=i)
            times.append(time.perf_counter() - t0)
        checks = [_time_check(am, tree, trajs) for _, _, trajs in recs[: args.check]]
    ms = 1e3 * np.asarray(times)
    out = {
        "model": str(args.model or "small 1-joint model (trained here)"),
        "labels": am.labels,
        "layout": am.meta["layout"],
        "draws": args.draws,
        "recordings": args.recordings,
        "load_s": round(load_s, 3),
        "first_call_ms": round(1e3 * first, 2),
        "latency_ms": {
            "median": float(np.median(ms)),
            "p90": float(np.quantile(ms, 0.9)),
            "max": float(ms.max()),
        },
        "check": checks,
        "machine": {
            "platform": platform.platform(),
            "cpus": os.cpu_count(),
            "jax_platforms": os.environ.get("JAX_PLATFORMS", ""),
        },
    }
    print(
        f"amortised posterior, {args.draws} draws, {len(am.labels)} columns, "
        f"{lay.n_pulls} pulls x {lay.n_steps} samples:"
    )
    print(f"  load {out['load_s']:.2f} s, first call {out['first_call_ms']:.0f} ms")
    lat = out["latency_ms"]
    print(f"  latency median {lat['median']:.2f} ms, p90 {lat['p90']:.2f} ms, max {lat['max']:.2f}")
    for c in checks:
        print(
            f"  check: problem {c['problem_s']:.2f} s, first density {c['compile_s']:.2f} s, "
            f"check {c['check_s']:.3f} s ({c['rounds']} round(s), k_hat {c['khat']:.2f}, "
            f"used {c['used']}; {c['xla_compiles']} compilations, {c['cache_loads']} cache loads)"
        )
    if args.json:
        args.json.write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
