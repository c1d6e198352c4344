"""``treeinfer evaluate``: held-out metrics of a run, or k-fold cross-validation of its settings."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from .. import runs
from ..data.pulls import data_grasp_fractions
from ..data.trajectories import band_csv_text, read_trajectory_dir, stack_trajectories
from ..errors import ConfigError
from ..evaluation.predictive import (
    band_arrays,
    evaluate_trajectories,
    force_noise_for,
    kfold_splits,
    mean_metrics,
    noise_for,
    write_evaluation,
)
from ..io.atomic import check_output_dir
from .common import (
    _RUN_SIM_NOTE,
    COMMAND_HELP,
    EXIT_OK,
    _base_config,
    _check_grasp,
    _metrics_md,
    _prepare_jax,
    _print_metrics,
    _print_simulation,
    _say,
    add_command_parser,
    add_model_options,
    add_out_option,
    add_run_option,
    add_simulation_options,
    check_simulation_options,
    simulator_for_run,
)
from .options import add_formats_option, figure_names

# ==== evaluate ====================================================================================
_EVALUATE_EPILOG = """\
examples:
  treeinfer evaluate --run runs/nnsvgd --data data/test --out eval/nnsvgd
  treeinfer evaluate --run runs/nnsvgd --data data/real --kfold 5 --out eval/real-5fold

Writes metrics.json, metrics.md and bands.png (95% predictive bands vs the held-out trajectories),
config.json and per recording <name>_prediction.csv (time, force, recorded, mean, lower, upper;
header first). With a pulls.yaml in DIR each recording is predicted at its own grasp point.
Metrics (treeinfer.evaluation.metrics.summarize): average 95% band width (m), share of
ground-truth points outside the band (%), predictive NLL of the held-out points under the
per-step KDE, the posterior NLL (particle-averaged kT-scaled loss on the held-out data) and,
if DIR has a true_params.json, the posterior against the true parameters (log space).

--kfold K (the paper's real-to-sim protocol): the trajectories in DIR, in file-name order, are
split into K contiguous folds; for each fold the posterior is inferred afresh on the other K-1
folds with the run's sampler settings (sampler, particles, iterations, kT, eta, seed) and
evaluated on the held-out fold. metrics.json has the per-fold and the mean metrics.
"""


def configure_evaluate(subparsers) -> argparse.ArgumentParser:
    p = add_command_parser(
        subparsers,
        "evaluate",
        help=COMMAND_HELP["evaluate"],
        description="Score a run's posterior on held-out trajectories: 95% band width, share of "
        "points outside the band, predictive and posterior NLL, posterior vs truth when known; or "
        "cross-validate the run's settings with --kfold.",
        epilog=_EVALUATE_EPILOG,
    )
    add_run_option(p)
    p.add_argument(
        "--data", required=True, type=Path, metavar="DIR", help="folder of held-out trajectory CSVs"
    )
    add_out_option(p)
    p.add_argument(
        "--kfold",
        type=int,
        metavar="K",
        help="k-fold cross-validation over DIR's trajectories (K >= 2)",
    )
    p.add_argument(
        "--grasp-fraction",
        type=float,
        metavar="F",
        help="where along the grasped branch DIR's data were recorded, in (0, 1] (default: as "
        "the run's training data)",
    )
    p.add_argument("--force", action="store_true", help="replace a non-empty output folder")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (--kfold)")
    add_formats_option(p, "figure (bands.png)")
    add_model_options(p, run=True)
    add_simulation_options(p, _RUN_SIM_NOTE)
    p.add_argument(
        "--allow-modified",
        action="store_true",
        help="use the run even if its files changed since `infer` wrote them (checksums in its "
        "config.json); recorded in the output",
    )
    return p


def _prediction_csvs(pred, obs, trajs) -> dict[str, str]:
    """Per recording ``<stem>_prediction.csv``: time, force, recorded, mean, lower, upper (the
    parameter band) and, when the run has a noise model, predictive_lower, predictive_upper (the
    band that metrics.json scores), as ``predict`` writes."""
    out = {}
    noisy = getattr(pred, "predictive_lower", None) is not None
    for b, t in enumerate(trajs):
        n = t.n_steps
        out[f"{Path(t.source).stem}_prediction.csv"] = band_csv_text(
            np.asarray(t.time) - t.time[0],
            obs.force[b, :n],
            obs.displacement[b, :n],
            pred.mean[b, :n],
            pred.lower[b, :n],
            pred.upper[b, :n],
            pred.predictive_lower[b, :n] if noisy else None,
            pred.predictive_upper[b, :n] if noisy else None,
        )
    return out


def _channel_bands(args, run, sim, model, trajs, metrics: dict, md: list, grasp=None):
    """The data folder's observation channels (channels.yaml) against the run's posterior (any
    model: the paper's, static, stiffness only, each recording's own pull):
    ``({file name: CSV text}, bands)``; their metrics go to ``metrics["channels"]`` and ``md``."""
    from ..data.channels import read_channels
    from ..evaluation.channel_bands import band_csv, channel_bands

    channels = read_channels(args.data, run.tree, trajs)
    if not channels:
        return {}, []
    bands = channel_bands(
        sim, run.theta, run.labels, channels, trajs, run.config.get("problem"), run.stable,
        model=model, grasp_fraction=None if grasp is None else np.atleast_1d(grasp),
    )  # fmt: skip
    metrics["channels"] = {b.channel.name: b.metrics() for b in bands}
    md += ["", "## observation channels", "", "| channel | kind | point | band | outside [%] | "
           "rmse | unit |", "|---|---|---|---|---|---|---|"]  # fmt: skip
    for name, cm in metrics["channels"].items():
        md.append(
            f"| {name} | {cm['kind']} | {cm['point']} | {cm['band']} | {cm['pct_outside']:.2f} | "
            f"{cm['rmse']:.4g} | {cm['unit']} |"
        )
    return {f"channel_{b.channel.name}_prediction.csv": band_csv(b) for b in bands}, bands


def run_evaluate(args: argparse.Namespace) -> int:
    _check_grasp(args.grasp_fraction)
    check_output_dir(args.out, args.force, "evaluation", inputs=[args.run, args.data, args.model])
    _prepare_jax()
    check_simulation_options(args)
    cache = runs.SimulatorCache()  # this command's simulators (the run's, and k-fold's)
    run = runs.load_run(args.run, cache, allow_modified=args.allow_modified, model_file=args.model)
    for note in run.notes:
        _say(f"warning: {note}")
    trajs = read_trajectory_dir(args.data)
    dt = trajs[0].dt
    if not math.isclose(dt, run.sim.obs_dt, rel_tol=1e-6):
        raise ConfigError(
            f"{args.data}: trajectories have dt={dt:g} s but run {args.run} was inferred at "
            f"dt={run.sim.obs_dt:g} s; resample them to the run's step"
        )
    truth = runs.read_true_params(run.tree, args.data)
    grasp = args.grasp_fraction if args.grasp_fraction is not None else run.grasp_fraction
    # every model pulls at any branch and in any direction (each recording's own, pulls.yaml)
    own = data_grasp_fractions(args.data, run.tree, [t.source for t in trajs], True, True)
    if own is not None:  # each recording at its own grasp point (the folder's pulls.yaml)
        if args.grasp_fraction is not None and not np.allclose(own, args.grasp_fraction):
            raise ConfigError(
                f"--grasp-fraction {args.grasp_fraction:g}: {args.data}/pulls.yaml records these "
                f"pulls at {', '.join(f'{g:g}' for g in own)}; a prediction at another point is "
                "not comparable with the recordings (leave --grasp-fraction out)"
            )
        grasp = own
    config = _base_config("evaluate", args)
    config.update(
        run=str(Path(args.run).resolve()),
        data_files=runs.data_manifest(args.data),
        dt=dt,
        grasp_fraction=(
            np.asarray(grasp).tolist() if grasp is not None else run.tree.grasp_fraction
        ),
        run_options=run.config["options"],
        integrity_notes=list(run.notes),
        run_fit_status=run.summary.get("status"),
    )
    if args.kfold is None:
        from ..inference.static import model_with_pulls

        model, grasp = model_with_pulls(
            run.model, args.data, [t.source for t in trajs], grasp, tree=run.tree
        )
        sim = simulator_for_run(run, args, stack_trajectories(trajs).force, grasp, cache)
        config["simulation"] = runs.simulation_summary(sim)
        _print_simulation(config["simulation"])
        sigma, kind = noise_for(run.theta, run.sim.n_joints, run.config.get("problem"))
        m, pred, obs = evaluate_trajectories(
            sim,
            run.theta,
            list(run.labels),
            trajs,
            run.kT,
            grasp,
            truth,
            run.stable,
            noise_sigma=sigma,
            noise_kind=kind,
            model=model,
            force_noise=force_noise_for(run.config.get("problem")),
        )
        metrics = {"run": str(args.run), "data": str(args.data), "metrics": m}
        md = [f"# treeinfer evaluate: run `{args.run}` on `{args.data}`", ""] + _metrics_md(
            "held-out metrics", m
        )
        channel_files, bands = _channel_bands(args, run, sim, model, trajs, metrics, md, grasp)
        write_evaluation(
            args.out,
            metrics,
            band_arrays([(pred, obs)]),
            [t.source for t in trajs],
            dt,
            config,
            args.force,
            md,
            extra_files={**_prediction_csvs(pred, obs, trajs), **channel_files},
            formats=args.formats or ("png",),
        )
        _print_metrics(m, f"held-out metrics on {len(trajs)} trajectories of {args.data}")
        if bands:
            from ..evaluation.channel_bands import plot_channel_bands
            from ..evaluation.plots import save_figure

            save_figure(plot_channel_bands(bands)[0], Path(args.out) / "channels.png",
                        formats=args.formats)  # fmt: skip
            for name, cm in metrics["channels"].items():
                print(
                    f"  channel {name} ({cm['kind']} at {cm['point']}): {cm['pct_outside']:.1f}% "
                    f"outside the 95% {cm['band']} band, rmse {cm['rmse']:.3g} {cm['unit']}"
                )
        print(
            f"wrote {args.out}/ (metrics.json, metrics.md, {figure_names('bands', args.formats)}, "
            "config.json, "
            "<recording>_prediction.csv per recording)"
        )
        return EXIT_OK

    kfold_splits(len(trajs), args.kfold)  # K too large: fail before any inference
    if own is not None:  # each recording at its own point: runs.kfold splits them with the folds
        grasp = float(own[0]) if np.allclose(own, own[0]) else own
    o = run.config["options"]
    _say(
        f"{args.kfold}-fold cross-validation on {len(trajs)} trajectories with the run's settings "
        f"({o['sampler']}, {o['particles']} particles x {o['iterations']} iterations per fold)"
    )
    results = runs.kfold(
        run.config,
        run.tree,
        trajs,
        args.kfold,
        grasp,
        truth,
        progress=not args.no_progress,
        log=_say,
        cache=cache,
        data_dir=args.data,
    )
    mean, std = mean_metrics([r.metrics for r in results])
    folds = [
        {
            "fold": r.fold,
            "train": r.train,
            "test": r.test,
            "metrics": r.metrics,
            "warnings": list(r.warnings),
        }
        for r in results
    ]
    metrics = {
        "run": str(args.run),
        "data": str(args.data),
        "kfold": args.kfold,
        "folds": folds,
        "mean": mean,
        "std": std,
    }
    md = [
        f"# treeinfer evaluate --kfold {args.kfold}: settings of `{args.run}` on `{args.data}`",
        "",
        "| fold | held out | band width [mm] | outside [%] | predictive NLL [nats/point] | "
        "posterior NLL |",
        "|---|---|---|---|---|---|",
    ]
    for r in results:
        m = r.metrics
        md.append(
            f"| {r.fold} | {', '.join(r.test)} | {1000 * m['ci_width']:.4g} | "
            f"{m['pct_outside']:.2f} | {m['predictive_nll_per_point']:.4g} | "
            f"{m.get('posterior_nll', float('nan')):.4g} |"
        )
    md.append(
        f"| mean | | {1000 * mean['ci_width']:.4g} | {mean['pct_outside']:.2f} | "
        f"{mean['predictive_nll_per_point']:.4g} | "
        f"{(mean.get('posterior_nll') or float('nan')):.4g} |"
    )
    md.append("")
    for r in results:
        md += _metrics_md(f"fold {r.fold} (held out: {', '.join(r.test)})", r.metrics)
        if r.metrics.get("channels"):  # the held-out fold's observation channels
            md += ["", "| channel | kind | point | band | outside [%] | rmse | unit |",
                   "|---|---|---|---|---|---|---|"]  # fmt: skip
            md += [
                f"| {n} | {c['kind']} | {c['point']} | {c['band']} | {c['pct_outside']:.2f} | "
                f"{c['rmse']:.4g} | {c['unit']} |"
                for n, c in r.metrics["channels"].items()
            ]
    titles = [f"{name} (fold {r.fold})" for r in results for name in r.test]
    # per-fold observations for the band grid

    by_name = {t.source: t for t in trajs}
    pairs = [(r.prediction, stack_trajectories([by_name[n] for n in r.test])) for r in results]
    labels = list(run.labels)
    extra = {
        f"fold_{r.fold}_particles.csv": runs.particles_csv(
            r.theta, labels, np.zeros(len(r.theta)), r.prediction.valid
        )
        for r in results
    }
    write_evaluation(
        args.out,
        metrics,
        band_arrays(pairs),
        titles,
        dt,
        config,
        args.force,
        md,
        extra,
        formats=args.formats or ("png",),
    )
    for r in results:
        _print_metrics(r.metrics, f"fold {r.fold} (held out {', '.join(r.test)})")
        for name, c in (r.metrics.get("channels") or {}).items():
            print(
                f"  fold {r.fold}: channel {name} ({c['kind']} at {c['point']}): "
                f"{c['pct_outside']:.1f}% outside the 95% {c['band']} band"
            )
        for w in r.warnings:
            print(f"  fold {r.fold}: {w}")
    print(
        f"mean over {args.kfold} folds: 95% band {1000 * mean['ci_width']:.3g} mm, "
        f"{mean['pct_outside']:.1f}% outside, predictive NLL "
        f"{mean['predictive_nll_per_point']:.3g} nats/point"
    )
    print(
        f"wrote {args.out}/ (metrics.json, metrics.md, {figure_names('bands', args.formats)}, "
        "config.json, fold_*_particles.csv)"
    )
    return EXIT_OK
