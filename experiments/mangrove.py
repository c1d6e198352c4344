"""Issue 30 sections 3 and 4: static winch pulling tests of mangrove trees, the static chain
model with inclinometer observations (elastic or viscoelastic joints, a softening root plate,
i.i.d., AR(1) or AR(1) + gain-error residuals) against a beam baseline, on held-out parts of
each record.

Data: ``../shared/data/mangrove`` (``pull_tests/*.pul`` and ``trees.csv``), from
``jack-w-hill/mangrove-tree-strength``; paper: Hill JW, Bennion V, Lovelock CE (2024), *Mangrove
tree strength estimated with field experiments*, Ecological Engineering 203: 107259,
doi:10.1016/j.ecoleng.2024.107259. The data are read where they are, never copied.

Per test:

1. the ``.pul`` file and its metadata row -> force along the cable and the signed tilts of the
   root and trunk inclinometers on one time base (``treeinfer.data.pull_test``);
2. fit on the first half (in time) of the loading ramp: the two-link chain
   (``treeinfer.inference.pulltest``: root hinge at the ground, stem hinge at the root clino,
   cable at the sling height and angle), NUTS over both stiffnesses and each channel's noise,
   several ways (``--models``, :data:`MODELS`): springs or standard linear solids per joint
   (``creep``), a fast lag on the root or every joint (``lag``, ``lag2``), a softening root
   plate (``soft``), i.i.d., AR(1) or AR(1) + gain-error residuals; the default
   (:data:`BEST`) is the one that reaches the targets on all four tests. The force drives the
   models through the load cell's level crossings (``--force dequantised``, the default) or
   as recorded; the uniform Euler-Bernoulli cantilever on a root-plate spring and a spring per
   inclinometer by least squares are the baselines;
3. held out: the second half of the ramp (``ramp2``), the hold at the peak (``hold``: creep) and
   the release (``release``: hysteresis); per part and channel, the share of recorded tilts
   inside the 95% posterior predictive band, and the RMSE of the chain's predictive mean and of
   the beam's prediction; and the check of the fit's residuals (their lag-1 autocorrelation
   on the fitted samples).

    nice python experiments/mangrove.py [--data ../shared/data/mangrove] [--tests a,b]
        [--models soft+lag2+creep+ar1+gain,...] [--force dequantised|recorded] [--merge]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import pickle
import platform
import sys
import time
from pathlib import Path

if __name__ == "__main__":  # run as a script from anywhere: use this checkout's treeinfer
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np

from experiments._mangrove_tables import PARTS, _deg, figure, markdown

REPO = Path(__file__).resolve().parent.parent
TESTS = ("halloran_1", "halloran_10", "gladstone_21", "gladstone_31")
MODELS = {  # name -> (creep, noise, lag: the root's fast lag element[, soft: root softening])
    "elastic": (False, "iid", False),
    "elastic+ar1": (False, "ar1", False),
    "creep": (True, "iid", False),
    "creep+ar1": (True, "ar1", False),
    "lag+creep+ar1": (True, "ar1", True),
    "lag2+creep+ar1": (True, "ar1", "all"),  # the fast lag on every joint
    "soft+lag2+creep+ar1": (True, "ar1", "all", True),  # and a softening root plate
    "soft+creep+ar1": (True, "ar1", False, True),
    # and a slowly varying gain error per channel (model error proportional to the tilt)
    "soft+lag2+creep+ar1+gain": (True, "ar1+gain", "all", True),
    "soft+creep+ar1+gain": (True, "ar1+gain", False, True),
    "lag+creep+ar1+gain": (True, "ar1+gain", True),
}
BEST = "soft+lag2+creep+ar1+gain"  # the default: the model results/mangrove/README.md reports
CITATION = (
    "Hill JW, Bennion V, Lovelock CE (2024) Mangrove tree strength estimated with field "
    "experiments. Ecological Engineering 203: 107259. doi:10.1016/j.ecoleng.2024.107259"
)


def shared_data() -> Path | None:
    """``$TREEINFER_SHARED_DATA/mangrove``, else ``shared/data/mangrove`` beside the repository
    or any folder above it (a worktree lies deeper than the main checkout)."""
    env = os.environ.get("TREEINFER_SHARED_DATA")
    cands = [Path(env) / "mangrove"] if env else []
    cands += [p / "shared" / "data" / "mangrove" for p in (REPO, *REPO.parents)]
    return next((c for c in cands if (c / "trees.csv").is_file()), None)


SPLITS = ("ramp", "loading")


def windows(test, split: str = "ramp") -> dict[str, slice]:
    """The fitted and held-out parts. ``ramp``: fit on the first half of the loading ramp;
    ``loading``: fit on the whole loading (ramp and hold), only the release held out (what a
    creep model needs to see to tell its relaxation time)."""
    ph, t = test.phases, test.time
    if split == "loading":
        empty = slice(ph["release_start"], ph["release_start"])
        return {
            "fit": slice(ph["ramp_start"], ph["release_start"]),
            "ramp2": empty,
            "hold": empty,
            "release": slice(ph["release_start"], ph["release_end"] + 1),
        }
    mid = int(np.searchsorted(t, (t[ph["ramp_start"]] + t[ph["ramp_end"]]) / 2))
    return {
        "fit": slice(ph["ramp_start"], mid),
        "ramp2": slice(mid, ph["ramp_end"] + 1),
        "hold": slice(ph["ramp_end"] + 1, ph["release_start"]),
        "release": slice(ph["release_start"], ph["release_end"] + 1),
    }


def _rmse(a, b) -> float:
    d = np.asarray(a) - np.asarray(b)
    d = d[np.isfinite(d)]
    return float(np.sqrt(np.mean(d**2))) if d.size else math.nan


def label(kind: str, force: str, hist: bool = False) -> str:
    """A fit's name in the tables: the model, ``/dq`` when driven by the dequantised force,
    ``/hist`` when from the record's start (``--history``)."""
    return kind + ("" if force == "recorded" else "/dq") + ("/hist" if hist else "")


def _order(lab: str) -> tuple[int, str]:
    kind, _, force = lab.partition("/")
    return (list(MODELS).index(kind), force)


def load_test(name: str, data: Path, args):
    """The test (force as ``--force`` says), its set-up and its chain model."""
    from treeinfer.data import make_pull_test, read_pul, read_test_setups
    from treeinfer.inference.pulltest import pull_model

    setup = read_test_setups(data / "trees.csv")[name]
    test = make_pull_test(read_pul(data / "pull_tests" / f"{name}.pul"), setup)
    if args.force == "dequantised":  # the load cell's 10 N staircase -> its level crossings
        from treeinfer.data.pull_test import dequantised_force

        test = dataclasses.replace(test, force=dequantised_force(test.time, test.force))
    return test, setup, pull_model(setup)


HISTORY_STEP_S = 1.0  # s: the load before the ramp, thinned (a slow pre-load; creep >= 5 s)


def history(test, start: int, on: bool) -> np.ndarray:
    """Indices of the samples before ``start`` (the fitted part's first) that drive the model
    without being fitted (``--history``): from the record's start, at least
    :data:`HISTORY_STEP_S` apart. Why: the creep and lag elements start at rest where the
    simulation starts; a tree held under a pre-load (halloran_1: 10-35 N for 80 s before the
    ramp) has crept already, and a model started at the ramp sees the tilt there too high."""
    if not on or start == 0:
        return np.zeros(0, int)
    t = test.time[:start]
    return np.flatnonzero(np.diff(np.floor((t - t[0]) / HISTORY_STEP_S), prepend=-1) > 0)


def run_test(name: str, data: Path, args, kind: str = "elastic") -> tuple[dict, dict]:
    from treeinfer.inference.pulltest import fit_pull_test

    creep, noise, lag, *soft = MODELS[kind]
    t0 = time.time()
    test, setup, model = load_test(name, data, args)
    chans = list(model.sensors)
    win = windows(test, args.split)
    y = np.stack([test.tilt[c] for c in chans])  # [C, T] rad
    fit = win["fit"]
    hist = history(test, fit.start, args.history)
    tilt_fit = np.concatenate([np.full((len(chans), hist.size), np.nan), y[:, fit]], axis=1)
    post = fit_pull_test(
        model,
        test.force[np.r_[hist, fit.start : fit.stop]],
        tilt_fit,
        time=test.time[np.r_[hist, fit.start : fit.stop]],
        num_warmup=args.warmup,
        num_samples=args.samples,
        num_chains=args.chains,
        seed=args.seed,
        noise=noise,
        creep=creep,
        lag=lag,
        soft=bool(soft and soft[0]),
    )
    result = {
        "test": name,
        "model": label(kind, args.force, args.history),
        "force": args.force,
        "soft": bool(soft and soft[0]),
        "lag": lag,
        "noise": noise,
        "creep": creep,
        "tree_id": setup.tree_id,
        "species": setup.species,
        "site": setup.site,
        "peak_force_N": float(test.force.max()),
        "cable_angle_deg": math.degrees(setup.cable_angle),
        "sling_height_m": setup.sling_height,
        "channels": {
            c: {"height_m": test.channels[c].height, "link": model.sensors[c]} for c in chans
        },
        "phases_s": {k: float(test.time[v]) for k, v in test.phases.items()},
        "fit_samples": int(fit.stop - fit.start),
        "posterior": post.summary(),
        "diagnostics": post.diagnostics,
    }
    result, curves = score(test, setup, model, post, args, result)
    result["wall_s"] = time.time() - t0
    return result, curves


def score(test, setup, model, post, args, result: dict) -> tuple[dict, dict]:
    """The band(s), the baselines and the per-part scores of a fitted posterior ``post``
    (``result`` completed). An ``ar1+gain`` fit is scored with both gain bands, the
    stationary marginal and the forecast from the fitted part (``coverage_<band>``,
    ``band_width_<band>``); ``coverage`` and ``band_width`` are those of ``--gain-band``."""
    from treeinfer.inference.pulltest import (
        beam_predict,
        fit_beam,
        fit_springs,
        predictive_band,
        residual_check,
        springs_predict,
    )

    chans = list(model.sensors)
    win = windows(test, args.split)
    y = np.stack([test.tilt[c] for c in chans])  # [C, T] rad
    fit = win["fit"]
    span = slice(win["fit"].start, win["release"].stop)
    # the creep state starts at rest at the ramp's start (the fit window's and the band's), or
    # with --history at the record's start, the load before the ramp driving it unobserved
    hist = history(test, fit.start, args.history)
    sim = np.r_[hist, span.start : span.stop]
    kw = dict(n_draws=args.draws, seed=args.seed, time=test.time[sim])
    fit_tilt = np.concatenate([np.full((len(chans), hist.size), np.nan), y[:, fit]], axis=1)
    bands = {"stationary": predictive_band(model, post, test.force[sim], **kw)}
    if post.noise == "ar1+gain":
        bands["forecast"] = predictive_band(model, post, test.force[sim], fit_tilt=fit_tilt, **kw)
    bands = {k: {q: v[:, hist.size :] for q, v in b.items()} for k, b in bands.items()}
    choice = args.gain_band if args.gain_band in bands else "stationary"
    band = bands[choice]
    heights = [test.channels[c].height for c in chans]
    beam = fit_beam(heights, setup.sling_height, setup.cable_angle, test.force[fit], y[:, fit])
    beam_all = beam_predict(beam, heights, setup.sling_height, setup.cable_angle, test.force[span])
    springs = fit_springs(setup.sling_height, setup.cable_angle, test.force[fit], y[:, fit])
    springs_all = springs_predict(springs, setup.sling_height, setup.cable_angle, test.force[span])
    off = span.start
    parts = {}
    for part in ("fit", *PARTS, "heldout"):
        if part == "heldout":  # the second half of the ramp and the release (not the hold)
            idx = np.r_[
                win["ramp2"].start - off : win["ramp2"].stop - off,
                win["release"].start - off : win["release"].stop - off,
            ]
        else:
            idx = np.arange(win[part].start - off, win[part].stop - off)
        rec = {}
        for i, c in enumerate(chans):
            yy = y[i, off:][idx]
            ok = np.isfinite(yy)

            def cover(b):
                inside = (yy >= b["lo"][i, idx]) & (yy <= b["hi"][i, idx])
                return float(inside[ok].mean()) if ok.any() else math.nan

            def width(b):  # the band's sharpness: a band as wide as the tilt covers anything
                return float(np.mean(b["hi"][i, idx] - b["lo"][i, idx]))

            rec[c] = {
                "n": int(ok.sum()),
                "coverage": cover(band),
                "rmse_chain": _rmse(band["mean"][i, idx], yy),
                "band_width": width(band),
                # of the model's tilt alone: the parameters' share of the width
                "band_width_model": float(
                    np.mean(band["model_hi"][i, idx] - band["model_lo"][i, idx])
                ),
                "rmse_beam": _rmse(beam_all[i, idx], yy),
                "rmse_springs": _rmse(springs_all[i, idx], yy),
            }
            if len(bands) > 1:
                for k, b in bands.items():
                    rec[c] |= {f"coverage_{k}": cover(b), f"band_width_{k}": width(b)}
                # the predictive mean with the gain's forecast (the model's mean: rmse_chain)
                rec[c]["rmse_centre"] = _rmse(bands["forecast"]["centre"][i, idx], yy)
        parts[part] = rec
    n_fit = fit.stop - fit.start
    check = residual_check(band["mean"][:, :n_fit], y[:, fit])
    result = result | {
        "gain_band": choice if post.noise == "ar1+gain" else None,
        "history_samples": int(hist.size),
        "residual_lag1": {c: float(v) for c, v in zip(chans, check["lag1"])},
        "beam": {"k_root": beam.k_root, "ei": beam.ei, "fit_rmse": beam.rmse},
        "springs": {c: float(k) for c, k in zip(chans, springs)},
        "parts": parts,
    }
    curves = {
        "time": test.time[span],
        "tilt": y[:, span],
        "band": band,
        "beam": beam_all,
        "springs": springs_all,
        "fit": (test.time[fit.start], test.time[fit.stop - 1]),
        "phases": {k: test.time[v] for k, v in test.phases.items()},
        "channels": chans,
        # kept for bands and checks redrawn without refitting (the pickle in partial/)
        "posterior": post,
        "force": test.force[span],
        "fit_slice": (fit.start - span.start, fit.stop - span.start),
    }
    return result, curves


def innovations_lag1(r: dict, cv: dict) -> dict | None:
    """An ``ar1`` or ``ar1+gain`` fit's check: the lag-1 autocorrelation of its standardised
    Kalman innovations on the fitted samples, at the posterior means of the noise parameters
    (``ar1+gain``: the two-state filter, the predictive mean as the gain's coefficient)."""
    from treeinfer.inference.pulltest import (
        gain_ou_innovations,
        lag1_autocorrelation,
        ou_white_innovations,
    )

    if r["noise"] not in ("ar1", "ar1+gain"):
        return None
    n, chans = r["fit_samples"], cv["channels"]
    mean = cv["band"]["mean"][:, :n]
    resid = cv["tilt"][:, :n] - mean
    keys = ("sigma_w", "sigma_a", "tau_ar")
    keys += ("sigma_g", "tau_g") if r["noise"] == "ar1+gain" else ()
    p = [np.array([r["posterior"][f"{k}_{c}"]["mean"] for c in chans]) for k in keys]
    mask = np.isfinite(resid)
    if r["noise"] == "ar1":
        z = ou_white_innovations(np.nan_to_num(resid), mask, cv["time"][:n], *p)
    else:
        z = gain_ou_innovations(np.nan_to_num(resid), mean, mask, cv["time"][:n], *p)
    return {c: float(v) for c, v in zip(chans, lag1_autocorrelation(z))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, help="the mangrove folder (default: found)")
    ap.add_argument("--tests", default=",".join(TESTS), help="comma-separated test names")
    ap.add_argument("--out", type=Path, default=REPO / "experiments" / "results" / "mangrove")
    ap.add_argument("--warmup", type=int, default=300)
    ap.add_argument("--samples", type=int, default=500)
    ap.add_argument("--chains", type=int, default=2)
    ap.add_argument("--draws", type=int, default=400, help="posterior draws in the band")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--force",
        choices=("recorded", "dequantised"),
        default="dequantised",
        help="the force driving the models: as recorded (10 N steps) or through its level "
        "crossings (treeinfer.data.pull_test.dequantised_force)",
    )
    ap.add_argument("--split", choices=SPLITS, default="ramp", help="fitted part (windows())")
    ap.add_argument(
        "--gain-band",
        choices=("stationary", "forecast"),
        default="stationary",
        help="an ar1+gain fit's band: the gain error's stationary marginal, or its forecast "
        "from the fitted part (treeinfer.inference.pulltest.gain.gain_band_terms); both scored",
    )
    ap.add_argument(
        "--history",
        action="store_true",
        help="drive the models from the record's start (the pre-load, thinned to 1 s, not "
        "fitted) so that creep and lag start at rest before the load, not at the ramp",
    )
    ap.add_argument(
        "--rescore",
        action="store_true",
        help="redraw the bands and scores of the fits kept in partial/ from their posteriors "
        "(pickles that keep one), refitting nothing",
    )
    ap.add_argument(
        "--models",
        default=BEST,
        help=f"comma-separated: {', '.join(MODELS)} (default: {BEST}, the best on all four)",
    )
    ap.add_argument(
        "--tables-only",
        action="store_true",
        help="write the tables and figures from the fits kept in partial/, fitting nothing",
    )
    ap.add_argument("--keep-partial", action="store_true", help="keep partial/ at the end")
    ap.add_argument(
        "--merge",
        action="store_true",
        help="keep OUT/results.json's fits of other models or tests in the tables (their "
        "figures are not redrawn)",
    )
    args = ap.parse_args(argv)
    data = args.data or shared_data()
    if data is None:
        print("the mangrove data (../shared/data/mangrove) is absent; give --data", file=sys.stderr)
        return 2
    kinds = [s.strip() for s in args.models.split(",") if s.strip()]
    bad = [k for k in kinds if k not in MODELS]
    if bad:
        print(f"--models: unknown {bad}; expected {list(MODELS)}", file=sys.stderr)
        return 2
    from treeinfer.io import atomic_write_text

    t0, cpu0 = time.time(), time.process_time()
    results, curves = [], {}
    args.out.mkdir(parents=True, exist_ok=True)
    # each fit is kept as it ends: a run stopped on the shared box resumes where it was
    # (``partial/`` goes once every fit is in the tables)
    partial = args.out / "partial"
    partial.mkdir(exist_ok=True)
    resumed = 0
    for kind in kinds:
        lab = label(kind, args.force, args.history)
        curves[lab] = {}
        for name in [s.strip() for s in args.tests.split(",") if s.strip()]:
            kept = partial / f"{lab.replace('/', '_')}_{name}.pkl"
            if kept.is_file():
                r, cv = pickle.loads(kept.read_bytes())
                resumed += 1
                if args.rescore and "posterior" in cv:  # same posterior, bands redrawn
                    test, setup, model = load_test(name, data, args)
                    r, cv = score(test, setup, model, cv["posterior"], args, r)
                    kept.write_bytes(pickle.dumps((r, cv)))
            elif args.tables_only:
                print(f"{name} ({lab}): not fitted yet, left out (--tables-only)", flush=True)
                continue
            else:
                print(f"{name} ({lab}) ...", flush=True)
                r, cv = run_test(name, data, args, kind)
                kept.write_bytes(pickle.dumps((r, cv)))
            r["innovations_lag1"] = innovations_lag1(r, cv)
            results.append(r)
            curves[lab][name] = cv
            h = r["parts"]["heldout"]
            print(
                "  held out: coverage "
                + ", ".join(f"{c} {m['coverage']:.1%}" for c, m in h.items())
                + "; RMSE chain/beam/springs (deg) "
                + ", ".join(
                    f"{c} "
                    + "/".join(_deg(m[k]) for k in ("rmse_chain", "rmse_beam", "rmse_springs"))
                    for c, m in h.items()
                )
                + f"; lag-1 {r['residual_lag1']} ({r['wall_s']:.0f} s)",
                flush=True,
            )
        if curves[lab]:
            stem = lab.replace("+", "_").replace("/", "_")
            figure(curves[lab], args.out / f"bands_{stem}.png", lab)
    import jax
    import numpyro

    kept = []
    if args.merge and (args.out / "results.json").is_file():  # earlier fits, other models/tests
        old = json.loads((args.out / "results.json").read_text())
        done = {(r["test"], r["model"]) for r in results}
        kept = [r for r in old["results"] if (r["test"], r["model"]) not in done]
        results = sorted(kept + results, key=lambda r: _order(r["model"]))
    config = {
        "command": " ".join(["nice python experiments/mangrove.py", *(argv or sys.argv[1:])]),
        "data": str(data),
        "tests": sorted({r["test"] for r in results}),
        "models": list(dict.fromkeys(r["model"] for r in results)),
        "split": args.split,
        "gain_band": args.gain_band,
        "history": args.history,
        "force": args.force,
        "warmup": args.warmup,
        "samples": args.samples,
        "chains": args.chains,
        "draws": args.draws,
        "seed": args.seed,
        "citation": CITATION,
        "versions": {
            "python": platform.python_version(),
            "jax": jax.__version__,
            "numpyro": numpyro.__version__,
            "numpy": np.__version__,
        },
        "wall_s": time.time() - t0,
        "cpu_s": time.process_time() - cpu0,
        "fits_resumed": resumed,
        "fits_merged": len(kept),
        "fit_wall_s": sum(r["wall_s"] for r in results),
    }
    atomic_write_text(
        args.out / "results.json",
        json.dumps({"config": config, "results": results}, indent=2, default=float) + "\n",
    )
    atomic_write_text(args.out / "results.md", markdown(results, config))
    for kind in kinds if not args.keep_partial else ():  # only this run's: runs may share it
        lab = label(kind, args.force, args.history)
        for name in {r["test"] for r in results if r["model"] == lab}:
            (partial / f"{lab.replace('/', '_')}_{name}.pkl").unlink(missing_ok=True)
    if not any(partial.iterdir()):
        partial.rmdir()
    print(f"wrote {args.out}/results.json, results.md, bands_*.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
