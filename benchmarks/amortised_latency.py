"""Latency of an amortised posterior on the CPU (issue 31 §2 target: a new recording's
posterior in < 100 ms on the 2-core CPU after training).

Loads a model (``--model``, written by ``treeinfer amortise`` or
``experiments/amortised_calibration.py``; without it, trains a small one for a 1-joint chain
first, not timed), simulates ``--recordings`` recordings of its layout, and times per recording:
the summary features plus ``--draws`` flow draws with their log densities (what ``infer
--amortised`` prints before its check), after one untimed call (compilation, or a load from the
persistent compile cache, which is timed separately as ``first_call_ms``), and the model's load.
Prints a table and, with ``--json``, writes the figures with the machine.

    JAX_PLATFORMS=cpu python -m benchmarks.amortised_latency [--model M] [--draws 1024]
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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, default=None, help="an amortised model folder")
    ap.add_argument("--draws", type=int, default=1024, help="flow draws per recording")
    ap.add_argument("--recordings", type=int, default=50)
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
        rng = np.random.default_rng(0)
        recs = []
        for _ in range(args.recordings):  # plausible recordings: forces of the family, a sag
            f = ti.data.forces.profile_set(
                lay.profile_kind, lay.n_pulls, lay.duration, lay.dt, lay.peak_range, seed=rng
            )
            x = 0.01 * f / lay.peak_range[1] + 1e-3 * rng.normal(size=f.shape)
            recs.append((f + 0.02 * rng.normal(size=f.shape), x))
        t0 = time.perf_counter()
        am.draw(*recs[0], args.draws)
        first = time.perf_counter() - t0
        times = []
        for i, (f, x) in enumerate(recs):
            t0 = time.perf_counter()
            am.draw(f, x, args.draws, seed=i)
            times.append(time.perf_counter() - t0)
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
    if args.json:
        args.json.write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
