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
    python experiments/default_calibration.py --seeds 1 --clean-only   # the clean runs alone
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
from experiments._study_stats import identified, rate_record  # noqa: E402

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


def _prior_log_width(tree) -> dict:
    """Width of each gain's prior box in log units, by label."""
    lo, hi = tree.bounds_array()
    return dict(zip(tree.parameter_labels(), map(float, np.log(np.asarray(hi) / np.asarray(lo)))))


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
    py = [sys.executable, "-m", "treeinfer"]
    infer = py + ["infer", "--tree", str(d / "tree.yaml"), "--data", str(d / "train")]
    infer += ["--out", str(d / "run"), *infer_args]
    done = d / "infer_done.json"  # a finished infer of an attempt that failed later: reused
    if done.exists() and (d / "run").exists():
        finished = json.loads(done.read_text())
        rc, wall = finished["exit"], finished["wall_s"]
    else:
        for sub in ("run", "eval"):  # a half-finished earlier attempt
            if (d / sub).exists():
                import shutil

                shutil.rmtree(d / sub)
        rc, wall = _run(infer, d / "infer.log")
        done.write_text(json.dumps({"exit": rc, "wall_s": wall}) + "\n")
    if (d / "eval").exists():  # evaluate is rerun: never on top of a half-written folder
        import shutil

        shutil.rmtree(d / "eval")
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
        rec["convergence_warnings"] = list(s.get("convergence_warnings", []))
        rec["stop_reason"] = s.get("stop_reason")
        rec["n_iterations_done"] = s.get("n_iterations_done")
        rec["khat"] = (s.get("diagnostics") or {}).get("khat")
        rec["posterior_log_std"] = _posterior_log_std(d / "run", labels)
        if not clean:
            crb, crb_f = _crb(case, int(s["simulation"]["substeps"]))
            rec["crb_log_std"], rec["crb_log_std_force_noise"] = crb, crb_f
            # the bound is of the gains (sigma_x's own is not part of the target)
            rec["std_over_crb"] = {k: rec["posterior_log_std"][k] / crb[k] for k in crb}
            rec["std_over_crb_force_noise"] = {
                k: rec["posterior_log_std"][k] / crb_f[k] for k in crb_f
            }
            # a parameter the data barely inform has the prior's std: its ratio is no test
            width = _prior_log_width(case.tree)
            rec["identified"] = {k: identified(crb_f[k], width[k]) for k in crb_f}
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


def _group(noisy_runs: list[dict]) -> dict:
    """Figures over a group of noisy runs (one case, or all): band coverage of the unseen
    points, truths inside their 95% interval (pooled and per parameter, Clopper-Pearson),
    posterior std / CRB of the identified parameters, stuck particles, warnings, wall times."""
    out: dict = {"n_runs": len(noisy_runs)}
    inside = [v for r in noisy_runs for v in r.get("truth_in_interval", {}).values()]
    if inside:
        out["truth_in_interval"] = rate_record(inside)
        labels = sorted({k for r in noisy_runs for k in r.get("truth_in_interval", {})})
        out["truth_in_interval_per_parameter"] = {
            k: rate_record(
                [
                    r["truth_in_interval"][k]
                    for r in noisy_runs
                    if k in r.get("truth_in_interval", {})
                ]
            )
            for k in labels
        }
    cov = [r["test_pct_inside"] for r in noisy_runs if "test_pct_inside" in r]
    if cov:
        out["test_pct_inside"] = {
            "mean": float(np.mean(cov)),
            "min": float(np.min(cov)),
            "max": float(np.max(cov)),
            "runs_in_target_93_97": int(sum(93.0 <= c <= 97.0 for c in cov)),
            "bands": sorted({r["test_band"] for r in noisy_runs if "test_band" in r}),
        }
    for key in ("std_over_crb", "std_over_crb_force_noise"):
        pairs = [
            (v, r.get("identified", {}).get(k, True))
            for r in noisy_runs
            for k, v in r.get(key, {}).items()
        ]
        ident = [v for v, ok in pairs if ok]
        if pairs:
            out[key] = {
                "identified_parameters": len(ident),
                "all_parameters": len(pairs),
                "median_identified": float(np.median(ident)) if ident else None,
                "max_identified": float(np.max(ident)) if ident else None,
                # within a factor 2 either way: narrower than half the bound is over-confidence
                "share_identified_within_2x": float(
                    np.mean((np.asarray(ident) >= 0.5) & (np.asarray(ident) <= 2.0))
                )
                if ident
                else None,
                "share_identified_below_half": float(np.mean(np.asarray(ident) < 0.5))
                if ident
                else None,
            }
    walls = [r["infer"]["wall_s"] for r in noisy_runs]
    if walls:
        out["infer_wall_s"] = {"median": float(np.median(walls)), "max": float(np.max(walls))}
    ev = [r["evaluate"]["wall_s"] for r in noisy_runs if "evaluate" in r]
    if ev:
        out["evaluate_wall_s"] = {"median": float(np.median(ev)), "max": float(np.max(ev))}
    out["exit_codes"] = sorted({r["infer"]["exit"] for r in noisy_runs})
    out["verdicts"] = {
        v: sum(str(r.get("verdict")) == v for r in noisy_runs)
        for v in sorted({str(r.get("verdict")) for r in noisy_runs})
    }
    out["stop_reasons"] = {
        v: sum(str(r.get("stop_reason")) == v for r in noisy_runs)
        for v in sorted({str(r.get("stop_reason")) for r in noisy_runs})
    }
    out["stuck_particles"] = int(sum(r.get("stragglers") or 0 for r in noisy_runs))
    out["runs_with_stuck_particles"] = int(sum((r.get("stragglers") or 0) > 0 for r in noisy_runs))
    out["runs_with_convergence_warnings"] = int(
        sum(bool(r.get("convergence_warnings")) for r in noisy_runs)
    )
    return out


def summarise(records: list[dict]) -> dict:
    """Pooled and per-case figures over the noisy runs; the clean runs' checks."""
    noisy_runs = [r for r in records if not r["clean"]]
    clean_runs = [r for r in records if r["clean"]]
    out = {"pooled": _group(noisy_runs)}
    out["per_case"] = {
        c: _group([r for r in noisy_runs if r["case"] == c])
        for c in sorted({r["case"] for r in noisy_runs})
    }
    out["n_noisy_runs"] = len(noisy_runs)
    out["stuck_particles_all_runs"] = int(sum(r.get("stragglers") or 0 for r in records))
    out["clean"] = [
        {
            "case": r["case"],
            "seed": r["seed"],
            "exit": r["infer"]["exit"],
            "verdict": r.get("verdict"),
            "poor_fit": r.get("verdict") == "poor_fit",
            "truths_inside": all(r.get("truth_in_interval", {}).values())
            if r.get("truth_in_interval")
            else None,
            "test_pct_inside": r.get("test_pct_inside"),
            "stuck_particles": r.get("stragglers"),
            "convergence_warnings": r.get("convergence_warnings"),
            "target_met": r["infer"]["exit"] == 0
            and r.get("verdict") != "poor_fit"
            and bool(r.get("truth_in_interval"))
            and all(r["truth_in_interval"].values()),
        }
        for r in clean_runs
    ]
    return out


def markdown(res: dict) -> str:
    s, c = res["summary"], res["config"]
    lines = [
        f"# Default-command calibration ({c['size']}): `{c['infer_command']}`",
        "",
        f"treeinfer {c['treeinfer_commit']}, {c['cpu_count']} CPUs, {c['machine']}, "
        f"{c['date_utc']}",
        "",
        "| case | seed | exit | verdict | stop | test % inside | truths inside "
        "| std/CRB (force noise), identified | stuck | warnings | infer s | evaluate s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in res["runs"]:
        ins = r.get("truth_in_interval", {})
        ratios = [
            v
            for k, v in r.get("std_over_crb_force_noise", {}).items()
            if r.get("identified", {}).get(k, True)
        ]
        rr = f"{min(ratios):.2f}-{max(ratios):.2f}" if ratios else "-"
        lines.append(
            f"| {r['case']}{' (clean)' if r['clean'] else ''} | {r['seed']} | "
            f"{r['infer']['exit']} | {r.get('verdict')} | {r.get('stop_reason')} | "
            f"{r.get('test_pct_inside', float('nan')):.1f} | "
            f"{sum(ins.values())}/{len(ins)} | {rr} | {r.get('stragglers')} | "
            f"{len(r.get('convergence_warnings') or [])} | {r['infer']['wall_s']:.0f} | "
            f"{r.get('evaluate', {}).get('wall_s', float('nan')):.0f} |"
        )
    lines += [
        "",
        "| group | runs | test % inside: mean (min-max) | runs in 93-97% | truths inside "
        "(Clopper-Pearson 95%) | identified std/CRB: median, max, share in 0.5-2 | stuck "
        "| runs with warnings | infer s median |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, g in [("pooled", s["pooled"]), *s["per_case"].items()]:
        t, ti = g.get("test_pct_inside", {}), g.get("truth_in_interval", {})
        cr = g.get("std_over_crb_force_noise", {})
        ci = ti.get("clopper_pearson_95", [math.nan, math.nan])

        def f(x, fmt=".2f"):
            return "-" if x is None else format(x, fmt)

        lines.append(
            f"| {name} | {g['n_runs']} | {f(t.get('mean'), '.1f')} ({f(t.get('min'), '.1f')}-"
            f"{f(t.get('max'), '.1f')}) | {t.get('runs_in_target_93_97', '-')} | "
            f"{ti.get('k', '-')}/{ti.get('n', '-')} [{ci[0]:.2f}, {ci[1]:.2f}] | "
            f"{f(cr.get('median_identified'))}, {f(cr.get('max_identified'))}, "
            f"{f(cr.get('share_identified_within_2x'))} | {g['stuck_particles']} | "
            f"{g['runs_with_convergence_warnings']} | "
            f"{f(g.get('infer_wall_s', {}).get('median'), '.0f')} |"
        )
    lines += ["", "```json", json.dumps(s, indent=2), "```", ""]
    return "\n".join(lines)


def _write(out: Path, res: dict) -> None:
    from treeinfer.io.atomic_write import atomic_write_bytes

    # atomically: an interrupted write leaves the previous summary, never half of one
    atomic_write_bytes(out / "results.json", (json.dumps(res, indent=2) + "\n").encode())
    atomic_write_bytes(out / "results.md", markdown(res).encode())


def merge(paths: list[Path], out: Path) -> dict:
    """One summary of the runs of several ``results.json`` (e.g. seed chunks run in separate
    GPU calls); a later file's run replaces an earlier one of the same case, seed and data."""
    runs: dict = {}
    configs = []
    for p in paths:
        res = json.loads(Path(p).read_text())
        configs.append(res["config"])
        for r in res["runs"]:
            runs[(r["case"], r["seed"], r["clean"])] = r
    records = [runs[k] for k in sorted(runs)]
    config = {**configs[-1], "merged_from": [str(p) for p in paths], "configs": configs}
    res = {"config": config, "summary": summarise(records), "runs": records}
    out.mkdir(parents=True, exist_ok=True)
    _write(out, res)
    print(markdown(res))
    return res


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", choices=list(SIZES), default="cpu")
    ap.add_argument("--seeds", type=int, help="seeds per case (default: the size's)")
    ap.add_argument("--seed-start", type=int, default=0, help="first seed (default 0)")
    ap.add_argument(
        "--cases", default=",".join(CASES), help="comma-separated, of " + ", ".join(CASES)
    )
    ap.add_argument("--no-clean", action="store_true", help="skip the noise-free runs")
    ap.add_argument(
        "--clean-only", action="store_true", help="only the noise-free runs (seed 0 of each case)"
    )
    ap.add_argument("--infer-args", default="", help="extra flags for `infer` (default: none)")
    ap.add_argument(
        "--budget-s",
        type=float,
        help="start no new run after this many seconds (stay inside a call's time limit; a "
        "rerun with the same --out continues)",
    )
    ap.add_argument(
        "--merge",
        nargs="+",
        type=Path,
        metavar="RESULTS_JSON",
        help="run nothing: summarise the runs of these results.json files into --out",
    )
    ap.add_argument(
        "--out", type=Path, help="default experiments/results/default_calibration_<size>"
    )
    args = ap.parse_args(argv)
    out = args.out or ROOT / "experiments" / "results" / f"default_calibration_{args.size}"
    if args.merge:
        return merge(args.merge, out)
    size = SIZES[args.size]
    seeds = args.seeds or size["seeds"]
    cases = [c.strip() for c in args.cases.split(",") if c.strip()]
    bad = [c for c in cases if c not in CASES]
    if bad or seeds < 1 or args.seed_start < 0:
        ap.error(f"--cases: unknown {bad}" if bad else "--seeds must be >= 1, --seed-start >= 0")
    if args.clean_only and (args.no_clean or args.seed_start != 0):
        ap.error("--clean-only: the clean runs belong to seed 0 (no --no-clean, --seed-start 0)")
    infer_args = shlex.split(args.infer_args)
    work = out / "work"
    # another flag set is another experiment: keep its runs apart
    if infer_args:
        work = out / ("work_" + "_".join(a.strip("-").replace("/", "_") for a in infer_args))
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True
    ).stdout.strip()
    seed_list = list(range(args.seed_start, args.seed_start + seeds))
    config = {
        "size": args.size,
        "seeds": seed_list,
        "cases": cases,
        "n_train": N_TRAIN,
        "n_test": size["n_test"],
        "duration_s": DURATION,
        "dt_s": DT,
        "sigma_x_m": SIGMA_X,
        "force_noise_share_of_peak": FORCE_LEVEL,
        "clean": (size["clean"] or args.clean_only) and not args.no_clean,
        "clean_only": args.clean_only,
        "infer_command": "python -m treeinfer infer --tree T --data D --out R"
        + (" " + shlex.join(infer_args) if infer_args else ""),
        "evaluate_command": "python -m treeinfer evaluate --run R --data TEST --out E",
        "reference": "treeinfer.sim.planar_reference.PlanarTree (scipy DOP853, rtol 1e-11)",
        "crb": "Fisher J^T (C + sigma^2 I)^-1 J at the truth on the noisy training forces "
        "(J central differences of the run's simulator; C the force-noise term), and J^T J / "
        "sigma^2 without it; 'identified': CRB std < 1/4 of the uniform prior's log std",
        "treeinfer_commit": commit,
        "cpu_count": os.cpu_count(),
        "machine": platform.platform(),
        "jax_platforms": os.environ.get("JAX_PLATFORMS"),
        "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()),
        "budget_s": args.budget_s,
    }
    records = []
    t0 = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    res = {"config": config, "summary": summarise([]), "runs": []}
    stopped = False
    # seeds outer, cases inner: an interrupted study still has every case
    for seed in seed_list:
        for name in cases:
            case = make_case(name, seed, N_TRAIN, size["n_test"], DURATION, DT)
            runs = [] if args.clean_only else [False]
            runs += [True] if config["clean"] and seed == 0 else []
            for clean in runs:
                if args.budget_s is not None and time.perf_counter() - t0 > args.budget_s:
                    stopped = True
                    break
                rec = one_run(case, work, clean, infer_args)
                records.append(rec)
                print(
                    f"{name} seed {seed}{' clean' if clean else ''}: exit {rec['infer']['exit']}, "
                    f"verdict {rec.get('verdict')}, test inside "
                    f"{rec.get('test_pct_inside', math.nan):.1f}%, truths "
                    f"{rec.get('truth_in_interval')}, stuck {rec.get('stragglers')}, "
                    f"infer {rec['infer']['wall_s']:.0f} s",
                    flush=True,
                )
                # written after every run: the figures so far survive an interrupted study
                config["total_wall_s"] = time.perf_counter() - t0
                res = {"config": config, "summary": summarise(records), "runs": records}
                _write(out, res)
    if stopped:
        print(f"time budget of {args.budget_s:.0f} s spent: rerun with the same --out to go on")
    print(markdown(res))
    return res


if __name__ == "__main__":
    main()
