"""``treeinfer predict``: the posterior predictive band of a run under a force profile."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

from .. import runs
from ..data.forces import from_spec
from ..data.pulls import PULLS_FILE, ResolvedPull, check_same_pull, load_data_pulls, pull_direction
from ..data.trajectories import ForceProfile, band_csv_text, read_force_profile
from ..errors import ConfigError
from ..evaluation.metrics import fraction_outside
from ..evaluation.plots import plot_trajectory_bands, save_figure
from ..evaluation.predictive import force_noise_for, noise_for, predict_run
from ..io.atomic import atomic_write_text, check_output_dir, staged_output_dir
from .common import (
    _RUN_SIM_NOTE,
    COMMAND_HELP,
    EXIT_OK,
    _base_config,
    _check_grasp,
    _prepare_jax,
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
from .options import OverwriteOrOldValue, add_deprecated, add_formats_option, figure_names

# ==== predict =====================================================================================
_PREDICT_EPILOG = """\
examples:
  treeinfer predict --run runs/nnsvgd --force-csv data/test/traj_000.csv --out pred/t0
  treeinfer predict --run runs/nnsvgd --force-csv pull.csv --grasp-fraction 0.5 --out pred/mid
  treeinfer predict --run runs/nnsvgd --profile 'hold:peak=6,ramp=0.5,hold=1,release=0.5' \\
      --duration 3 --out pred/hold

FORCE.csv is a trajectory CSV (time,force,displacement[,velocity]: its displacement is drawn as
ground truth) or a force profile with only time,force columns; its time step must be the run's.
--profile SPEC samples a profile spec instead (as in `treeinfer simulate --profile`; see its help).
Writes prediction.csv (time, force, recorded, mean, lower, upper; s, N, m; header first),
prediction.png and config.json. A run with observation channels (channels.yaml) also writes
channels/<channel>_prediction.csv and channels.png: the recording's own channels where its
folder's channels.yaml names it, else one band per sensor the run was trained with.
Particles whose simulation is unstable are left out and counted.
A recording is predicted at its own grasp point (its folder's pulls.yaml); predicted elsewhere
(--grasp-fraction), it is not compared: a warning says so and 'recorded' stays empty.
--force alone replaces a non-empty --out folder, as in every command.
"""


def configure_predict(subparsers) -> argparse.ArgumentParser:
    p = add_command_parser(
        subparsers,
        "predict",
        help=COMMAND_HELP["predict"],
        description="Simulate every posterior particle of a run under a force profile (a CSV or a "
        "profile spec), optionally grasped at another point of the branch, and write the mean "
        "displacement with its 95% predictive band (per-time-step KDE over the particles).",
        epilog=_PREDICT_EPILOG,
    )
    add_run_option(p)
    p.add_argument(
        "--force-csv",
        dest="force_file",
        type=Path,
        metavar="FORCE.csv",
        help="force profile or trajectory CSV",
    )
    p.add_argument(
        "--profile", metavar="SPEC", help="force profile spec, e.g. 'ramp:peak=5,ramp=1'"
    )
    p.add_argument("--duration", type=float, metavar="S", help="s, length of a --profile")
    p.add_argument(
        "--dt", type=float, metavar="S", help="s, sample step of a --profile (default: the run's)"
    )
    p.add_argument(
        "--grasp-fraction",
        type=float,
        metavar="F",
        help="where along the grasped branch the force acts, in (0, 1] (default: a recording's "
        "own grasp point from its folder's pulls.yaml, else where the run's training data were "
        "recorded)",
    )
    add_out_option(p)
    p.add_argument(
        "--force",
        dest="force_flag",
        action=OverwriteOrOldValue,
        old_dest="force_file",
        old_flag="--force-csv",
        metavar="",
        help="replace a non-empty output folder, as in every command (the old `--force FILE` is "
        "read as --force-csv FILE, with a deprecation message)",
    )
    add_model_options(p, run=True)
    add_simulation_options(p, _RUN_SIM_NOTE)
    p.add_argument(
        "--allow-modified",
        action="store_true",
        help="use the run even if its files changed since `infer` wrote them (checksums in its "
        "config.json); recorded in the output",
    )
    add_formats_option(p, "figure (prediction.png)")
    add_deprecated(p, "--overwrite", "--force")
    return p


def _resolve_force_options(args: argparse.Namespace) -> bool:
    """Exactly one force source; returns whether to overwrite (``--force``; the old ``--force
    FILE`` was turned into ``--force-csv FILE`` while parsing, :class:`OverwriteOrOldValue`)."""
    if (args.force_file is None) == (args.profile is None):
        raise ConfigError("give exactly one of --force-csv FILE and --profile SPEC")
    return bool(args.force_flag)


def _compare_check(args: argparse.Namespace, run, grasp):
    """(grasp to predict at, whether the recording may be compared with the prediction).

    A recording is predicted at its own grasp point (its folder's pulls.yaml) unless
    --grasp-fraction says otherwise; then it is not compared (a loud warning says why)."""
    path = Path(args.force_file)
    tree = run.tree
    own = None
    if (path.parent / PULLS_FILE).is_file():
        own = load_data_pulls(path.parent, tree, [path.name])[0]
        if args.grasp_fraction is None:
            grasp = own.fraction
    run_frac = run.grasp_fraction if run.grasp_fraction is not None else tree.grasp_fraction
    frac = grasp if grasp is not None else run_frac
    down = pull_direction(tree, tree.grasp_branch, "down")
    predicted = ResolvedPull(tree.grasp_branch, float(frac), down, "down")
    recorded = own or ResolvedPull(tree.grasp_branch, float(run_frac), down, "down")
    problem = check_same_pull(recorded, predicted, str(path))
    if problem is not None:
        print(
            f"WARNING: {problem}; the recording is NOT compared with this prediction "
            "(prediction.csv leaves 'recorded' empty)",
            file=sys.stderr,
        )
    return grasp, problem is None


def _channel_bands(run, sim, model, grasp, prof, src: Path | None, compare: bool) -> list:
    """Bands of the run's observation channels (issue 30) under this force: the recording's own
    channels where its folder's channels.yaml names it (and it is compared), else one channel
    per sensor the run was trained with, bands only; [] for a run without channels."""
    settings = run.config.get("problem") or {}
    if not settings.get("channels"):
        return []
    from ..data.channels import read_channels
    from ..data.trajectories import Trajectory
    from ..evaluation.channel_bands import channel_bands, run_channels

    name = src.name if src is not None else "profile"
    disp = prof.displacement if prof.displacement is not None else np.zeros_like(prof.force)
    traj = Trajectory(prof.time, prof.force, disp, None, name)
    channels = ()
    if src is not None and compare:
        channels = read_channels(src.parent, run.tree, [traj], only_these_pulls=True)
    if not channels:
        channels = run_channels(settings, name, prof.time)
    if not channels:
        return []
    return channel_bands(
        sim, run.theta, run.labels, channels, [traj], settings, run.stable, model=model,
        grasp_fraction=None if grasp is None else np.atleast_1d(np.asarray(grasp, float)),
    )  # fmt: skip


def run_predict(args: argparse.Namespace) -> int:
    _check_grasp(args.grasp_fraction)
    overwrite = _resolve_force_options(args)
    inputs = [args.run, args.force_file, args.model]
    check_output_dir(args.out, overwrite, "prediction", inputs=inputs)
    _prepare_jax()
    check_simulation_options(args)
    cache = runs.SimulatorCache()
    run = runs.load_run(args.run, cache, allow_modified=args.allow_modified, model_file=args.model)
    for note in run.notes:
        _say(f"warning: {note}")
    dt_run = run.sim.obs_dt
    if args.force_file is not None:
        if args.duration is not None or args.dt is not None:
            raise ConfigError(
                "--duration and --dt go with --profile; a force file has its own time column"
            )
        prof = read_force_profile(args.force_file)
        if not math.isclose(prof.dt, dt_run, rel_tol=1e-6):
            raise ConfigError(
                f"{args.force_file}: time step {prof.dt:g} s differs from the run's {dt_run:g} s "
                "(the data it was inferred from); resample the force profile to the run's step"
            )
    else:
        if args.duration is None:
            raise ConfigError("--profile needs --duration (seconds)")
        dt = dt_run if args.dt is None else args.dt
        if not math.isclose(dt, dt_run, rel_tol=1e-6):
            raise ConfigError(
                f"--dt {dt:g} s differs from the run's {dt_run:g} s; leave it out to use the "
                "run's step"
            )
        f = from_spec(args.profile, args.duration, dt)
        prof = ForceProfile(np.arange(len(f)) * dt, f, None, args.profile)
    _say(
        f"simulating {len(run.theta)} particles (the first prediction of a shape compiles for up "
        "to a minute)..."
    )
    grasp = args.grasp_fraction if args.grasp_fraction is not None else run.grasp_fraction
    compare = prof.displacement is not None
    model = run.model
    src = None if args.force_file is None else Path(args.force_file)
    if (
        src is not None and args.grasp_fraction is None and (src.parent / PULLS_FILE).is_file()
    ):  # at the recording's own branch, point and direction (pulls.yaml)
        from ..inference.static import model_with_pulls

        model, own = model_with_pulls(model, src.parent, [src.name], tree=run.tree)
        grasp = float(np.asarray(own)[0])
    elif src is not None:
        grasp, same = _compare_check(args, run, grasp)
        compare = compare and same
    sim = simulator_for_run(run, args, prof.force[None], grasp, cache)
    _print_simulation(runs.simulation_summary(sim))
    sigma, kind = noise_for(run.theta, run.sim.n_joints, run.config.get("problem"))
    pred = predict_run(
        sim,
        run.theta,
        prof.force[None],
        grasp,
        run.stable,
        noise_sigma=sigma,
        noise_kind=kind,
        model=model,
        # a recording's force is the noisy sensor's: its band carries the force-noise term; a
        # profile without a recorded response is taken as the force actually applied
        force_noise=force_noise_for(run.config.get("problem"))
        if prof.displacement is not None
        else None,
    )
    n_bad = int((~pred.valid).sum())
    mean = pred.mean[0]
    lower, upper = (a[0] for a in pred.band())  # what a recording is compared with
    has_noise = pred.predictive_lower is not None
    band_name = (
        "parameter band (no noise model known)"
        if not has_noise
        else "predictive band (simulation + fitted noise + force-noise term)"
        if pred.force_variance is not None
        else "predictive band (simulation + fitted noise)"
    )
    recorded = prof.displacement if compare else None
    csv_text = band_csv_text(
        prof.time,
        prof.force,
        recorded,
        mean,
        pred.lower[0],
        pred.upper[0],
        pred.predictive_lower[0] if has_noise else None,
        pred.predictive_upper[0] if has_noise else None,
    )
    config = _base_config("predict", args)
    config.update(
        run=str(Path(args.run).resolve()),
        force_source=prof.source,
        dt=float(dt_run),
        n_steps=len(prof.time),
        grasp_fraction=grasp if grasp is not None else run.tree.grasp_fraction,
        compared_with_recording=bool(compare),
        band=band_name,
        band_includes_force_noise=pred.force_variance is not None,
        n_particles=len(run.theta),
        n_valid=int(pred.valid.sum()),
        n_excluded=n_bad,
        integrity_notes=list(run.notes),
        run_fit_status=run.summary.get("status"),
    )
    bands = _channel_bands(run, sim, model, grasp, prof, src, compare)
    if bands:
        config["channels"] = {b.channel.name: b.metrics() for b in bands}
    with staged_output_dir(args.out, overwrite, "prediction", inputs=inputs) as stage:
        atomic_write_text(stage / "prediction.csv", csv_text)
        if bands:  # channels/<name>_prediction.csv and channels.png
            from ..evaluation.channel_bands import write_channel_outputs

            write_channel_outputs(stage, bands, formats=args.formats or ("png",))
        fig, _ = plot_trajectory_bands(
            prof.time,
            lower,
            upper,
            mean,
            recorded,
            samples=pred.tau[pred.valid, 0],
            title=f"{prof.source}: 95% {band_name}, {int(pred.valid.sum())} particles",
        )
        save_figure(fig, stage / "prediction.png", formats=args.formats)
        runs.write_json(stage / "config.json", config)
    peak = float(np.max(np.abs(mean)))
    print(
        f"predicted {len(prof.time)} steps under {prof.source}: peak mean displacement "
        f"{1000 * peak:.3g} mm, band {1000 * float(np.mean(upper - lower)):.3g} mm wide on "
        f"average; {n_bad} of {len(run.theta)} particles excluded"
    )
    if compare:
        print(
            f"  {100 * float(fraction_outside(lower, upper, prof.displacement)):.1f}% of the "
            "recorded displacement lies outside the band"
        )
    for b in bands:
        cm = b.metrics()
        scored = (
            f"{cm['pct_outside']:.1f}% of the recorded {cm['kind']} outside the 95% "
            f"{cm['band']} band" if cm["pct_outside"] is not None
            else f"95% {cm['band']} band {cm['band_width']:.3g} {cm['unit']} wide on average"
        )  # fmt: skip
        print(f"  channel {b.channel.name} ({cm['kind']} at {cm['point']}): {scored}")
    print(
        f"wrote {args.out}/ (prediction.csv, {figure_names('prediction', args.formats)}, "
        "config.json" + (", channels/<channel>_prediction.csv, channels.png" if bands else "") + ")"
    )
    return EXIT_OK
