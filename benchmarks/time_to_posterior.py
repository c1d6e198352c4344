"""From process start to a usable posterior: today's path against the fast path, in one run.

    python -m benchmarks.time_to_posterior                      # CPU (2 cores), writes the JSON
    python -m benchmarks.time_to_posterior --device gpu         # the same on a GPU
    python -m benchmarks.time_to_posterior --fast-gradients jvp --fast-jacobian jvp
    python -m benchmarks.time_to_posterior --paths today,importance --reference-from ref.json

The standard problem (``benchmarks/inference.py``: three-branch example, R = 3, 128 particles,
3 training pulls x 300 steps, NNSVGD). Each path runs in a **fresh Python process** with an
**empty compilation cache** (cold start, imports and compilation included), one after the other:

* ``reference``: uniform initialisation, central differences, ``--reference-iterations`` (long);
* ``today``: today's code path, uniform initialisation in the prior box, central differences,
  ``--today-iterations`` (200, the paper's setting);
* ``fast``: Levenberg–Marquardt MAP from ``--starts`` Latin-hypercube points, at most
  ``--lm-iterations`` (40) (:func:`treeinfer.inference.fit_problem`), particles drawn around it
  (:func:`treeinfer.inference.mapfit.laplace_particles`; for the Boltzmann loss the Gaussian matched
  to its cone-shaped density, :func:`treeinfer.inference.mapfit.norm_loss_covariance`, at
  ``--laplace-scale`` 1), NNSVGD with ``--fast-gradients`` (fd: on the CPU forward mode costs 2.6x
  central differences, ``benchmarks/gradient_cost.py``), its Adam learning rate ramped up over
  ``--fast-warmup`` iterations (the sampler's ``warmup`` option), stopped by
  :class:`treeinfer.inference.ConvergenceCriterion` (``--stop-when-converged``) or at
  ``--fast-iterations`` (60).

* ``importance``: :func:`treeinfer.inference.fast_posterior`, no sampler iterations: one
  compiled rollout program screens ``4 K`` box points, runs Levenberg–Marquardt from the
  ``--is-starts`` best (its central-difference points are the program's batch K), and
  importance-samples the Boltzmann-matched Gaussian around the mode (Pareto-smoothed weights);
  when the weights fail their own check (``k_hat > 0.7`` or too few effective samples) NNSVGD
  runs from those particles as in ``fast``. The headline figure is this path's when it runs.

``--substeps`` sets the simulation step of every path (default: the library's
accuracy-controlled step); ``--compile-cache DIR`` keeps one compilation cache between runs
(run twice: the second is the warm-cache figure, written under a ``_warm_compile_cache`` key).
``--data-seed N`` writes another data set of the same shape (other force profiles), so a cold
process on a NEW recording can be timed against a cache filled on seed 0; each child's record
has its XLA compilations and persistent-cache loads (``xla_compiles``, ``compiled``,
``cache_hits``).

Every ``--check-every`` iterations each run stores its particles and the wall-clock time. A
posterior is *usable* when, on 3 held-out pulls (noise-free MuJoCo C reference), its 95%
predictive band's mean width is within ``--tolerance`` (10%) of the reference run's and its
share of held-out points outside the band is within 10% of the reference's (or 1 percentage
point, whichever is larger). ``first_usable_s`` is the wall time from a path's process start to
its first stored state that is usable (an oracle: it needs the reference);
``time_to_posterior_s`` is the wall time to the run's own end (convergence or its iteration
cap) when that end is usable, else null; the headline figure is the fast path's
``time_to_posterior_s``. The NN prior is trained (or loaded) once
before the timed runs, and the training data are written once and read by each run, as a
user's CSV files would be.

Writes ``time_to_posterior`` and, on a CPU, ``cpu_time_to_posterior_s`` (on a GPU
``time_to_posterior_cold_with_imports_s``) into ``experiments/results/benchmarks/<machine>.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks._ttp_child import (  # noqa: F401 -- re-exported; the child runs there
    DT,
    N_STEPS,
    child,
    child_importance,
)

ROOT = Path(__file__).resolve().parent.parent


# ---- data (parent) -----------------------------------------------------------------------------
def write_data(folder: Path, data_seed: int = 0) -> None:
    """Training and held-out pulls of the standard problem (C reference, noise-free); the
    profiles' seeds are ``2 data_seed`` and ``2 data_seed + 1`` (seed 0: the benchmark's data
    as before), the tree's true gains are the same for every data seed."""
    from benchmarks.inference import EXAMPLES
    from treeinfer.data import profile_set
    from treeinfer.sim import make_simulator
    from treeinfer.sim.reference import simulate_reference
    from treeinfer.sim.synthetic import default_true_params
    from treeinfer.tree import load_tree

    tree = load_tree(EXAMPLES / "three_branch.yaml")
    sim = make_simulator(tree, obs_dt=DT, accuracy="coarse")
    kp, kd = default_true_params(tree, np.random.default_rng(0))
    out = {"kp": kp, "kd": kd}
    for name, seed in (("train", 2 * data_seed), ("test", 2 * data_seed + 1)):
        forces = profile_set("mixed", n=3, duration=N_STEPS * DT, dt=DT, seed=seed)[:, :N_STEPS]
        ref = [simulate_reference(sim, kp, kd, f) for f in forces]
        out[f"{name}_force"] = forces
        out[f"{name}_tau"] = np.stack([r[0] for r in ref])
        out[f"{name}_tau_dot"] = np.stack([r[1] for r in ref])
    np.savez(folder / "data.npz", **out)


def warm_nn_prior() -> None:
    from benchmarks.inference import EXAMPLES
    from treeinfer.inference import nn_inequality_prior
    from treeinfer.tree import load_tree

    nn_inequality_prior(load_tree(EXAMPLES / "three_branch.yaml"))


# ---- comparison (parent) -----------------------------------------------------------------------
def band_metrics(sim, theta, forces, truth) -> dict:
    """95% predictive band of particles ``theta`` on ``forces`` against noise-free ``truth``."""
    from treeinfer.evaluation import summarize
    from treeinfer.inference.problem import predict

    roll = predict(sim, np.asarray(theta, np.float32), forces)
    s = summarize(roll.tau, truth, valid=np.all(np.asarray(roll.stable), axis=1))
    return {
        "ci_width_m": s["ci_width"],
        "pct_outside": s["pct_outside"],
        "n_valid": s["n_valid_particles"],
    }


def reference_metrics(sim, theta, forces, truth, n_particles: int) -> dict:
    """:func:`band_metrics` of the reference particles; with more than ``n_particles`` (the
    importance reference), the mean over its consecutive ``n_particles``-particle subsets, so
    its band has the same KDE smoothing (Scott's rule, ``n^-1/5``) as the runs'."""
    theta = np.asarray(theta)
    if len(theta) <= n_particles:
        return band_metrics(sim, theta, forces, truth)
    parts = [
        band_metrics(sim, theta[i : i + n_particles], forces, truth)
        for i in range(0, len(theta) - n_particles + 1, n_particles)
    ]
    return {k: float(np.mean([m[k] for m in parts])) for k in parts[0]} | {"n_subsets": len(parts)}


def usable(m: dict, ref: dict, tol: float) -> bool:
    width_ok = abs(m["ci_width_m"] - ref["ci_width_m"]) <= tol * ref["ci_width_m"]
    out_ok = abs(m["pct_outside"] - ref["pct_outside"]) <= max(tol * ref["pct_outside"], 1.0)
    return bool(width_ok and out_ok)


def run_child(mode: str, args, workdir: Path) -> dict:
    result = workdir / f"{mode}.json"
    cache = Path(args.compile_cache) if args.compile_cache else workdir / f"cache-{mode}"
    cache.mkdir(parents=True, exist_ok=True)
    n_cached = sum(1 for p in cache.rglob("*") if p.is_file())
    # keep an existing PYTHONPATH (packages installed with --target, as on a lent GPU machine)
    path = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)
    env = {**os.environ, "TREEINFER_JAX_CACHE": str(cache), "PYTHONPATH": path}
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    if args.device != "auto":
        env["JAX_PLATFORMS"] = args.device
    cmd = [
        sys.executable,
        "-m",
        "benchmarks.time_to_posterior",
        "--child",
        mode,
        "--workdir",
        str(workdir),
        "--result",
        str(result),
    ] + args.passthrough
    if args.cores and (os.cpu_count() or 1) > args.cores and shutil.which("taskset"):
        cmd = ["taskset", "-c", f"0-{args.cores - 1}"] + cmd
    print(f"[{mode}] {' '.join(cmd[-8:])}", flush=True)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t_spawn = time.time()
    subprocess.run(cmd, env=env, check=True, cwd=ROOT)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    rec = json.loads(result.read_text())
    rec["t_spawn"] = t_spawn
    rec["wall_s"] = rec["marks"]["infer"] - t_spawn
    # CPU seconds of the whole child (all threads): robust to other users' load on the box
    rec["cpu_s"] = (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)
    rec["load_average_after"] = os.getloadavg()
    rec["compile_cache_entries_at_start"] = n_cached
    return rec


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--particles", type=int, default=128)
    p.add_argument("--reference-iterations", type=int, default=400)
    p.add_argument("--today-iterations", type=int, default=200)
    p.add_argument("--fast-iterations", type=int, default=60, help="fast path: at most")
    p.add_argument("--fast-gradients", default="fd", choices=["fd", "jvp"])
    p.add_argument(
        "--fast-jacobian",
        default="fd",
        choices=["fd", "jvp"],
        help="residual Jacobian of the LM fit",
    )
    p.add_argument("--starts", type=int, default=6, help="LM starting points")
    p.add_argument("--lm-iterations", type=int, default=40)
    p.add_argument(
        "--lm-agree",
        type=int,
        default=None,
        help="stop LM once this many starts agree on the lowest minimum",
    )
    p.add_argument("--laplace-scale", type=float, default=1.0)
    p.add_argument(
        "--laplace-covariance",
        default="auto",
        choices=["auto", "laplace", "norm"],
        help="auto: the Gaussian matched to the Boltzmann loss (mapfit.norm_loss_covariance)",
    )
    p.add_argument(
        "--stop-when-converged",
        type=int,
        default=1,
        help="fast path: stop at convergence (diagnostics.ConvergenceCriterion, checked every "
        "--check-every iterations; 0: run --fast-iterations)",
    )
    p.add_argument("--min-iterations", type=int, default=10)
    p.add_argument(
        "--fast-learning-rate",
        type=float,
        default=None,
        help="NNSVGD Adam learning rate of the fast path (default: the sampler's)",
    )
    p.add_argument(
        "--fast-warmup",
        type=int,
        default=5,
        help="fast path: ramp Adam's learning rate up over this many iterations",
    )
    p.add_argument(
        "--substeps",
        type=int,
        default=None,
        help="simulation substeps per observation of every path (default: the library's "
        "accuracy-controlled step; 4 is the stability step of the earlier figures)",
    )
    p.add_argument("--is-starts", type=int, default=8, help="importance path: LM starting points")
    p.add_argument(
        "--is-df",
        type=float,
        default=8.0,
        help="importance path: Student-t degrees of freedom of the proposals (inf: Gaussian, "
        "as before; fast_posterior's default 8)",
    )
    p.add_argument(
        "--is-rounds",
        type=int,
        default=3,
        help="importance path: at most this many adaptive proposal rounds (fast_posterior's 3; 1: "
        "the fit's proposal alone, as before)",
    )
    p.add_argument(
        "--reference-kind",
        default="nnsvgd",
        choices=["nnsvgd", "importance"],
        help="the reference posterior: NNSVGD for --reference-iterations (the paper's sampler; "
        "its band comes out 10-15%% narrower than the exact posterior's here) or importance "
        "sampling with 16384 draws (exact in the limit; band averaged over 32 P-particle subsets)",
    )
    p.add_argument("--check-every", type=int, default=5)
    p.add_argument("--tolerance", type=float, default=0.10)
    p.add_argument("--device", default="auto", choices=["auto", "cpu", "gpu", "cuda"])
    p.add_argument("--cores", type=int, default=2, help="pin CPU runs to this many cores")
    p.add_argument("--paths", default="reference,today,fast")
    p.add_argument(
        "--reference-from",
        default=None,
        help="reuse a reference run saved with --save-reference (same problem)",
    )
    p.add_argument("--save-reference", default=None, help="write the reference run here")
    p.add_argument(
        "--compile-cache",
        default=None,
        help="persistent compilation cache folder kept between runs (default: a fresh empty "
        "one per path: a cold start); run twice with the same folder for the warm-cache figure",
    )
    p.add_argument(
        "--data-seed",
        type=int,
        default=0,
        help="another data set of the same shape (3 pulls x 300 steps, other force profiles): "
        "fill the cache with seed 0, then time a cold process on seed 1 (a new recording). "
        "The reference must be of the same data seed (--save-reference with it)",
    )
    p.add_argument("--machine", default=None)
    p.add_argument("--no-write", dest="write", action="store_false")
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)
    p.add_argument("--workdir", default=None, help=argparse.SUPPRESS)
    p.add_argument("--result", default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        return child(args)

    keep = [
        "particles",
        "reference_iterations",
        "today_iterations",
        "fast_iterations",
        "fast_gradients",
        "fast_jacobian",
        "starts",
        "lm_iterations",
        "laplace_scale",
        "check_every",
        "fast_learning_rate",
        "fast_warmup",
        "substeps",
        "lm_agree",
        "laplace_covariance",
        "stop_when_converged",
        "min_iterations",
        "is_starts",
        "is_df",
        "is_rounds",
    ]
    args.passthrough = []
    for k in keep:
        if getattr(args, k) is not None:
            args.passthrough += [f"--{k.replace('_', '-')}", str(getattr(args, k))]
    if args.device != "auto":
        os.environ["JAX_PLATFORMS"] = args.device

    from benchmarks import _common as C

    workdir = Path(tempfile.mkdtemp(prefix="ttp-"))
    try:
        write_data(workdir, args.data_seed)
        warm_nn_prior()
        paths = args.paths.split(",")
        runs = {}
        if args.reference_from:  # a reference posterior saved by an earlier run (--save-reference)
            runs["reference"] = json.loads(Path(args.reference_from).read_text())
            paths = [m for m in paths if m != "reference"]
        for mode in paths:
            child_mode = (
                "reference_importance"
                if mode == "reference" and args.reference_kind == "importance"
                else mode
            )
            runs[mode] = run_child(child_mode, args, workdir)
        if args.save_reference and "reference" in paths:
            Path(args.save_reference).write_text(json.dumps(runs["reference"]))
        summary = compare(runs, workdir, args)
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    info = C.machine_info()
    summary["machine"] = info
    if args.write:
        machine = args.machine or C.default_machine_name()
        warm = any(
            bool(summary.get(m, {}).get("compile_cache_entries_at_start"))
            for m in ("fast", "importance")
        )
        key = (
            "cpu_time_to_posterior_s"
            if info["platform"] == "cpu"
            else "time_to_posterior_cold_with_imports_s"
        )
        if warm:  # a cache filled by an earlier run: not a cold start
            key = key.replace("_cold", "") + "_warm_compile_cache"
            summary["compile_cache"] = "warm"
        if args.data_seed:  # another data set than the benchmark's: its own key
            key += f"_data_seed_{args.data_seed}"
        best = "importance" if "importance" in summary else "fast"
        headline = summary.get(best, {}).get("time_to_posterior_s")
        summary["headline_path"] = best
        top = {key: headline} if headline is not None else {}
        path = C.merge_results(C.RESULTS_DIR / f"{machine}.json", "time_to_posterior", summary, top)
        print(f"wrote {path}")
    return 0


def compare(runs: dict, workdir: Path, args) -> dict:
    from benchmarks.inference import EXAMPLES
    from treeinfer.sim import make_simulator
    from treeinfer.tree import load_tree

    data = np.load(workdir / "data.npz")
    sim = make_simulator(load_tree(EXAMPLES / "three_branch.yaml"), obs_dt=DT, accuracy="coarse")
    forces, truth = data["test_force"], data["test_tau"]
    ref = reference_metrics(sim, runs["reference"]["final_theta"], forces, truth, args.particles)
    print(
        f"reference ({runs['reference']['n_iterations']} it): band width "
        f"{ref['ci_width_m'] * 1e3:.2f} mm, {ref['pct_outside']:.1f}% outside",
        flush=True,
    )
    summary: dict = {
        "reference": {
            **ref,
            "n_iterations": runs["reference"]["n_iterations"],
            "wall_s": runs["reference"]["wall_s"],
        },
        "tolerance": args.tolerance,
        "n_particles": args.particles,
    }
    for mode in [m for m in runs if m != "reference"]:
        rec = runs[mode]
        first_ok, table = None, []
        for c in rec["checks"]:
            m = band_metrics(sim, c["theta"], forces, truth)
            ok = usable(m, ref, args.tolerance)
            elapsed = c["time"] - rec["t_spawn"]
            table.append({"iteration": c["iteration"], "elapsed_s": elapsed, **m, "usable": ok})
            if ok and first_ok is None:
                first_ok = table[-1]
        print(
            f"{mode} checks: "
            + "; ".join(
                f"it {r['iteration']} {r['elapsed_s']:.0f}s {r['ci_width_m'] * 1e3:.2f}mm "
                f"{r['pct_outside']:.1f}%{' ok' if r['usable'] else ''}"
                for r in table
            ),
            flush=True,
        )
        final = band_metrics(sim, rec["final_theta"], forces, truth)
        marks = {k: v - rec["t_spawn"] for k, v in rec["marks"].items()}
        summary[mode] = {
            "wall_s": rec["wall_s"],
            "cpu_s": rec.get("cpu_s"),
            "load_average_after": rec.get("load_average_after"),
            "compile_cache_entries_at_start": rec.get("compile_cache_entries_at_start"),
            "data_seed": args.data_seed,
            # this child's XLA compilations and persistent-cache loads (treeinfer.sim.compile_stats)
            "xla_compiles": (rec.get("compile_stats") or {}).get("xla_compiles"),
            "compile_s": (rec.get("compile_stats") or {}).get("compile_s"),
            "compiled": (rec.get("compile_stats") or {}).get("compiled"),
            "cache_hits": (rec.get("compile_stats") or {}).get("cache_hits"),
            "n_iterations": rec["n_iterations"],
            "gradient": rec["gradient"],
            "phase_ends_s": marks,
            "final": final,
            "final_usable": usable(final, ref, args.tolerance),
            "first_usable_iteration": None if first_ok is None else first_ok["iteration"],
            "first_usable_s": None if first_ok is None else first_ok["elapsed_s"],
            "stop_reason": rec.get("stop_reason"),
            "n_iterations_done": rec.get("n_iterations_done", rec["n_iterations"]),
            # what a user gets without a reference: the run's own end, if its result is usable
            "time_to_posterior_s": rec["wall_s"] if usable(final, ref, args.tolerance) else None,
            "checks": table,
            **({"map": rec["map"]} if "map" in rec else {}),
            **({"importance": rec["importance"]} if "importance" in rec else {}),
        }
        print(
            f"{mode}: {rec.get('n_iterations_done', rec['n_iterations'])} it "
            f"({rec.get('stop_reason', 'max_iterations')}) in {rec['wall_s']:.1f} s from "
            "process start, "
            f"{rec.get('cpu_s', float('nan')):.0f} CPU s "
            f"(phases: {', '.join(f'{k} {v:.1f}' for k, v in marks.items())}); final band "
            f"{final['ci_width_m'] * 1e3:.2f} mm, {final['pct_outside']:.1f}% outside; first "
            f"usable: "
            + (
                "never"
                if first_ok is None
                else f"iteration {first_ok['iteration']} at {first_ok['elapsed_s']:.1f} s"
            )
            + f"; XLA compiles {summary[mode]['xla_compiles']} "
            f"({summary[mode]['compile_s']} s), cache loads {summary[mode]['cache_hits']}",
            flush=True,
        )
    for fast in [m for m in ("fast", "importance") if m in summary and "today" in summary]:
        fast_t = summary[fast]["time_to_posterior_s"]
        today_fixed = summary["today"]["wall_s"]
        today_first = summary["today"]["first_usable_s"]
        if fast_t:
            sfx = "" if fast == "fast" else f"_{fast}"
            summary[f"speedup_vs_today_fixed{sfx}"] = today_fixed / fast_t
            print(
                f"today's code ({summary['today']['n_iterations']} it): {today_fixed:.1f} s; "
                f"{fast} path: {fast_t:.1f} s; ratio {today_fixed / fast_t:.2f}x",
                flush=True,
            )
            if today_first:
                summary[f"speedup_vs_today_first_usable{sfx}"] = today_first / fast_t
                print(
                    f"(today's first usable state at {today_first:.1f} s: ratio "
                    f"{today_first / fast_t:.2f}x)",
                    flush=True,
                )
    return summary


if __name__ == "__main__":
    sys.exit(main())
