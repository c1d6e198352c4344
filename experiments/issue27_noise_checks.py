"""Issue 27 (noise priors and verdicts): the figures of the h27noise report.

Run from the repository root after simulating the data sets it reads:

    for prof in release step mixed; do for seed in 0 1 2; do
      python -m treeinfer simulate --tree treeinfer/examples/three_branch.yaml \
        --out /tmp/h27n_sim/${prof}_$seed --profile-kind $prof --n-traj 4 --seed $seed; done; done
    python -m experiments.issue27_noise_checks

Prints: time-unit findings on treeinfer's own release/step/mixed pulls (and on the same pulls
with time in minutes), and the displacement-noise estimate of a 0.5 mm stepper and of a 50 Hz
stream written at 100 Hz, against the pre-issue-27 estimator (MAD of all second differences).
"""

from __future__ import annotations

import glob
import math

import numpy as np

from treeinfer.data import estimate_white_noise, read_trajectory, speed_limit
from treeinfer.evaluation import data_checks
from treeinfer.examples import example_path
from treeinfer.tree import load_tree, response_range


def _old_estimate(x: np.ndarray) -> float:
    d2 = np.diff(x, n=2, axis=-1).ravel()
    return 1.4826 * float(np.median(np.abs(d2 - np.median(d2)))) / math.sqrt(6)


def speed_check(pattern: str = "/tmp/h27n_sim/*") -> None:
    tree = load_tree(example_path("three_branch"))
    mob = response_range(tree)[2]
    worst, flagged, n_minutes, n = 0.0, 0, 0, 0
    for d in sorted(glob.glob(pattern)):
        trajs = [read_trajectory(p) for p in sorted(glob.glob(d + "/traj_*.csv"))]
        n += len(trajs)
        flagged += sum(f.check == "time-unit" for f in data_checks(tree, trajs))
        minutes = [t._replace(time=t.time / 60, velocity=None) for t in trajs]
        n_minutes += sum(f.check == "time-unit" for f in data_checks(tree, minutes))
        for t in trajs:
            x, f, dt = np.asarray(t.displacement), np.asarray(t.force), float(t.dt)
            limit = speed_limit(f, x, dt, mob)[0]
            worst = max(worst, float(np.max(np.abs(x[10:] - x[:-10]))) / (10 * dt) / limit)
    print(
        f"mobility {mob:.3g} 1/kg; time-unit findings on {n} simulated pulls: {flagged}; "
        f"largest speed / limit {worst:.3f}; the same pulls in minutes flagged: {n_minutes}/{n}"
    )


def estimates() -> None:
    rng = np.random.default_rng(1)
    t = np.arange(301) * 0.01
    clean = np.stack([0.05 * (1 - np.exp(-3 * t)) * (1 + 0.2 * b) for b in range(3)])
    q = 5e-4
    rec = q * np.round((clean + q / 20 * rng.standard_normal(clean.shape)) / q)
    e = estimate_white_noise(rec)
    print(
        f"0.5 mm stepper: realised rounding std {np.std(rec - clean) * 1e3:.4f} mm, "
        f"old estimate {_old_estimate(rec) * 1e3:.4f} mm, new {e.sigma * 1e3:.4f} mm ({e.method})"
    )
    tn = np.arange(160) * 0.02
    native = np.stack([0.05 * (1 - np.exp(-3 * tn)) for _ in range(3)])
    native = native + 2e-3 * rng.standard_normal(native.shape)
    up = np.stack([np.interp(np.arange(319) * 0.01, tn, r) for r in native])
    e = estimate_white_noise(up)
    print(
        f"50 Hz stream with 2 mm noise written at 100 Hz (linear): old estimate "
        f"{_old_estimate(up) * 1e3:.2g} mm, new {e.sigma * 1e3:.3f} mm (factor {e.factor})"
    )


if __name__ == "__main__":
    speed_check()
    estimates()
