"""Simulator accuracy and the posterior: a one-joint grid posterior under three simulators.

Issue 12's check, with the independent reference of ``tests/planar_chain.py`` (Lagrange's
equations of the planar chain integrated by scipy's DOP853 at rtol 1e-11) standing in for the
exact physics. One branch (0.6 m, 15 mm radius, pitched 15 degrees up), grasped at 90% of its
length, two 3 s pulls at 10 ms (a 6 N ramp-hold-release and a 4 N smooth step). The data are
the reference's displacement at the true gains (Kp 30 N m/rad, Kd 0.3 N m s/rad) plus Gaussian
noise (sd 1 mm, seeded). The posterior of log Kp on a grid (Kd at its true value; flat prior in
log Kp; Gaussian likelihood with the true noise sd) is computed three times, with the
displacement from:

* **old**: treeinfer's previous defaults, forces held over each sample (zero-order hold) and the
  stability step capped at 5 ms;
* **new**: the new defaults, first-order hold and the step refined to 0.1 mm on these profiles;
* **exact**: the reference itself.

Printed (and written to ``experiments/results/sim_accuracy/results.json``): each posterior's
mean and sd of Kp, the largest displacement error at the truth against the reference, and the
chosen steps. The same for Kd on a grid with Kp at its true value.

    python experiments/sim_accuracy.py [--points 41] [--noise 0.001]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
if __package__ in (None, ""):  # `python experiments/sim_accuracy.py`
    sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))  # the reference lives with the tests

import numpy as np

DT, DURATION = 0.01, 3.0
TRUE_KP, TRUE_KD = 30.0, 0.3


def _posterior(grid: np.ndarray, loglik: np.ndarray) -> tuple[float, float]:
    """Mean and sd of the grid parameter under a flat prior in its log (grid log-spaced)."""
    w = np.exp(loglik - loglik.max())
    w /= w.sum()
    mean = float(w @ grid)
    return mean, float(np.sqrt(w @ (grid - mean) ** 2))


def main(argv=None) -> dict:
    import jax.numpy as jnp
    from planar_chain import PlanarTree

    from treeinfer.data import forces as F
    from treeinfer.sim import make_simulator, simulate
    from treeinfer.tree import chain

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=41, help="grid points per parameter")
    ap.add_argument("--noise", type=float, default=1e-3, help="noise sd of the data, m")
    ap.add_argument("--out", type=Path, default=ROOT / "experiments" / "results" / "sim_accuracy")
    args = ap.parse_args(argv)

    tree = chain(1, 0.6, 0.015, angles_deg=10.0, base_pitch_deg=5.0, grasp_fraction=0.9)
    prof = np.stack(
        [
            F.ramp_hold(6.0, 0.5, 0.5, 0.3, DURATION, DT, start=0.2),
            F.smooth_step(4.0, 0.3, DURATION, DT, start=0.1),
        ]
    )
    rng = np.random.default_rng(0)

    def exact(kp, kd):
        ref = PlanarTree(tree, [kp], [kd])
        return np.stack([ref.rollout(f, DT) for f in prof])

    truth = exact(TRUE_KP, TRUE_KD)
    data = truth + rng.normal(0.0, args.noise, truth.shape)
    sims = {
        "old (hold, 5 ms)": make_simulator(tree, obs_dt=DT, force_interp="hold", accuracy="coarse"),
        "new (linear, 0.1 mm)": make_simulator(tree, obs_dt=DT, forces=prof),
    }
    out = {"noise_sd_m": args.noise, "true": {"kp": TRUE_KP, "kd": TRUE_KD}, "steps": {}}
    for name, sim in sims.items():
        kp, kd = np.array([[TRUE_KP]]), np.array([[TRUE_KD]])
        tau = np.asarray(simulate(sim, kp, kd, jnp.asarray(prof)).tau[0])
        err = float(np.max(np.abs(tau - truth)))
        loss = float(np.sum((tau - truth) ** 2) / (2 * args.noise**2))
        out["steps"][name] = {
            "substeps": sim.substeps,
            "sim_dt_s": sim.sim_dt,
            "max_error_at_truth_m": err,
            "summed_loss_at_truth": loss,
        }
        print(
            f"{name}: {sim.substeps} substeps ({sim.sim_dt * 1e3:.3g} ms), at the truth max |tau "
            f"- exact| = {err * 1e3:.3f} mm, summed squared error / (2 sd^2) = {loss:.3f}",
            flush=True,
        )
    for which, lo, hi in (("kp", 29.2, 30.8), ("kd", 0.24, 0.36)):
        grid = np.exp(np.linspace(np.log(lo), np.log(hi), args.points))
        kp = grid if which == "kp" else np.full_like(grid, TRUE_KP)
        kd = grid if which == "kd" else np.full_like(grid, TRUE_KD)
        res = {}
        t0 = time.perf_counter()
        taus = {"exact": np.stack([exact(a, b) for a, b in zip(kp, kd)])}
        for name, sim in sims.items():
            roll = simulate(sim, kp[:, None], kd[:, None], jnp.asarray(prof))
            taus[name] = np.asarray(roll.tau)
        for name, tau in taus.items():
            ll = -np.sum((tau - data[None]) ** 2, axis=(1, 2)) / (2 * args.noise**2)
            mean, sd = _posterior(grid, ll)
            res[name] = {"mean": mean, "sd": sd}
            print(f"{which}: {name:22s} posterior {mean:.3f} +- {sd:.3f}", flush=True)
        out[which] = res
        print(f"  ({which} grid of {args.points}: {time.perf_counter() - t0:.0f} s)", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(out, indent=2) + "\n")
    return out


if __name__ == "__main__":
    main()
