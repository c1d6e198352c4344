"""Simulation-based calibration (SBC) of the DEFAULT path of ``treeinfer infer`` (issue 27).

For data set ``i`` (its own streams ``numpy.random.SeedSequence([seed, i])``):

1. truth from the default path's prior: the log gains from the smoothed box (``--prior-tail``
   default) times the learned parent-stiffer-than-child prior of the default sampler (NNSVGD),
   by exact rejection (box draws accepted with probability ``exp(nn - max nn)``); ``log sigma_x``
   uniform on ``--sigma-x-range`` (default 1-4 mm; see "the noise prior" below);
2. data as ``treeinfer simulate`` makes them: ``--n-traj`` mixed ramp-hold-release / hold pulls
   of ``--duration`` s at ``--dt`` (peaks 2-8 N), rolled out by treeinfer's accuracy-controlled
   simulator at the truth, then white noise: ``sigma_x`` on displacement, ``--noise-force`` N
   on the recorded force (the velocity column left out, as for a recording);
3. the fit: exactly what ``treeinfer infer --tree T --data D --out R`` runs with no other flag,
   through the API the CLI uses (``runs.infer_config`` with ``INFER_DEFAULTS``, then
   ``runs.run_inference``), in this process with ONE :class:`treeinfer.runs.SimulatorCache` for
   every data set, so whatever the default path can reuse between recordings (compiled programs,
   shape buckets, the persistent XLA cache) it reuses here;
4. the rank of each true parameter among the run's usable posterior rows (log units; ties
   broken at random), as the fractional rank ``u = (rank + V) / (L + 1)``, exactly uniform under
   calibration whatever each data set's ``L``.

Every data set's record (truth, posterior rows, wall time, stop reason, Pareto k-hat, stuck
particles, convergence warnings, verdict) is appended to ``OUT/records.jsonl`` as soon as it is
done; a rerun skips the indices already there, so several calls (each under ``--budget-s``)
add up to ``--n-datasets``. ``--merge A.jsonl B.jsonl`` summarises records made elsewhere.

Summary (``OUT/results.json`` with the config, ``OUT/results.md``, ``OUT/rank_histograms.png``):
per parameter the chi-square test on ``--bins`` equal bins of ``u`` and the Kolmogorov-Smirnov
test against Uniform(0, 1), passing at the family-wise 1% level (Bonferroni over parameters and
the two tests; :func:`treeinfer.calibration.rank_uniformity`), and the observed coverage of the
central 50/80/90/95% intervals.

The noise prior: the default prior on ``log sigma_x`` is flat from the sensor's resolution to
the data's range, which depends on the data. Truths are drawn log-uniformly from a range well
inside it; with ~900 samples per data set the posterior of sigma_x is a few percent wide, so it
lies far from either end of both ranges and the posterior is the same under either: ranks stay
uniform. The force noise is estimated from the data by the default path (a plug-in, not a
parameter), so it is not ranked; its errors-in-variables term is part of what SBC tests.

    python experiments/sbc_default.py --size tiny                   # smoke (2-core CPU, minutes)
    python experiments/sbc_default.py --size full --budget-s 480 --out DIR   # GPU, repeat
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from experiments._study_stats import append_jsonl, read_jsonl  # noqa: E402

SIZES = {
    # a smoke test of the harness: the two-branch example, one short coarse pull
    "tiny": {
        "tree": "two_branch",
        "n_datasets": 2,
        "n_traj": 1,
        "duration": 1.0,
        "dt": 0.02,
    },
    # issue 27's standard problem: three-joint tree, 3 pulls of 3 s at 10 ms
    "full": {
        "tree": "three_branch",
        "n_datasets": 200,
        "n_traj": 3,
        "duration": 3.0,
        "dt": 0.01,
    },
}
PEAKS = (2.0, 8.0)  # N, as `treeinfer simulate` draws them
LEVELS = (0.5, 0.8, 0.9, 0.95)


# ---- the prior of the default path ---------------------------------------------------------
class GainPrior:
    """Exact draws of the log gains from the default path's prior: the smoothed box
    (:func:`treeinfer.calibration.sample_smoothed_box`, tail ``prior_tail`` of each log width)
    times, when the default sampler uses it, the learned inequality prior
    (:func:`treeinfer.model.prior_terms.nn_inequality_prior`, the term ``make_problem`` adds), by
    rejection: a box draw is kept with probability ``exp(nn(theta) - nn_max)``. ``nn_max`` is the
    largest ``nn`` over 20,000 box draws of a fixed stream (the network is bounded; a draw above
    it would be kept with probability one, a bias below 1e-4 in practice)."""

    def __init__(self, tree, options: dict):
        from treeinfer.inference.samplers import sampler_spec
        from treeinfer.model.prior_terms import nn_inequality_prior

        lo, hi = (np.log(b) for b in tree.bounds_array())
        self.lower, self.upper = lo, hi
        self.sigma = float(options["prior_tail"]) * (hi - lo)
        self.nn = None
        if sampler_spec(options["sampler"]).nn_prior:
            self.nn = nn_inequality_prior(tree, eta=float(options["eta"]), seed=0)
        self.nn_max = 0.0
        if self.nn is not None:
            ref = self._box(np.random.default_rng(20_000), 20_000)
            self.nn_max = float(np.max(self._nn(ref)))

    def _box(self, rng, n):
        from treeinfer.calibration import sample_smoothed_box

        return sample_smoothed_box(rng, self.lower, self.upper, self.sigma, n)

    def _nn(self, theta) -> np.ndarray:
        import jax.numpy as jnp

        return np.asarray(self.nn(jnp.asarray(theta, jnp.float32)), float)

    def log_density(self, theta) -> np.ndarray:
        """Unnormalised log prior of ``theta [N, 2R]`` (box + inequality), for the tests."""
        import jax.numpy as jnp

        from treeinfer.model.priors import smoothed_box

        box = smoothed_box(self.lower, self.upper, self.sigma)
        out = np.asarray(box(jnp.asarray(theta, jnp.float32)), float)
        return out + (self._nn(theta) if self.nn is not None else 0.0)

    def draw(self, rng: np.random.Generator, n: int = 1) -> np.ndarray:
        """``[n, 2R]`` exact draws."""
        if self.nn is None:
            return self._box(rng, n)
        out: list[np.ndarray] = []
        while sum(len(o) for o in out) < n:
            th = self._box(rng, 4 * n)
            keep = rng.uniform(size=len(th)) < np.exp(self._nn(th) - self.nn_max)
            out.append(th[keep])
        return np.concatenate(out)[:n]


# ---- one data set ---------------------------------------------------------------------------
def draw_dataset(tree, prior: GainPrior, cfg: dict, index: int):
    """``(truth {label: log value}, trajectories)`` of data set ``index``."""
    from treeinfer.data import from_spec, random_specs
    from treeinfer.sim.synthetic import simulate_batch, synthetic_trajectories

    s_truth, s_pulls, s_noise = (
        np.random.default_rng(s) for s in np.random.SeedSequence([cfg["seed"], index]).spawn(3)
    )
    theta = prior.draw(s_truth, 1)[0]
    lo, hi = np.log(cfg["sigma_x_range"])
    log_sx = float(s_truth.uniform(lo, hi))
    r = tree.n_inferred
    kp, kd = np.exp(theta[:r]), np.exp(theta[r:])
    specs = random_specs("mixed", cfg["n_traj"], cfg["duration"], PEAKS, s_pulls)
    forces = np.stack([from_spec(s, cfg["duration"], cfg["dt"]) for s in specs])
    roll, _ = simulate_batch(tree, kp, kd, forces, cfg["dt"])
    names = [f"traj_{b:03d}" for b in range(len(forces))]
    trajs = synthetic_trajectories(
        roll, forces, cfg["dt"], names, cfg["noise_force"], math.exp(log_sx), s_noise
    )
    labels = list(tree.parameter_labels()) + ["sigma_x"]
    truth = dict(zip(labels, [float(v) for v in theta] + [log_sx]))
    return truth, trajs, specs


def default_fit(tree_path: Path, data_dir: Path, out: Path, cache) -> tuple:
    """``treeinfer infer --tree tree_path --data data_dir --out out`` with no other flag, through
    the API the CLI calls (``treeinfer.cli.infer.run_infer``'s steps) with the given cache:
    ``(posterior, summary)``."""
    from treeinfer import runs
    from treeinfer.cli.infer_options import INFER_DEFAULTS

    o = dict(INFER_DEFAULTS)
    o["grasp_fraction"] = None
    inputs = runs.load_run_inputs(
        tree_path, data_dir, None, None, o["model_kind"], o["tie"], o["tie_scale"]
    )
    config = runs.infer_config(
        tree_path, data_dir, out, force=False, model=None, repair_inertia=None, inputs=inputs, **o
    )
    outcome = runs.run_inference(config, progress=False, cache=cache, inputs=inputs)
    return outcome.posterior, outcome.summary


def fit_record(posterior, summary: dict) -> dict:
    """What SBC keeps of one fit: the usable posterior rows (log units) and its diagnostics."""
    rows = np.asarray(posterior.theta, float)[np.asarray(posterior.usable, bool)]
    strag = summary.get("stragglers") or {}
    return {
        "labels": list(posterior.labels),
        "draws": rows.tolist(),
        "n_rows": int(len(posterior.theta)),
        "status": summary.get("status"),
        "stop_reason": summary.get("stop_reason"),
        "diagnostics_kind": summary.get("diagnostics_kind"),
        "khat": (summary.get("diagnostics") or {}).get("khat"),
        "n_iterations_done": summary.get("n_iterations_done"),
        "n_stragglers": strag.get("n_stragglers"),
        "n_reinitialised": strag.get("n_reinitialised"),
        "n_unstable": summary.get("n_unstable"),
        "convergence_warnings": list(summary.get("convergence_warnings", [])),
        "substeps": (summary.get("simulation") or {}).get("substeps"),
    }


# ---- the driver (also run by the tests with a conjugate toy) --------------------------------
def run_sbc(
    records: Path,
    indices: Sequence[int],
    one: Callable[[int], dict],
    budget_s: float | None = None,
    log: Callable[[str], None] = lambda m: print(m, flush=True),
    done_in: Sequence[Path] | None = None,
) -> int:
    """Run ``one(i)`` (a record with ``truth`` and ``draws``, or ``error``) for every index not
    yet in ``records`` (or in any of ``done_in``, e.g. the other workers' files) and append each
    record as it comes; stop starting new ones once ``budget_s`` seconds have passed. Returns how
    many were added."""
    done = {r["index"] for r in read_jsonl([records, *(done_in or [])])}
    t0, added = time.perf_counter(), 0
    for i in indices:
        if i in done:
            continue
        if budget_s is not None and time.perf_counter() - t0 > budget_s:
            log(f"time budget of {budget_s:.0f} s spent: stopping before data set {i}")
            break
        t1 = time.perf_counter()
        rec = {"index": int(i), **one(i)}
        rec["wall_s"] = time.perf_counter() - t1
        append_jsonl(records, rec)
        added += 1
        log(
            f"data set {i}: {rec.get('status', rec.get('error', ''))}, {rec['wall_s']:.1f} s, "
            f"stop {rec.get('stop_reason')}, k-hat {rec.get('khat')}, "
            f"stuck {rec.get('n_stragglers')}"
        )
    return added


def summarise(recs: Sequence[dict], n_bins: int | None = None, seed: int = 0) -> dict:
    """Fractional ranks, uniformity tests, coverage and the fits' diagnostics of ``recs``."""
    from treeinfer.calibration import ALPHA, binomial_band, rank_coverage, rank_uniformity

    ok = [r for r in recs if "draws" in r and len(r["draws"]) >= 1]
    failed = [r for r in recs if r not in ok]
    out: dict = {"n_records": len(recs), "n_ranked": len(ok), "n_failed": len(failed)}
    out["failures"] = [{"index": r["index"], "error": r.get("error")} for r in failed]
    if not ok:
        return out
    labels = list(ok[0]["labels"])
    rng = np.random.default_rng(seed)
    u = np.empty((len(ok), len(labels)))
    for n, r in enumerate(ok):
        d = np.asarray(r["draws"], float)  # [L, D]
        t = np.asarray([r["truth"][k] for k in labels], float)
        less, ties = np.sum(d < t, axis=0), np.sum(d == t, axis=0)
        rank = less + rng.integers(0, ties + 1)
        u[n] = (rank + rng.uniform(size=len(labels))) / (len(d) + 1)
    nb = int(n_bins) if n_bins else int(max(2, min(20, len(ok) // 10)))
    out["labels"] = labels
    out["u"] = u.tolist()
    out["uniformity"] = rank_uniformity(u, labels, nb, ALPHA)
    cov = rank_coverage(u, LEVELS)
    out["coverage"] = [
        {
            "level": a,
            "band_99": [x / len(ok) for x in binomial_band(len(ok), a, 0.99)],
            **{lab: float(cov[k, j]) for j, lab in enumerate(labels)},
        }
        for k, a in enumerate(LEVELS)
    ]
    walls = np.asarray([r["wall_s"] for r in ok], float)
    out["wall_s"] = {
        "first": float(walls[0]),
        "median": float(np.median(walls)),
        "median_after_first": float(np.median(walls[1:])) if len(walls) > 1 else None,
        "max": float(walls.max()),
        "total": float(walls.sum()),
    }
    out["draws_per_dataset"] = sorted({len(r["draws"]) for r in ok})
    out["status"] = _counts(r.get("status") for r in ok)
    out["stop_reason"] = _counts(r.get("stop_reason") for r in ok)
    out["datasets_with_stuck_particles"] = int(sum((r.get("n_stragglers") or 0) > 0 for r in ok))
    out["stuck_particles_total"] = int(sum(r.get("n_stragglers") or 0 for r in ok))
    out["datasets_with_warnings"] = int(sum(bool(r.get("convergence_warnings")) for r in ok))
    kh = [r["khat"] for r in ok if r.get("khat") is not None]
    if kh:
        out["khat"] = {
            "median": float(np.median(kh)),
            "share_above_0.7": float(np.mean(np.asarray(kh) > 0.7)),
        }
    return out


def _counts(values) -> dict:
    vals = [str(v) for v in values]
    return {v: vals.count(v) for v in sorted(set(vals))}


def plot_ranks(summary: dict, path: Path) -> None:
    """Rank histograms (one panel per parameter) with the 99% binomial band of a uniform
    histogram, p-values in the titles."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    from treeinfer.calibration import binomial_band

    labels, uni = summary["labels"], summary["uniformity"]
    u, n, nb = np.asarray(summary["u"]), summary["n_ranked"], uni["n_bins"]
    lo, hi = binomial_band(n, 1.0 / nb, 0.99)
    ncol = min(len(labels), 4)
    nrow = math.ceil(len(labels) / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(3.2 * ncol, 2.6 * nrow), squeeze=False)
    for j, lab in enumerate(labels):
        ax = axes[j // ncol][j % ncol]
        t = uni["parameters"][lab]
        ax.axhspan(lo, hi, color="0.85", label="99% band of a uniform histogram")
        ax.axhline(n / nb, color="0.5", lw=0.8)
        ax.hist(u[:, j], bins=nb, range=(0, 1), color="C0" if t["pass"] else "C3", ec="white")
        ax.set_xlim(0, 1)
        ax.set_title(f"{lab}\np(chi2) {t['p_chi2']:.2g}, p(KS) {t['p_ks']:.2g}", fontsize=8)
        ax.set_xlabel("fractional rank of the truth (1)", fontsize=8)
        ax.set_ylabel("data sets", fontsize=8)
    for j in range(len(labels), nrow * ncol):
        axes[j // ncol][j % ncol].axis("off")
    axes[0][0].legend(fontsize=6, loc="lower left")
    verdict = "uniform" if uni["pass"] else "NOT uniform"
    if n < 50:  # a handful of ranks passes any test: say so rather than claim uniformity
        verdict = f"not judged ({n} data sets; SBC needs >= 200)"
    fig.suptitle(
        f"SBC of the default `treeinfer infer`, N = {n} data sets: ranks {verdict} at the 1% "
        "level (Bonferroni)",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def markdown(res: dict) -> str:
    s, c = res["summary"], res["config"]
    lines = [
        f"# SBC of the default path ({c['size']}): `{c['infer_command']}`",
        "",
        f"treeinfer {c['treeinfer_commit']}, {c['machine']}, {c['date_utc']}; tree "
        f"{c['tree']}, {c['n_traj']} pulls of {c['duration']} s at {c['dt']} s, noise "
        f"sigma_x log-uniform {c['sigma_x_range']} m, force {c['noise_force']} N",
        "",
        f"{s['n_ranked']} data sets ranked ({s['n_failed']} failed); wall per fit: "
        + (
            f"first {s['wall_s']['first']:.1f} s, median {s['wall_s']['median']:.1f} s "
            f"(workers: {c.get('workers', 1)}; this call {c.get('fits_this_call', '-')} fits "
            f"in {c.get('call_wall_s', float('nan')):.0f} s)"
            if "wall_s" in s
            else "-"
        ),
        "",
    ]
    if "uniformity" in s:
        lines += [
            "| parameter | chi2 | p(chi2) | KS | p(KS) | uniform at 1% | "
            + " | ".join(f"cover {a:.0%}" for a in LEVELS)
            + " |",
            "|---|---|---|---|---|---|" + "---|" * len(LEVELS),
        ]
        for lab in s["labels"]:
            t = s["uniformity"]["parameters"][lab]
            cov = " | ".join(f"{row[lab]:.3f}" for row in s["coverage"])
            lines.append(
                f"| {lab} | {t['chi2']:.1f} | {t['p_chi2']:.3g} | {t['ks']:.3f} | "
                f"{t['p_ks']:.3g} | {'yes' if t['pass'] else 'NO'} | {cov} |"
            )
        bands = ", ".join(
            f"{row['level']:.0%}: [{row['band_99'][0]:.3f}, {row['band_99'][1]:.3f}]"
            for row in s["coverage"]
        )
        lines += ["", f"99% binomial bands of the coverage: {bands}"]
    short = {k: v for k, v in s.items() if k not in ("u", "uniformity", "coverage", "labels")}
    lines += ["", "```json", json.dumps(short, indent=2), "```", ""]
    return "\n".join(lines)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", choices=list(SIZES), default="tiny")
    ap.add_argument("--n-datasets", type=int, help="data sets in all (default: the size's)")
    ap.add_argument(
        "--budget-s",
        type=float,
        help="start no new fit after this many seconds (stay inside a call's time limit)",
    )
    ap.add_argument("--seed", type=int, default=0, help="master seed of the data sets")
    ap.add_argument(
        "--sigma-x-range",
        default="0.001,0.004",
        help="m,m: true displacement noise, log-uniform (default 0.001,0.004)",
    )
    ap.add_argument(
        "--noise-force", type=float, default=0.05, help="N, recorded force noise (default 0.05)"
    )
    ap.add_argument("--bins", type=int, help="rank histogram bins (default N/10, 2-20)")
    ap.add_argument("--out", type=Path, help="default experiments/results/sbc_default_<size>")
    ap.add_argument(
        "--merge", nargs="+", type=Path, metavar="JSONL", help="only summarise these records"
    )
    ap.add_argument("--keep", action="store_true", help="keep every data set's run folder")
    ap.add_argument(
        "--workers",
        type=int,
        default=1,
        help="fit this many data sets at once, each in its own process sharing the GPU (one "
        "fit leaves most of a GPU idle; default 1)",
    )
    ap.add_argument("--worker", type=int, help=argparse.SUPPRESS)  # internal: worker k of N
    args = ap.parse_args(argv)
    if args.workers < 1 or (args.worker is not None and not 0 <= args.worker < args.workers):
        ap.error("--workers must be >= 1")
    size = SIZES[args.size]
    out = args.out or ROOT / "experiments" / "results" / f"sbc_default_{args.size}"
    sx = tuple(float(v) for v in args.sigma_x_range.split(","))
    if len(sx) != 2 or not 0 < sx[0] < sx[1]:
        ap.error(f"--sigma-x-range: expected two increasing positive values, got {sx}")
    from treeinfer.cli.infer_options import INFER_DEFAULTS
    from treeinfer.examples import example_path

    tree_path = Path(example_path(size["tree"]))
    cfg = {
        "size": args.size,
        "tree": str(tree_path.relative_to(ROOT))
        if tree_path.is_relative_to(ROOT)
        else str(tree_path),
        "n_datasets": args.n_datasets or size["n_datasets"],
        "n_traj": size["n_traj"],
        "duration": size["duration"],
        "dt": size["dt"],
        "peaks_n": list(PEAKS),
        "seed": args.seed,
        "sigma_x_range": list(sx),
        "noise_force": args.noise_force,
        "workers": args.workers,
        "infer_command": "treeinfer infer --tree T --data D --out R (no other flag; API, one "
        "SimulatorCache for every data set)",
        "infer_defaults": {k: v for k, v in INFER_DEFAULTS.items()},
        "treeinfer_commit": subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True
        ).stdout.strip(),
        "machine": platform.platform(),
        "cpu_count": os.cpu_count(),
        "jax_platforms": os.environ.get("JAX_PLATFORMS"),
        "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()),
    }
    records = out / "records.jsonl"
    t_call = time.perf_counter()
    n_before = len(read_jsonl(sorted(out.glob("records*.jsonl")))) if out.exists() else 0
    if args.merge:
        paths = list(args.merge)
    elif args.workers > 1 and args.worker is None:
        # N processes, data set i to worker i mod N, each appending to its own file (no two
        # writers on one file); JAX must not pre-allocate the GPU in each of them
        out.mkdir(parents=True, exist_ok=True)
        env = {**os.environ, "XLA_PYTHON_CLIENT_PREALLOCATE": "false"}
        argv = list(sys.argv[1:] if argv is None else argv)
        procs = [
            subprocess.Popen([sys.executable, __file__, *argv, "--worker", str(w)], env=env)
            for w in range(args.workers)
        ]
        codes = [p.wait() for p in procs]
        cfg["worker_exit_codes"] = codes
        paths = sorted(out.glob("records*.jsonl"))
    else:
        import jax

        import treeinfer
        from treeinfer import runs
        from treeinfer.data.trajectories import write_trajectory
        from treeinfer.tree import load_tree

        treeinfer.enable_compilation_cache()  # as the CLI does (cli.common._prepare_jax)
        cfg["jax_devices"] = [str(d) for d in jax.devices()]
        tree = load_tree(tree_path)
        prior = GainPrior(tree, INFER_DEFAULTS)
        cache = runs.SimulatorCache()
        work = out / "work"

        def one(i: int) -> dict:
            truth, trajs, specs = draw_dataset(tree, prior, cfg, i)
            d = work / f"ds{i:04d}"
            if d.exists():
                shutil.rmtree(d)
            (d / "data").mkdir(parents=True)
            for t in trajs:
                write_trajectory(d / "data" / f"{t.source}.csv", t)
            rec = {"truth": truth, "specs": specs}
            try:
                post, summary = default_fit(tree_path, d / "data", d / "run", cache)
                rec.update(fit_record(post, summary))
            except Exception as e:  # a failed fit is a finding: recorded and counted
                rec["error"] = f"{type(e).__name__}: {e}"
            if not args.keep:
                shutil.rmtree(d, ignore_errors=True)
            return rec

        out.mkdir(parents=True, exist_ok=True)
        indices = range(cfg["n_datasets"])
        others = sorted(out.glob("records*.jsonl"))
        if args.worker is not None:
            records = out / f"records_w{args.worker}.jsonl"
            indices = [i for i in indices if i % args.workers == args.worker]

            def log(msg: str) -> None:
                print(f"[worker {args.worker}] {msg}", flush=True)

            run_sbc(records, indices, one, args.budget_s, log, done_in=others)
            return {}  # the parent summarises every worker's records
        run_sbc(records, indices, one, args.budget_s, done_in=others)
        paths = sorted(out.glob("records*.jsonl"))
    recs = read_jsonl(paths)
    if not args.merge:  # this call's throughput (with --workers: all of them together)
        cfg["call_wall_s"] = time.perf_counter() - t_call
        cfg["fits_this_call"] = len(recs) - n_before
        cfg["fits_per_minute_this_call"] = 60.0 * cfg["fits_this_call"] / cfg["call_wall_s"]
    summary = summarise(recs, args.bins, args.seed)
    res = {"config": cfg, "records": [str(p) for p in paths], "summary": summary}
    out.mkdir(parents=True, exist_ok=True)
    from treeinfer.io.atomic_write import atomic_write_bytes

    # atomically: an interrupted write leaves the previous summary, never half of one
    atomic_write_bytes(out / "results.json", (json.dumps(res, indent=2) + "\n").encode())
    atomic_write_bytes(out / "results.md", markdown(res).encode())
    if "uniformity" in summary:
        plot_ranks(summary, out / "rank_histograms.png")
    print(markdown(res))
    return res


if __name__ == "__main__":
    main()
