"""Is the DEFAULT command calibrated? Issue 27's targets, on data from an independent simulator.

For every case of :mod:`experiments._planar_cases` (a two- and a three-joint planar chain whose
data come from Lagrange's equations integrated by scipy, not from treeinfer's simulator) and
every seed: 3 training pulls and unseen test pulls with 2 mm + 2% force noise, then, each as a
fresh process exactly as a user types it,

    python -m treeinfer infer --tree T --data TRAIN --out RUN       (no other flag)
    python -m treeinfer evaluate --run RUN --data TEST --out EVAL

and from their files:

* **band coverage**: the share of the unseen noisy test points inside the run's 95% band
  (``evaluate``'s metrics: the predictive band when the run has a noise model, else the
  parameter band; which one is recorded as ``band``). Target 93-97%.
* **interval coverage**: whether each true parameter lies in its 95% interval; pooled over
  seeds x cases x parameters with a Clopper-Pearson 95% interval for the rate, which should
  contain 0.95.
* **std / CRB**: the posterior std of each log parameter (the run's stable particles) over its
  Cramer-Rao bound at the truth (:func:`experiments.coverage.crb_log_std`: ``J^T J / sigma^2``
  with 2 mm, and the bound with the force noise, ``force_noise_basis``), target <= 2.
* the exit code, the fit verdict, stuck particles (``stragglers``) and the wall time of each
  command;
* **clean data** (no noise) per case: exit 0, not ``poor_fit``, truths inside.

``--infer-args`` appends flags to ``infer`` (to compare another path against the default).
Finished runs are kept under ``OUT/work`` and reused by a rerun with the same settings (delete
the folder to start over). Results: ``OUT/results.json`` (with the config) and ``results.md``.

    python experiments/default_calibration.py --size cpu    # 2 cases x 3 seeds + clean
    python experiments/default_calibration.py --size full   # 2 cases x 10 seeds, 25 test pulls
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from experiments._planar_cases import CASES, FORCE_LEVEL, SIGMA_X, make_case, noisy, write_folder  # noqa: E402

SIZES = {
    "tiny": {"seeds": 1, "n_test": 2, "clean": False},  # a smoke test of the harness itself
    "cpu": {"seeds": 3, "n_test": 10, "clean": True},
    "full": {"seeds": 10, "n_test": 25, "clean": True},
}
N_TRAIN, DURATION, DT = 3, 3.0, 0.01  # the standard problem's recording: 3 pulls of 3 s


def _run(cmd: list[str], log: Path) -> tuple[int, float]:
    """Run ``cmd`` from the repository root (this checkout's treeinfer): (exit code, wall s)."""
    t0 = time.perf_counter()
    with open(log, "w") as f:
        rc = subprocess.run(cmd, cwd=ROOT, stdout=f, stderr=subprocess.STDOUT).returncode
    return rc, time.perf_counter() - t0


def _posterior_log_std(run: Path, labels: list[str]) -> dict:
    """std of each log parameter over the run's stable particles (``particles.csv``)."""
    import csv

    with open(run / "particles.csv") as f:
        rows = [r for r in csv.DictReader(line for line in f if not line.startswith("#"))]
    rows = [r for r in rows if r["stable"] == "true"]
    return {k: float(np.std(np.log([float(r[k]) for r in rows]), ddof=1)) for k in labels}


def _crb(case, substeps: int) -> tuple[dict, dict]:
    """Cramer-Rao std of each log parameter at the truth on the NOISY training forces (as a fit
    sees them), without and with the force noise; the simulator at the run's own step."""
    from experiments.coverage import crb_log_std
    from treeinfer.data.trajectories import Trajectory
    from treeinfer.sim import make_simulator

    (f, x), _ = noisy(case)
    t = np.arange(f.shape[1]) * case.dt
    train = [Trajectory(t, fi, xi, None, f"train{i}") for i, (fi, xi) in enumerate(zip(f, x))]
    sim = make_simulator(case.tree, obs_dt=case.dt, substeps=substeps)
    labels = case.tree.parameter_labels()
    plain = crb_log_std(sim, case.kp, case.kd, train)
    with_f = crb_log_std(sim, case.kp, case.kd, train, sigma_force=case.sigma_force)
    return dict(zip(labels, map(float, plain))), dict(zip(labels, map(float, with_f)))


def one_run(case, work: Path, clean: bool, infer_args: list[str]) -> dict:
    """Data folders, ``infer`` and ``evaluate`` of one case and seed; the record of both."""
    from treeinfer.tree import dump_tree

    tag = f"{case.name}_s{case.seed}" + ("_clean" if clean else "")
    d = work / tag
    record_path = d / "record.json"
    if record_path.exists():
        return json.loads(record_path.read_text())
    d.mkdir(parents=True, exist_ok=True)
    if clean:
        tr, te = (case.train_force, case.train_tau), (case.test_force, case.test_tau)
    else:
        tr, te = noisy(case)
    dump_tree(case.tree, d / "tree.yaml")
    write_folder(d / "train", case.tree, case.kp, case.kd, *tr, case.dt, "train")
    write_folder(d / "test", case.tree, case.kp, case.kd, *te, case.dt, "test")
    for sub in ("run", "eval"):  # a half-finished earlier attempt
        if (d / sub).exists():
            import shutil

            shutil.rmtree(d / sub)
    py = [sys.executable, "-m", "treeinfer"]
    infer = py + ["infer", "--tree", str(d / "tree.yaml"), "--data", str(d / "train")]
    infer += ["--out", str(d / "run"), *infer_args]
    rc, wall = _run(infer, d / "infer.log")
    rec = {
        "case": case.name,
        "seed": case.seed,
        "clean": clean,
        "truth": {"kp": case.kp.tolist(), "kd": case.kd.tolist()},
        "sigma_force_n": 0.0 if clean else case.sigma_force,
        "sigma_x_m": 0.0 if clean else SIGMA_X,
        "infer": {"command": shlex.join(infer), "exit": rc, "wall_s": wall},
    }
    if (d / "run" / "summary.json").exists():
        s = json.loads((d / "run" / "summary.json").read_text())
        labels = list(s["posterior"])
        rec["verdict"] = s.get("status")
        rec["fit_reasons"] = s.get("fit", {}).get("reasons", [])
        rec["stragglers"] = s.get("stragglers", {}).get("n_stragglers")
        rec["n_unstable"] = s.get("n_unstable")
        rec["training_pct_outside"] = s.get("training_metrics", {}).get("pct_outside")
        rec["simulation"] = s.get("simulation")
        rec["posterior_log_std"] = _posterior_log_std(d / "run", labels)
        if not clean:
            crb, crb_f = _crb(case, int(s["simulation"]["substeps"]))
            rec["crb_log_std"], rec["crb_log_std_force_noise"] = crb, crb_f
            rec["std_over_crb"] = {k: rec["posterior_log_std"][k] / crb[k] for k in labels}
            rec["std_over_crb_force_noise"] = {
                k: rec["posterior_log_std"][k] / crb_f[k] for k in labels
            }
        ev = py + ["evaluate", "--run", str(d / "run"), "--data", str(d / "test")]
        ev += ["--out", str(d / "eval")]
        rc_e, wall_e = _run(ev, d / "evaluate.log")
        rec["evaluate"] = {"command": shlex.join(ev), "exit": rc_e, "wall_s": wall_e}
        if (d / "eval" / "metrics.json").exists():
            m = json.loads((d / "eval" / "metrics.json").read_text())["metrics"]
            rec["test_band"] = m["band"]
            rec["test_pct_inside"] = 100.0 - float(m["pct_outside"])
            rec["test_band_width_m"] = m["ci_width"]
            rec["truth_in_interval"] = {
                k: bool(v["in_interval"]) for k, v in m["parameters"].items()
            }
    record_path.write_text(json.dumps(rec, indent=2) + "\n")
    return rec


def summarise(records: list[dict]) -> dict:
    """Pooled figures over the noisy runs; the clean runs' checks."""
    from scipy.stats import binomtest

    noisy_runs = [r for r in records if not r["clean"]]
    clean_runs = [r for r in records if r["clean"]]
    inside = [v for r in noisy_runs for v in r.get("truth_in_interval", {}).values()]
    out: dict = {"n_noisy_runs": len(noisy_runs)}
    if inside:
        k, n = int(sum(inside)), len(inside)
        ci = binomtest(k, n).proportion_ci(0.95)
        out["truth_in_interval"] = {
            "k": k,
            "n": n,
            "rate": k / n,
            "clopper_pearson_95": [ci.low, ci.high],
            "nominal_0.95_inside_ci": bool(ci.low <= 0.95 <= ci.high),
        }
    cov = [r["test_pct_inside"] for r in noisy_runs if "test_pct_inside" in r]
    if cov:
        out["test_pct_inside"] = {
            "mean": float(np.mean(cov)),
            "min": float(np.min(cov)),
            "max": float(np.max(cov)),
            "in_target_93_97": int(sum(93.0 <= c <= 97.0 for c in cov)),
            "bands": sorted({r["test_band"] for r in noisy_runs if "test_band" in r}),
        }
    for key in ("std_over_crb", "std_over_crb_force_noise"):
        ratios = [v for r in noisy_runs for v in r.get(key, {}).values()]
        if ratios:
            out[key] = {
                "median": float(np.median(ratios)),
                "max": float(np.max(ratios)),
                "share_within_2x": float(np.mean(np.asarray(ratios) <= 2.0)),
            }
    walls = [r["infer"]["wall_s"] for r in noisy_runs + clean_runs]
    out["infer_wall_s"] = {"median": float(np.median(walls)), "max": float(np.max(walls))}
    ev = [r["evaluate"]["wall_s"] for r in noisy_runs + clean_runs if "evaluate" in r]
    if ev:
        out["evaluate_wall_s"] = {"median": float(np.median(ev)), "max": float(np.max(ev))}
    out["exit_codes"] = sorted({r["infer"]["exit"] for r in records})
    out["verdicts"] = {
        v: sum(r.get("verdict") == v for r in noisy_runs)
        for v in sorted({str(r.get("verdict")) for r in noisy_runs})
    }
    out["stuck_particles"] = int(sum(r.get("stragglers") or 0 for r in records))
    out["clean"] = [
        {
            "case": r["case"],
            "exit": r["infer"]["exit"],
            "verdict": r.get("verdict"),
            "poor_fit": r.get("verdict") == "poor_fit",
            "truths_inside": all(r.get("truth_in_interval", {}).values())
            if r.get("truth_in_interval")
            else None,
            "test_pct_inside": r.get("test_pct_inside"),
        }
        for r in clean_runs
    ]
    return out


def markdown(res: dict) -> str:
    s, c = res["summary"], res["config"]
    lines = [
        f"# Default-command calibration ({c['size']}): `{c['infer_command']}`",
        "",
        f"treeinfer {c['treeinfer_commit']}, {c['cpu_count']} CPUs, {c['date_utc']}",
        "",
        "| case | seed | exit | verdict | test % inside | truths inside "
        "| max std/CRB (force noise) | infer s | evaluate s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in res["runs"]:
        ins = r.get("truth_in_interval", {})
        ratio = max(r.get("std_over_crb_force_noise", {}).values(), default=float("nan"))
        lines.append(
            f"| {r['case']}{' (clean)' if r['clean'] else ''} | {r['seed']} | "
            f"{r['infer']['exit']} | {r.get('verdict')} | "
            f"{r.get('test_pct_inside', float('nan')):.1f} | "
            f"{sum(ins.values())}/{len(ins)} | {ratio:.2f} | {r['infer']['wall_s']:.0f} | "
            f"{r.get('evaluate', {}).get('wall_s', float('nan')):.0f} |"
        )
    lines += ["", "```json", json.dumps(s, indent=2), "```", ""]
    return "\n".join(lines)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", choices=list(SIZES), default="cpu")
    ap.add_argument("--seeds", type=int, help="seeds per case (default: the size's)")
    ap.add_argument(
        "--cases", default=",".join(CASES), help="comma-separated, of " + ", ".join(CASES)
    )
    ap.add_argument("--no-clean", action="store_true", help="skip the noise-free runs")
    ap.add_argument("--infer-args", default="", help="extra flags for `infer` (default: none)")
    ap.add_argument(
        "--out", type=Path, help="default experiments/results/default_calibration_<size>"
    )
    args = ap.parse_args(argv)
    size = SIZES[args.size]
    seeds = args.seeds or size["seeds"]
    cases = [c.strip() for c in args.cases.split(",") if c.strip()]
    bad = [c for c in cases if c not in CASES]
    if bad or seeds < 1:
        ap.error(f"--cases: unknown {bad}" if bad else "--seeds must be >= 1")
    infer_args = shlex.split(args.infer_args)
    out = args.out or ROOT / "experiments" / "results" / f"default_calibration_{args.size}"
    work = out / "work"
    # another flag set is another experiment: keep its runs apart
    if infer_args:
        work = out / ("work_" + "_".join(a.strip("-").replace("/", "_") for a in infer_args))
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True
    ).stdout.strip()
    config = {
        "size": args.size,
        "seeds": seeds,
        "cases": cases,
        "n_train": N_TRAIN,
        "n_test": size["n_test"],
        "duration_s": DURATION,
        "dt_s": DT,
        "sigma_x_m": SIGMA_X,
        "force_noise_share_of_peak": FORCE_LEVEL,
        "clean": size["clean"] and not args.no_clean,
        "infer_command": "python -m treeinfer infer --tree T --data D --out R"
        + (" " + shlex.join(infer_args) if infer_args else ""),
        "reference": "treeinfer.sim.planar_reference.PlanarTree (scipy DOP853, rtol 1e-11)",
        "treeinfer_commit": commit,
        "cpu_count": os.cpu_count(),
        "machine": platform.platform(),
        "jax_platforms": os.environ.get("JAX_PLATFORMS"),
        "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()),
    }
    records = []
    t0 = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    # seeds outer, cases inner: an interrupted study still has every case
    for seed in range(seeds):
        for name in cases:
            case = make_case(name, seed, N_TRAIN, size["n_test"], DURATION, DT)
            runs = [False] + ([True] if config["clean"] and seed == 0 else [])
            for clean in runs:
                rec = one_run(case, work, clean, infer_args)
                records.append(rec)
                print(
                    f"{name} seed {seed}{' clean' if clean else ''}: exit {rec['infer']['exit']}, "
                    f"verdict {rec.get('verdict')}, test inside "
                    f"{rec.get('test_pct_inside', math.nan):.1f}%, truths "
                    f"{rec.get('truth_in_interval')}, infer {rec['infer']['wall_s']:.0f} s",
                    flush=True,
                )
                # written after every run: the figures so far survive an interrupted study
                config["total_wall_s"] = time.perf_counter() - t0
                res = {"config": config, "summary": summarise(records), "runs": records}
                (out / "results.json").write_text(json.dumps(res, indent=2) + "\n")
                (out / "results.md").write_text(markdown(res))
    print(json.dumps(res["summary"], indent=2))
    return res


if __name__ == "__main__":
    main()
