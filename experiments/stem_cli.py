"""Issue 13's stem target through the command line, literally (synthetic stand-in data).

For one data seed, every step is a ``treeinfer`` command (``treeinfer.cli.main.main([...])``,
the same entry point as the console script), with only file copies between them:

1. ``synthetic_stem.write_stem_logs``: raw logger CSVs of a tapered elastic stem pushed sideways
   at 0.12, 0.24 and 0.36 m (gf, mm, a wrapping ms counter, jitter, a load offset, noise);
2. ``treeinfer import-csv`` once per log into ``data/all`` (``--units time=ms,force=gf,
   displacement=mm --dt 0.5 --tare --zero-displacement contact --trim --direction horizontal``,
   ``--grasp-branch stem --grasp-distance H``: H the push height above the ground);
3. ``treeinfer tree --kind stem --stem-height 0.4 --base-diameter 0.010 --tip-diameter 0.006
   --push-heights-from data/all``: the matched 3-link chain (tie: shape, tie_scale 0.1), which
   also re-points ``data/all/pulls.yaml`` at the chain's links;
4. per held-out height: the two other CSVs (and pulls.yaml) copied to ``foldK/train``, the held-out
   one to ``foldK/test``; ``treeinfer infer --model-kind static --likelihood gaussian
   --noise-force auto --sampler mh --init laplace --gradients jvp``; ``treeinfer evaluate``;
5. scored from the files those commands wrote: % of the held-out points inside the 95% band
   (``metrics.json``), RMSE of the predictive mean (``*_prediction.csv``) against the
   one-parameter cantilever ``x = F h^3 / 3EI`` fitted to the same two training CSVs, and the
   largest split R-hat of the run (arviz, over the chains' post-warm-up trace in ``trace.npz``).

Target (issue 13): >= 90% inside, RMSE <= the cantilever's, in every fold.

    nice python experiments/stem_cli.py --seed 0 [--iterations 1100 --particles 16]
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

if __name__ == "__main__":  # run as a script from anywhere: use this checkout's treeinfer
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np

HEIGHTS = (0.12, 0.24, 0.36)


def _cli(argv: list[str]) -> None:
    """One ``treeinfer`` command; raises if it exits non-zero (so a failing step is visible)."""
    from treeinfer.cli.main import main

    print("$ treeinfer " + " ".join(argv), flush=True)
    rc = main(argv)
    if rc not in (0, None):
        raise RuntimeError(f"treeinfer {argv[0]} exited {rc}")


def _rhat_max(run: Path, warmup: float) -> float:
    """Largest split R-hat (arviz) over the run's chains after the warm-up share."""
    from treeinfer.inference.diagnostics import arviz_compat as az

    with np.load(run / "trace.npz") as z:
        key = "positions" if "positions" in z.files else z.files[0]
        tr = np.asarray(z[key], float)  # [T, P, D]
    keep = tr[int(warmup * tr.shape[0]) :]
    rhat = az.rhat(np.swapaxes(keep, 0, 1))["x"].values
    return float(np.nanmax(rhat))


def prepare(work: Path, seed: int, tie_scale: str) -> tuple[Path, list[str]]:
    """Steps 1-3: logs, import-csv, tree --kind stem. Returns (tree file, CSV names)."""
    from treeinfer.tree import Stem, write_stem_logs

    raw = write_stem_logs(work / "raw", Stem(), heights=HEIGHTS, seed=seed)
    data = work / "data" / "all"
    for path, push in raw:
        _cli(
            [
                "import-csv",
                str(path),
                "--out",
                str(data),
                "--time",
                "millis",
                "--force-column",
                "load_g",
                "--displacement",
                "pos_mm",
                "--units",
                "time=ms,force=gf,displacement=mm",
                "--dt",
                "0.5",
                "--tare",
                "--zero-displacement",
                "contact",
                "--trim",
                "--grasp-branch",
                "stem",
                "--grasp-distance",
                f"{push.height:g}",
                "--direction",
                "horizontal",
            ]
        )
    tree = work / "stem.yaml"
    _cli(
        [
            "tree",
            "--kind",
            "stem",
            "--stem-height",
            "0.4",
            "--base-diameter",
            "0.010",
            "--tip-diameter",
            "0.006",
            "--push-heights-from",
            str(data),
            "--tie-scale",
            tie_scale,
            "--out",
            str(tree),
        ]
    )
    return tree, [p.stem + ".csv" for p, _ in raw]


def fold(work: Path, tree: Path, names: list[str], test: int, args) -> dict:
    """Steps 4-5 for one held-out height."""
    data = work / "data" / "all"
    fdir = work / f"fold{test}"
    train, held = fdir / "train", fdir / "test"
    for folder, pick in (
        (train, [n for k, n in enumerate(names) if k != test]),
        (held, [names[test]]),
    ):
        folder.mkdir(parents=True)
        for n in pick:
            shutil.copy(data / n, folder / n)
        shutil.copy(data / "pulls.yaml", folder / "pulls.yaml")
    run, ev = fdir / "run", fdir / "eval"
    _cli(
        [
            "infer",
            "--tree",
            str(tree),
            "--data",
            str(train),
            "--out",
            str(run),
            "--model-kind",
            "static",
            "--likelihood",
            "gaussian",
            "--noise-force",
            "auto",
            "--sampler",
            "mh",
            "--particles",
            str(args.particles),
            "--iterations",
            str(args.iterations),
            "--mcmc-warmup",
            str(args.warmup),
            "--init",
            "laplace",
            "--gradients",
            "jvp",
            "--seed",
            str(args.seed + test),
            "--no-progress",
            "--allow-poor-fit",
        ]
    )
    _cli(["evaluate", "--run", str(run), "--data", str(held), "--out", str(ev)])
    return score(work, names, test, args)


def _wall(config: dict) -> float | None:
    """Seconds from the run's creation to its end (``config.json``), compilation included."""
    from datetime import datetime

    try:
        a, b = (
            datetime.fromisoformat(config[k].replace("Z", "+00:00"))
            for k in ("created_utc", "finished_utc")
        )
    except (KeyError, TypeError, ValueError):
        return None
    return (b - a).total_seconds()


def score(work: Path, names: list[str], test: int, args) -> dict:
    """Step 5 from the files infer and evaluate wrote in ``work/fold<test>``: the share of the
    held-out points inside the band ``metrics.json`` scores (the predictive band, noise
    included, when the run has a noise model: the CSV's ``predictive_lower/upper``), the RMSE
    of the predictive mean and of the cantilever fitted to the two training CSVs, R-hat."""
    from treeinfer.data import read_trajectory
    from treeinfer.tree import cantilever_displacement, fit_cantilever

    fdir = work / f"fold{test}"
    train, run, ev = fdir / "train", fdir / "run", fdir / "eval"
    metrics = json.loads((ev / "metrics.json").read_text())["metrics"]
    pred = np.genfromtxt(next(ev.glob("*_prediction.csv")), delimiter=",", names=True)
    tr = [read_trajectory(train / n) for n in names if n != names[test]]
    hs = [h for k, h in enumerate(HEIGHTS) if k != test]
    ei = fit_cantilever([t.force for t in tr], [t.displacement for t in tr], hs)
    cant = cantilever_displacement(pred["force"], HEIGHTS[test], ei)
    rec = pred["recorded"]
    noisy = "predictive_lower" in pred.dtype.names
    lo, hi = (pred["predictive_lower"], pred["predictive_upper"]) if noisy else (None, None)
    inside = (
        float(np.mean((rec >= lo) & (rec <= hi)))
        if noisy
        else 1.0 - float(metrics["pct_outside"]) / 100.0  # evaluate before the CSV's columns
    )
    config = json.loads((run / "config.json").read_text())
    return {
        "held_out_height_m": HEIGHTS[test],
        "inside_95_band": inside,
        "band": metrics.get("band"),
        "band_includes_force_noise": metrics.get("band_includes_force_noise", False),
        "pct_outside_metrics_json": metrics["pct_outside"],
        "inside_parameter_band": 1.0 - metrics["parameter_band"]["pct_outside"] / 100.0
        if "parameter_band" in metrics
        else None,
        "rmse_static_m": float(np.sqrt(np.mean((pred["mean"] - rec) ** 2))),
        "rmse_cantilever_m": float(np.sqrt(np.mean((cant - rec) ** 2))),
        "cantilever_EI_Nm2": ei,
        "band_width_mean_m": float(metrics["ci_width"]),
        "rhat_max": _rhat_max(run, args.warmup),
        "infer_wall_s": _wall(config),
        "n_points": int(rec.size),
        "posterior": json.loads((run / "summary.json").read_text()).get("posterior"),
    }


def _find(d, key):
    """First value under ``key`` anywhere in nested dicts (None if absent)."""
    if isinstance(d, dict):
        if key in d:
            return d[key]
        for v in d.values():
            out = _find(v, key)
            if out is not None:
                return out
    return None


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=0, help="data seed (sampler seed: seed + fold)")
    ap.add_argument("--particles", type=int, default=16, help="MH chains (infer --particles)")
    ap.add_argument(
        "--iterations", type=int, default=1100, help="MH iterations per chain (infer --iterations)"
    )
    ap.add_argument(
        "--warmup", type=float, default=0.5, help="infer --mcmc-warmup: share discarded"
    )
    ap.add_argument(
        "--tie-scale", default="0.1", help="tree --tie-scale (0.1 as the study; 'none': hard)"
    )
    ap.add_argument("--folds", default="0,1,2", help="held-out heights by index")
    ap.add_argument("--out", default=None, help="results folder (default by seed)")
    ap.add_argument("--keep", type=Path, default=None, help="keep the work folder here")
    ap.add_argument(
        "--rescore",
        action="store_true",
        help="only score the folds already run in the --keep folder (no commands run)",
    )
    args = ap.parse_args(argv)
    if args.rescore and args.keep is None:
        ap.error("--rescore needs --keep DIR (a work folder of an earlier run)")
    out = Path(args.out or f"experiments/results/stem_cli_s{args.seed}")
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp) if args.keep is None else args.keep
        work.mkdir(parents=True, exist_ok=True)
        if args.rescore:
            tree = work / "stem.yaml"
            names = [f"push_{round(1000 * h)}mm.csv" for h in HEIGHTS]
        else:
            tree, names = prepare(work, args.seed, args.tie_scale)
        tree_text = tree.read_text()
        for k in (int(v) for v in args.folds.split(",")):
            if args.rescore:
                results.append(score(work, names, k, args))
            else:
                results.append(fold(work, tree, names, k, args))
            r = results[-1]
            print(
                f"held out {r['held_out_height_m']:.2f} m: {r['inside_95_band']:.0%} inside, "
                f"RMSE {1e3 * r['rmse_static_m']:.3f} mm (cantilever "
                f"{1e3 * r['rmse_cantilever_m']:.3f} mm), R-hat max {r['rhat_max']:.3f}, "
                f"infer {r['infer_wall_s'] or float('nan'):.0f} s",
                flush=True,
            )
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(
        json.dumps({"folds": results, "args": {**vars(args), "keep": str(args.keep)}}, indent=1)
        + "\n"
    )
    (out / "stem.yaml").write_text(tree_text)
    lines = [
        "| held-out height (m) | inside 95% band | RMSE static (mm) | RMSE cantilever (mm) "
        "| band width (mm) | R-hat max | infer wall (s) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in results:
        lines.append(
            f"| {r['held_out_height_m']:.2f} | {r['inside_95_band']:.0%} | "
            f"{1e3 * r['rmse_static_m']:.3f} | {1e3 * r['rmse_cantilever_m']:.3f} | "
            f"{1e3 * r['band_width_mean_m']:.3f} | {r['rhat_max']:.3f} | "
            f"{r['infer_wall_s'] or float('nan'):.0f} |"
        )
    lines.append(
        f"\nCLI path (import-csv -> tree --kind stem -> infer --model-kind static --likelihood "
        f"gaussian --noise-force auto --sampler mh --init laplace --gradients jvp -> evaluate), "
        f"MH {args.particles} chains x {args.iterations} iterations, warm-up share "
        f"{args.warmup}, tie_scale {args.tie_scale}; data seed {args.seed}"
    )
    (out / "results.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
