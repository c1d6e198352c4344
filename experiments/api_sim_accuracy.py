"""How close is each way of building the simulator to an independent integration? (issue 27, 4)

On the planar cases of :mod:`experiments._planar_cases` (two- and three-joint chains; the
reference is :class:`treeinfer.sim.planar_reference.PlanarTree`, Lagrange's equations
integrated by scipy's DOP853 at rtol 1e-11), at each seed's true gains, the displacement of the
UNSEEN clean test pulls from three simulators:

* ``coarse``: ``make_simulator(tree, obs_dt, accuracy="coarse")``, the stability step only
  (the API's default before issue 27);
* ``api default``: ``make_simulator(tree, obs_dt)``, the step accuracy-controlled on the
  representative pulls (:func:`treeinfer.sim.accuracy.representative_forces`);
* ``infer``: what ``treeinfer infer`` builds, the step accuracy-controlled on the TRAINING
  pulls' forces (``make_simulator(tree, obs_dt, forces=train_forces)``, 0.1 mm).

Reported per simulator: substeps, the largest ``|tau - tau_ref|`` over the test pulls (max over
seeds), and the summed squared error over 2 sigma^2 (sigma 2 mm: the Gaussian likelihood's
loss at the truth that the simulator's error alone adds), mean over seeds; plus the time
``make_simulator`` took in this process (the first call of a kind includes its compiles).

    python experiments/api_sim_accuracy.py [--seeds 3] [--n-test 10]

Writes ``experiments/results/api_sim_accuracy/results.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from experiments._planar_cases import CASES, SIGMA_X, make_case  # noqa: E402


def main(argv=None) -> dict:
    from treeinfer.inference.problem import predict
    from treeinfer.sim import make_simulator

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--n-test", type=int, default=10)
    ap.add_argument(
        "--out", type=Path, default=ROOT / "experiments" / "results" / "api_sim_accuracy"
    )
    args = ap.parse_args(argv)
    out: dict = {"config": vars(args) | {"out": str(args.out), "sigma_m": SIGMA_X}, "cases": {}}
    for name in CASES:
        rows: dict = {}
        for seed in range(args.seeds):
            case = make_case(name, seed, n_test=args.n_test)
            builders = {
                "coarse": lambda c=case: make_simulator(c.tree, obs_dt=c.dt, accuracy="coarse"),
                "api default": lambda c=case: make_simulator(c.tree, obs_dt=c.dt),
                "infer": lambda c=case: make_simulator(c.tree, obs_dt=c.dt, forces=c.train_force),
            }
            for kind, build in builders.items():
                t0 = time.perf_counter()
                sim = build()
                built = time.perf_counter() - t0
                # the step as a traced argument: one compiled program for the three simulators
                theta = np.log(np.concatenate([case.kp, case.kd]))[None]
                tau = predict(sim, theta, case.test_force, traced_substeps=True).tau
                err = np.asarray(tau[0], float) - case.test_tau
                r = rows.setdefault(
                    kind, {"substeps": [], "max_err_m": [], "loss": [], "build_s": []}
                )
                r["substeps"].append(int(sim.substeps))
                r["max_err_m"].append(float(np.max(np.abs(err))))
                r["loss"].append(float(np.sum(err**2) / (2 * SIGMA_X**2)))
                r["build_s"].append(built)
        for kind, r in rows.items():
            r["max_err_mm_max"] = 1e3 * max(r["max_err_m"])
            r["max_err_mm_range"] = [1e3 * min(r["max_err_m"]), 1e3 * max(r["max_err_m"])]
            r["loss_mean"] = float(np.mean(r["loss"]))
            print(
                f"{name} {kind:12s} substeps {r['substeps']}, max |tau - ref| "
                f"{r['max_err_mm_range'][0]:.3f}-{r['max_err_mm_range'][1]:.3f} mm, summed loss "
                f"{min(r['loss']):.4f}-{max(r['loss']):.4f}, build {np.round(r['build_s'], 1)} s",
                flush=True,
            )
        out["cases"][name] = rows
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(out, indent=2) + "\n")
    return out


if __name__ == "__main__":
    main()
