"""A sideways push at three grasp heights, end to end through the command line (issue 13).

A vertical two-link stem (hinge chain) is pushed horizontally at three heights; the pushes are
simulated by plain MuJoCo (``treeinfer.sim.reference``: float64 ``mj_step``, an integrator
independent of treeinfer's fused one), with Gaussian displacement noise, and written as raw
logger CSVs in ms, gf and mm. Then, as a user would:

1. ``treeinfer import-csv`` per height (units, grasp branch and fraction, ``--direction
   horizontal``) into a training folder (the low and top heights) and a test folder (the
   middle height); each folder gets its ``pulls.yaml``;
2. ``treeinfer infer --likelihood gaussian --sampler mh`` (sigma_x inferred) on the two
   training heights: the dynamic model fits every pull at its own branch, point and direction
   jointly (Metropolis-Hastings: no gradients, one rollout per chain and step; its summaries use
   every chain's post-warm-up trace; SVGD from the uniform start had not converged after 400
   iterations at this size);
3. ``treeinfer evaluate`` on the held-out middle height: the share of its noisy points inside
   the 95% predictive band (target 93-97%, issue 11's calibration rate) and the RMSE.

    JAX_PLATFORMS=cpu python experiments/sideways_push.py --size cpu   # committed results
    python experiments/sideways_push.py --size full                    # GPU: more pulls, seeds

Results: ``experiments/results/sideways_push/<size>.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

if __name__ == "__main__":  # run as a script from anywhere: use this checkout's treeinfer
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np

from treeinfer.cli.main import main
from treeinfer.data import forces as F
from treeinfer.data.direction import pull_direction
from treeinfer.io.atomic import atomic_write_text
from treeinfer.sim import make_simulator
from treeinfer.sim.reference import simulate_reference
from treeinfer.tree import chain
from treeinfer.tree.description import Bounds, dump_tree

# true gains in the simulator's joint order, tree.inferred = (branch1, branch0): the upper
# hinge first, then the base hinge
KP = np.array([40.0, 20.0])  # N m/rad
KD = np.array([0.4, 0.2])  # N m s/rad
# (label, branch, fraction of its 0.5 m length): heights 0.3 m, 0.7 m and 1.0 m
HEIGHTS = (("low", "branch0", 0.6), ("mid", "branch1", 0.4), ("top", "branch1", 1.0))
TRAIN, TEST = ("low", "top"), ("mid",)
DT = 0.01  # s
G0 = 9.80665  # m/s^2 per kgf

SIZES = {
    # pulls per height, seconds per pull, particles, iterations, seeds
    "tiny": dict(pulls=1, seconds=1.0, particles=4, iterations=3, seeds=(0,)),
    "cpu": dict(pulls=2, seconds=2.0, particles=64, iterations=1500, seeds=(0,)),
    "full": dict(pulls=4, seconds=3.0, particles=128, iterations=3000, seeds=(0, 1, 2, 3, 4)),
}


def stem_tree():
    """The vertical two-link stem (0.5 m links, 12 mm radius); prior box Kp 10-100 N m/rad,
    Kd 0.1-1.5 N m s/rad."""
    return chain(
        2,
        0.5,
        0.012,
        base_pitch_deg=90.0,
        bounds=Bounds(kp=(10.0, 100.0), kd=(0.1, 1.5)),
        name="sideways-stem",
    )


def write_raw_logs(folder: Path, tree, pulls: int, seconds: float, noise_mm: float, seed: int):
    """Raw logger CSVs ``push_<height>_<k>.csv`` (``t_ms,load_gf,pos_mm``), one per pull.

    Each pull is a ramp-hold-release horizontal push with random peak (0.8-2 N) and timing,
    simulated at the true gains by MuJoCo C; ``noise_mm`` Gaussian noise on the position, which
    the logger records from the branch's rest (so the import keeps ``--zero-displacement none``:
    zeroing at the first noisy sample would shift a whole pull by that sample's noise).
    Returns ``{height label: [paths]}``."""
    rng = np.random.default_rng(seed)
    sim = make_simulator(tree, obs_dt=DT, substeps=20)  # 0.5 ms steps
    folder.mkdir(parents=True, exist_ok=True)
    out = {}
    for label, branch, frac in HEIGHTS:
        d = pull_direction(tree, "horizontal", branch)
        out[label] = []
        for k in range(pulls):
            f = F.ramp_hold(
                rng.uniform(0.8, 2.0),
                rng.uniform(0.2, 0.5),
                rng.uniform(0.1, 0.4),
                rng.uniform(0.1, 0.3),
                seconds,
                DT,
                start=0.1,
            )
            tau, _ = simulate_reference(sim, KP, KD, f, frac, direction=d, grasp_branch=branch)
            x_mm = 1000 * tau + noise_mm * rng.standard_normal(tau.shape)
            ms = 1000 * DT * np.arange(len(f))
            lines = ["t_ms,load_gf,pos_mm"]
            lines += [f"{a:.0f},{b * 1000 / G0:.4f},{c:.5f}" for a, b, c in zip(ms, f, x_mm)]
            path = folder / f"push_{label}_{k}.csv"
            atomic_write_text(path, "\n".join(lines) + "\n")
            out[label].append(path)
    return out


def _cli(args: list[str]) -> None:
    rc = main(args)
    if rc != 0:
        raise SystemExit(f"treeinfer {' '.join(args)} exited with {rc}")


def run_pipeline(
    work: Path, size: str = "cpu", seed: int = 0, noise_mm: float = 2.0, init: str = "laplace"
) -> dict:
    """import-csv -> infer (two heights) -> evaluate (the third) in ``work``; returns the
    held-out metrics, the posterior summary and the truth."""
    s = SIZES[size]
    tree = stem_tree()
    tree_file = dump_tree(tree, work / "stem.yaml")
    raw = write_raw_logs(work / "raw", tree, s["pulls"], s["seconds"], noise_mm, seed)
    for label, branch, frac in HEIGHTS:
        out = work / ("train" if label in TRAIN else "test")
        _cli(
            ["import-csv", *map(str, raw[label]), "--out", str(out)]
            + ["--time", "t_ms", "--force-column", "load_gf", "--displacement", "pos_mm"]
            + ["--units", "time=ms,force=gf,displacement=mm"]
            + ["--grasp-branch", branch, "--grasp-fraction", str(frac)]
            + ["--direction", "horizontal", "--zero-displacement", "none", "--force"]
        )
    run = work / "run"
    _cli(
        ["infer", "--tree", str(tree_file), "--data", str(work / "train"), "--out", str(run)]
        + ["--likelihood", "gaussian", "--sampler", "mh", "--seed", str(seed)]
        + (["--init", init] if init != "uniform" else [])
        + ["--particles", str(s["particles"]), "--iterations", str(s["iterations"])]
        + ["--no-progress", "--checkpoint-every", "0", "--force"]
        + (["--allow-poor-fit"] if size == "tiny" else [])
    )
    ev = work / "eval"
    _cli(["evaluate", "--run", str(run), "--data", str(work / "test"), "--out", str(ev), "--force"])
    metrics = json.loads((ev / "metrics.json").read_text())["metrics"]
    summary = json.loads((run / "summary.json").read_text())
    params = (summary.get("diagnostics") or {}).get("parameters") or {}
    rhat = {k: v.get("rhat") for k, v in params.items()}
    return {
        "init": init,
        "rhat": rhat,
        "rhat_max": max((float(v) for v in rhat.values() if v is not None), default=None),
        "seed": seed,
        "pct_inside_predictive_95": 100.0 - metrics["pct_outside"],
        "per_trajectory": metrics["per_trajectory"],
        "rmse_m": metrics.get("rmse"),
        "posterior": summary["posterior"],
        "truth": {
            **{f"Kp[{n}]": float(k) for n, k in zip(tree.inferred, KP)},
            **{f"Kd[{n}]": float(k) for n, k in zip(tree.inferred, KD)},
            "sigma_x": noise_mm / 1000,
        },
        "fit_status": summary.get("status"),
    }


def main_cli(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", choices=sorted(SIZES), default="cpu")
    ap.add_argument("--noise-mm", type=float, default=2.0)
    ap.add_argument("--out", type=Path, default=None, help="results JSON (default: committed)")
    ap.add_argument(
        "--init",
        choices=("laplace", "uniform"),
        default="laplace",
        help="MH chains' start: 'laplace' (around the MAP of the run's log-density, proposal "
        "shaped by its covariance; default) or 'uniform' in the prior box (before issue 13)",
    )
    a = ap.parse_args(argv)
    start = time.time()
    folds = []
    for seed in SIZES[a.size]["seeds"]:
        with tempfile.TemporaryDirectory() as tmp:
            folds.append(run_pipeline(Path(tmp), a.size, seed, a.noise_mm, a.init))
        print(
            f"seed {seed}: {folds[-1]['pct_inside_predictive_95']:.1f}% inside, R-hat max "
            f"{folds[-1]['rhat_max']}",
            flush=True,
        )
    inside = [f["pct_inside_predictive_95"] for f in folds]
    result = {
        "experiment": "sideways_push",
        "size": a.size,
        "settings": SIZES[a.size]
        | {"noise_mm": a.noise_mm, "train": TRAIN, "test": TEST, "init": a.init},
        "heights": [{"label": h, "branch": b, "fraction": f} for h, b, f in HEIGHTS],
        "pct_inside_predictive_95": {"per_seed": inside, "median": float(np.median(inside))},
        "target": "93-97% of the held-out height's noisy points inside the 95% predictive band",
        "runs": folds,
        "seconds": round(time.time() - start, 1),
        "command": f"python experiments/sideways_push.py --size {a.size} --init {a.init}",
    }
    out = a.out or Path(__file__).parent / "results" / "sideways_push" / f"{a.size}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, json.dumps(result, indent=2) + "\n")
    print(json.dumps(result["pct_inside_predictive_95"]))
    return result


if __name__ == "__main__":
    main_cli()
