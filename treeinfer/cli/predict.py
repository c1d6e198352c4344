"""``treeinfer predict``: the posterior predictive band of a run under a force profile."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from .. import __version__, runs
from .._io import atomic_write_text, check_output_dir, staged_output_dir
from ..errors import ConfigError
from ..evaluation import noise_for, predict_run
from ..forces import from_spec
from ..metrics import fraction_outside
from ..plots import plot_trajectory_bands, save_figure
from ..trajectories import ForceProfile, read_force_profile
from .common import (
    COMMAND_HELP,
    EXIT_OK,
    _base_config,
    _check_grasp,
    _prepare_jax,
    _say,
    add_command_parser,
)

# ==== predict =====================================================================================
_PREDICT_EPILOG = """\
examples:
  treeinfer predict --run runs/nnsvgd --force data/test/traj_000.csv --out pred/t0
  treeinfer predict --run runs/nnsvgd --force pull.csv --grasp-fraction 0.5 --out pred/mid
  treeinfer predict --run runs/nnsvgd --profile 'hold:peak=6,ramp=0.5,hold=1,release=0.5' \\
      --duration 3 --out pred/hold

FORCE.csv is a trajectory CSV (time,force,displacement[,velocity]: its displacement is drawn as
ground truth) or a force profile with only time,force columns; its time step must be the run's.
--profile SPEC samples a profile spec instead (as in `treeinfer simulate --profile`; see its help).
Writes prediction.csv (time, force, mean, lower, upper [, displacement]; s, N, m), prediction.png
and config.json. Particles whose simulation is unstable are left out and counted.
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
    p.add_argument(
        "--run",
        required=True,
        type=Path,
        metavar="RUN",
        help="run folder written by `treeinfer infer`",
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument(
        "--force",
        dest="force_file",
        type=Path,
        metavar="FORCE.csv",
        help="force profile or trajectory CSV",
    )
    src.add_argument(
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
        help="where along the grasped branch the force acts, in (0, 1] (default: where the run's training data were recorded)",
    )
    p.add_argument(
        "--out",
        required=True,
        type=Path,
        metavar="DIR",
        help="output folder (must be empty or absent unless --overwrite)",
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace a non-empty output folder (--force names the force file here)",
    )
    return p


def run_predict(args: argparse.Namespace) -> int:
    _check_grasp(args.grasp_fraction)
    check_output_dir(args.out, args.overwrite)
    _prepare_jax()
    run = runs.load_run(args.run, runs.SimulatorCache())
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
                f"--dt {dt:g} s differs from the run's {dt_run:g} s; leave it out to use the run's step"
            )
        f = from_spec(args.profile, args.duration, dt)
        prof = ForceProfile(np.arange(len(f)) * dt, f, None, args.profile)
    _say(
        f"simulating {len(run.theta)} particles (the first prediction of a shape compiles for up to a minute)..."
    )
    grasp = args.grasp_fraction if args.grasp_fraction is not None else run.grasp_fraction
    sigma, kind = noise_for(run.theta, run.sim.n_joints, run.config.get("problem"))
    pred = predict_run(
        run.sim, run.theta, prof.force[None], grasp, run.stable, noise_sigma=sigma, noise_kind=kind
    )
    n_bad = int((~pred.valid).sum())
    mean = pred.mean[0]
    lower, upper = (a[0] for a in pred.band())  # what a recording is compared with
    has_noise = pred.predictive_lower is not None
    band_name = (
        "predictive band (simulation + fitted noise)" if has_noise else "parameter band (no noise model known)"
    )
    cols = ["time", "force", "mean", "lower", "upper"]
    rows = [prof.time, prof.force, mean, pred.lower[0], pred.upper[0]]
    if has_noise:
        cols += ["predictive_lower", "predictive_upper"]
        rows += [pred.predictive_lower[0], pred.predictive_upper[0]]
    if prof.displacement is not None:
        cols.append("displacement")
        rows.append(prof.displacement)
    lines = [
        f"# treeinfer {__version__} predict: run {args.run}, force {prof.source}; s, N, m (positive downward)",
        f"# lower/upper: 95% PARAMETER band over {int(pred.valid.sum())} particles (simulations only; "
        f"{n_bad} unstable or invalid, excluded)",
        *(
            ["# predictive_lower/predictive_upper: 95% PREDICTIVE band (simulations + the fitted "
             "noise model): where a new recording should fall"]
            if has_noise
            else []
        ),
        ",".join(cols),
    ] + [",".join(repr(float(v)) for v in r) for r in zip(*rows)]
    config = _base_config("predict", args)
    config.update(
        run=str(Path(args.run).resolve()),
        force_source=prof.source,
        dt=float(dt_run),
        n_steps=len(prof.time),
        grasp_fraction=grasp if grasp is not None else run.tree.grasp_fraction,
        n_particles=len(run.theta),
        n_valid=int(pred.valid.sum()),
        n_excluded=n_bad,
    )
    with staged_output_dir(args.out, args.overwrite) as stage:
        atomic_write_text(stage / "prediction.csv", "\n".join(lines) + "\n")
        fig, _ = plot_trajectory_bands(
            prof.time,
            lower,
            upper,
            mean,
            prof.displacement,
            samples=pred.tau[pred.valid, 0],
            title=f"{prof.source}: 95% {band_name}, {int(pred.valid.sum())} particles",
        )
        save_figure(fig, stage / "prediction.png")
        runs.write_json(stage / "config.json", config)
    peak = float(np.max(np.abs(mean)))
    print(
        f"predicted {len(prof.time)} steps under {prof.source}: peak mean displacement {1000 * peak:.3g} mm, "
        f"band {1000 * float(np.mean(upper - lower)):.3g} mm wide on average; {n_bad} of {len(run.theta)} particles excluded"
    )
    if prof.displacement is not None:
        print(
            f"  {100 * float(fraction_outside(lower, upper, prof.displacement)):.1f}% of the recorded displacement lies outside the band"
        )
    print(f"wrote {args.out}/ (prediction.csv, prediction.png, config.json)")
    return EXIT_OK
