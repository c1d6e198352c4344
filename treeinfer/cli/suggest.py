"""``treeinfer suggest``: rank candidate next pulls for a run's posterior (treeinfer.design)."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..design import STANDARD_TIMING, parse_target
from ..errors import ConfigError
from ..io.limits import check_command_size
from ..runs.suggest import suggest_for_run
from .common import (
    COMMAND_HELP,
    EXIT_OK,
    _floats,
    _prepare_jax,
    _say,
    add_command_parser,
    add_run_option,
)
from .options import AUTO, add_deprecated, add_formats_option, displacement_noise, figure_names

# ==== suggest =====================================================================================
_SUGGEST_EPILOG = """\
examples:
  treeinfer suggest --run runs/nnsvgd
  treeinfer suggest --run runs/nnsvgd --grasp-fractions 0.2,0.4,0.6,0.8,1 --peak-forces 2,5,8 \\
      --profile-kinds ramp,hold,step --out runs/nnsvgd/suggest
  treeinfer suggest --run runs/nnsvgd --target grasp=0.5,peak=5       # shrink that band most
  treeinfer suggest --run runs/nnsvgd --parameter worst               # the widest parameter

Score: the expected information gain about log Kp, log Kd (nats), by the Laplace/Fisher
approximation 0.5 E[log det(I + Sigma J^T J / sigma_x^2)] over the posterior particles, with the
displacement sensitivities J by central differences (all candidates x particles in one batched
simulator call: particles x 2D x candidates rollouts). With --target grasp=G,peak=F[,kind=K]:
the expected reduction of the linearised predictive variance of that manipulation; with
--parameter: of one parameter's posterior variance. sigma_x: the run's noise model, else the
noise its kT stands for (see --noise-displacement). Writes suggestions.json and suggestions.png
to --out (default RUN/suggest).
"""


def _words(text: str) -> list[str]:
    return [w for w in text.replace(" ", ",").split(",") if w]


def _directions(text: str) -> list:
    """``'down;1,0,0'`` -> [None, (1, 0, 0)]: 'down' (along gravity) or x,y,z, separated by ';'."""
    out = []
    for item in filter(None, (s.strip() for s in text.split(";"))):
        if item in ("down", "gravity"):
            out.append(None)
            continue
        try:
            v = tuple(float(x) for x in item.split(","))
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"direction {item!r}: expected x,y,z or 'down'"
            ) from None
        if len(v) != 3:
            raise argparse.ArgumentTypeError(f"direction {item!r}: expected 3 numbers")
        out.append(v)
    return out


def configure_suggest(subparsers) -> argparse.ArgumentParser:
    p = add_command_parser(
        subparsers,
        "suggest",
        help=COMMAND_HELP["suggest"],
        description="Rank candidate next pulls (grasp point x peak force x profile kind x "
        "direction) by how much they are expected to teach about the joints' gains, or to "
        "narrow a stated prediction, given a finished run's posterior.",
        epilog=_SUGGEST_EPILOG,
    )
    add_run_option(p)
    p.add_argument(
        "--grasp-fractions",
        type=_floats,
        default=[0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0],
        metavar="G,...",
        help="candidate grasp points, fractions of the grasped branch",
    )
    p.add_argument(
        "--peak-forces",
        type=_floats,
        default=[2.0, 4.0, 6.0, 8.0],
        metavar="N,...",
        help="candidate peak forces (N)",
    )
    p.add_argument(
        "--profile-kinds",
        type=_words,
        default=["ramp"],
        metavar="KIND,...",
        help=f"candidate profile shapes, of {', '.join(STANDARD_TIMING)} (standard timing)",
    )
    p.add_argument(
        "--directions",
        type=_directions,
        default=None,
        metavar="D;...",
        help="candidate pull directions, 'down' or x,y,z separated by ';' (needs a simulator "
        "with direction support)",
    )
    goal = p.add_mutually_exclusive_group()
    goal.add_argument(
        "--target",
        default=None,
        metavar="grasp=G,peak=F[,kind=K]",
        help="score by the predictive-variance reduction of this manipulation",
    )
    goal.add_argument(
        "--parameter",
        default=None,
        metavar="LABEL|worst",
        help="score by the variance reduction of one parameter, e.g. Kd[branch1]",
    )
    p.add_argument(
        "--noise-displacement",
        dest="sigma_x",
        type=displacement_noise,
        default=None,
        metavar="M|auto",
        help="displacement noise std sigma_x, m (0.002 or 2mm; cm, um); 'auto' (default): the "
        "run's noise model or the noise its kT stands for",
    )
    p.add_argument(
        "--duration",
        type=float,
        default=None,
        metavar="S",
        help="s per candidate pull (default: the run's training trajectory length)",
    )
    p.add_argument(
        "--particles",
        type=int,
        default=32,
        metavar="M",
        help="posterior particles the sensitivities are taken at",
    )
    p.add_argument("--top", type=int, default=10, help="rows of the ranked table to print")
    p.add_argument(
        "--seed",
        type=int,
        default=0,
        help="seed of the particle subsample and the nested Monte Carlo noise",
    )
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        help="folder for suggestions.json/png (default RUN/suggest)",
    )
    p.add_argument("--force", action="store_true", help="replace an earlier suggestions.json")
    add_formats_option(p, "figure (suggestions.png)")
    p.add_argument(
        "--allow-large",
        action="store_true",
        help="go past the size limit (treeinfer.io.limits) checked before any work",
    )
    p.add_argument(
        "--allow-modified",
        action="store_true",
        help="use the run even if its files changed since `infer` wrote them (checksums in its "
        "config.json); recorded in suggestions.json",
    )
    p.add_argument(
        "--sensors",
        action="store_true",
        help="rank where to add a sensor instead of the next pull: a marker (x, y, z) at "
        "quarters of every link and an inclinometer on every link, by the expected information "
        "gain on the run's own pulls (linearised at the posterior mean; "
        "treeinfer.design.sensors)",
    )
    p.add_argument(
        "--sensor-noise",
        type=_floats,
        default=None,
        metavar="M,RAD",
        help="--sensors: noise std of a marker (m) and of an inclinometer (rad) "
        "(default 0.001,0.001)",
    )
    add_deprecated(p, "--sigma-x", "--noise-displacement", "the same quantity in every command")
    return p


def _suggest_sensors(args) -> int:
    """``suggest --sensors``: rank candidate sensors on the run's training pulls."""
    import numpy as np

    from .. import runs
    from ..data.trajectories import read_trajectory_dir, stack_trajectories
    from ..design.sensors import candidate_sensors, rank_sensors, sensors_table
    from ..inference.static import model_with_pulls
    from ..io.atomic import atomic_write_json

    run = runs.load_run(args.run, allow_modified=args.allow_modified)
    data = run.config["options"].get("data")
    if not data or not Path(data).is_dir():
        raise ConfigError(f"--sensors: the run's training data folder {data!r} is not there")
    trajs = read_trajectory_dir(data)
    # any model: each training pull at its own branch, point and direction (pulls.yaml)
    model, grasp = model_with_pulls(
        run.model, data, [t.source for t in trajs], run.grasp_fraction, tree=run.tree
    )
    noise = {}
    if args.sensor_noise is not None:
        if len(args.sensor_noise) != 2 or min(args.sensor_noise) <= 0:
            raise ConfigError("--sensor-noise: expected two positive numbers M,RAD")
        noise = {"position": args.sensor_noise[0], "angle": args.sensor_noise[1]}
    forces = np.asarray(stack_trajectories(trajs).force)
    theta = np.asarray(run.theta)[np.asarray(run.stable, bool)]
    rng = np.random.default_rng(args.seed)
    if len(theta) > args.particles:
        theta = theta[rng.choice(len(theta), args.particles, replace=False)]
    cands = candidate_sensors(list(run.sim.branches), noise=noise)
    _say(f"scoring {len(cands)} candidate sensors on the {len(forces)} pulls of {data} ...")
    grasp = None if grasp is None else np.broadcast_to(np.asarray(grasp, float), len(forces))
    scores = rank_sensors(run.sim, theta, list(run.labels), forces, cands, model=model,
                          grasp_fraction=grasp)  # fmt: skip
    print("\n".join(sensors_table(scores, args.top)))
    out = args.out if args.out is not None else args.run / "suggest"
    out.mkdir(parents=True, exist_ok=True)
    record = {
        "run": str(args.run),
        "data": str(data),
        "method": "linearised information gain at the posterior mean (treeinfer.design.sensors)",
        "sensors": [s._asdict() for s in scores],
    }
    atomic_write_json(out / "sensors.json", record)
    best = scores[0]
    print(f"best: {best.label()} (gain {best.gain:.2f} nats); wrote {out / 'sensors.json'}")
    return EXIT_OK


def _refuse_stiffness_only(run) -> None:
    """The design scores differentiate the dynamic model in (log Kp, log Kd): refuse runs of the
    static model or of stiffness only (their particles have no Kd columns)."""
    import json

    try:
        problem = json.loads((Path(run) / "config.json").read_text()).get("problem") or {}
    except (OSError, ValueError, AttributeError):
        return  # suggest_for_run reports an unreadable run, naming the file
    kind = problem.get("model_kind", "dynamic")
    params = problem.get("parameters", ["kp", "kd"])
    if kind != "dynamic" or params != ["kp", "kd"]:
        raise ConfigError(
            f"{run}: a run of the {kind} model inferring {', '.join(params)} only; suggest "
            "scores pulls for runs of the "
            "dynamic model of Kp and Kd"
        )


def run_suggest(args: argparse.Namespace) -> int:
    check_command_size("suggest", args)  # before any work
    target = parse_target(args.target) if args.target else None
    if args.sigma_x == AUTO:  # the default, said out loud
        args.sigma_x = None
    if args.sigma_x is not None and not args.sigma_x > 0:
        raise ConfigError(
            f"--noise-displacement: must be a positive number of metres, got {args.sigma_x:g}"
        )
    if args.sensors:  # any model: the sensors' Jacobian of its own gain columns
        _prepare_jax()
        return _suggest_sensors(args)
    _refuse_stiffness_only(args.run)
    _prepare_jax()
    out = args.out if args.out is not None else args.run / "suggest"
    _say(f"scoring candidates for {args.run} ...")
    sugg = suggest_for_run(
        args.run,
        grasp_fractions=args.grasp_fractions,
        peak_forces=args.peak_forces,
        profile_kinds=args.profile_kinds,
        directions=args.directions,
        target=target,
        parameter=args.parameter,
        sigma_x=args.sigma_x,
        duration=args.duration,
        n_particles=args.particles,
        seed=args.seed,
        out=out,
        force=args.force,
        formats=args.formats,
        allow_modified=args.allow_modified,
    )
    for note in sugg.settings.get("integrity_notes", ()):
        _say(f"warning: {note}")
    s = sugg.settings
    print(
        f"{s['n_candidates']} candidates, objective {s['objective']}"
        + (f" ({s['target']['description']})" if s.get("target") else "")
        + f"; sigma_x {1e3 * s['sigma_x_m']:.3g} mm ({s['sigma_x_from']}); "
        f"{s['cost_rollouts']} rollouts"
    )
    print(sugg.table(args.top))
    print(f"best: {sugg.specs[0]} at grasp fraction {sugg.best.grasp_fraction:g}")
    figures = figure_names(str(out / "suggestions"), args.formats)
    print(f"wrote {out / 'suggestions.json'} and {figures}")
    return EXIT_OK
