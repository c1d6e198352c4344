"""``treeinfer simulate``: synthetic trajectories of a tree under force profiles (sim-to-sim
ground truth), via :mod:`treeinfer.sim.synthetic`.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

import jax
import mujoco
import numpy as np

from .. import __version__
from ..data.forces import DEFAULT_PEAK_RANGE, SET_KINDS, from_spec, n_steps, random_specs
from ..data.trajectories import (
    MAX_DT,
    TRUE_PARAMS_FILE,
    true_params_record,
    write_trajectory,
    write_true_params,
)
from ..errors import ConfigError, SimulationError
from ..io.atomic import atomic_write_json, check_output_dir, staged_output_dir
from ..io.limits import check_command_size
from ..runs import simulation_summary
from ..sim import DEFAULT_MAX_SIM_DT
from ..sim.synthetic import (
    default_true_params,
    parse_params,
    simulate_batch,
    synthetic_trajectories,
)
from ..tree.description import dump_tree, load_tree
from ..tree.usermodel import attach_model
from .common import (
    COMMAND_HELP,
    EXIT_OK,
    _floats,
    _fmt_params,
    _pair,
    _prepare_jax,
    _print_simulation,
    _say,
    add_backend_option,
    add_command_parser,
    add_model_options,
    add_out_option,
    add_simulation_options,
    check_simulation_options,
    print_model_report,
)
from .options import (
    DISPLACEMENT_NOISE_HELP,
    add_deprecated,
    displacement_noise,
    force_noise,
    refuse_noise_form,
)

# ==== simulate ====================================================================================
_SIMULATE_EPILOG = """\
examples:
  treeinfer simulate --tree two_branch.yaml --out data/train --n-traj 8 --seed 1
  treeinfer simulate --tree two_branch.yaml --out data/test --n-traj 25 --seed 2 \\
      --params-json data/train/true_params.json --noise-force 0.2 --noise-displacement 0.002
  treeinfer simulate --tree two_branch.yaml --out data/one --params 40,80,0.6,1.2 \\
      --profile 'hold:peak=6,ramp=0.5,hold=1.0,release=0.5'

Output folder: traj_000.csv ... (time,force,displacement,velocity in s, N, m, m/s; the velocity
column is the simulator's, left out when displacement noise is added, so that readers
differentiate the noisy displacement as for a recording), tree.yaml (the tree simulated),
true_params.json (the ground truth) and config.json (every option, the seed, the profile
specs and the treeinfer version). Nothing is written unless every trajectory simulates.

True parameters: --params lists Kp of every inferred joint, then Kd, in the tree's label order
(printed by `treeinfer tree --from TREE`); --params-json reads a true_params.json. By default
they are drawn log-uniformly in the middle third of each joint's log prior box with --seed and
ordered so that a parent is at least as stiff and as damped as its child (the inequality
prior's assumption; guaranteed when the joints share one prior box, as by default).

Force profiles (--profile SPEC, repeatable; or a seeded random set of --n-traj, see
--profiles): ramp:peak=N,ramp=S[,start=S]   hold:peak=N,ramp=S,hold=S,release=S[,start=S]
release:peak=N,ramp=S,release=S[,start=S]   step:peak=N,rise=S[,start=S]
"""


def configure_simulate(subparsers) -> argparse.ArgumentParser:
    p = add_command_parser(
        subparsers,
        "simulate",
        help=COMMAND_HELP["simulate"],
        description="Sim-to-sim ground truth: pull the tree's grasp point down with a set of "
        "force profiles using known (or drawn) joint stiffness and damping, in one batched "
        "simulation, and write the trajectories in treeinfer's CSV format with the true "
        "parameters.",
        epilog=_SIMULATE_EPILOG,
    )
    p.add_argument("--tree", required=True, type=Path, help="tree description (YAML/JSON)")
    add_out_option(p)
    p.add_argument(
        "--n-traj",
        type=int,
        metavar="N",
        default=None,
        help="number of trajectories (default 8; with --profile: one per spec)",
    )
    p.add_argument(
        "--seed", type=int, default=0, help="seed for the true parameters, profiles and noise"
    )
    gp = p.add_mutually_exclusive_group()
    gp.add_argument(
        "--params",
        type=_floats,
        metavar="KP1,..,KPR,KD1,..,KDR",
        help="true parameters, N m/rad then N m s/rad",
    )
    gp.add_argument(
        "--params-json", type=Path, metavar="FILE", help="true parameters from a true_params.json"
    )
    p.add_argument("--duration", type=float, default=3.0, metavar="S", help="s per trajectory")
    p.add_argument("--dt", type=float, default=0.01, metavar="S", help="s between samples")
    gf = p.add_mutually_exclusive_group()
    gf.add_argument(
        "--profile-kind",
        dest="profiles",
        choices=SET_KINDS,
        default=None,
        help="kind of random profile set (default mixed: ramp and ramp-hold-release "
        "alternately); --profile gives explicit specs instead",
    )
    gf.add_argument(
        "--profile",
        action="append",
        metavar="SPEC",
        help="explicit profile spec, repeatable (one trajectory each)",
    )
    # one letter from --profile, another meaning: the kind of random set is --profile-kind
    add_deprecated(p, "--profiles", "--profile-kind")
    p.add_argument(
        "--peak-range",
        type=_pair,
        default=DEFAULT_PEAK_RANGE,
        metavar="LO,HI",
        help="N, range of the random peaks (default "
        f"{DEFAULT_PEAK_RANGE[0]:g},{DEFAULT_PEAK_RANGE[1]:g})",
    )
    p.add_argument(
        "--noise-force",
        type=force_noise,
        default=0.0,
        metavar="SIGMA",
        help="Gaussian noise added to the force: N (0.05 or 0.05N; mN, kN) or P%% of the "
        "largest force of the profiles (2%%)",
    )
    p.add_argument(
        "--noise-displacement",
        type=displacement_noise,
        default=0.0,
        metavar="SIGMA",
        help=f"Gaussian noise added to the displacement: {DISPLACEMENT_NOISE_HELP}",
    )
    p.add_argument(
        "--grasp-fraction",
        type=float,
        metavar="F",
        help="grasp point along the grasped branch, in (0, 1] (default: the tree's)",
    )
    p.add_argument(
        "--channel",
        action="append",
        metavar="KIND:LINK:FRACTION[:AXES[:NOISE]]",
        help="also record a sensor on every pull, repeatable: KIND position (a marker: its "
        "displacement along the world AXES, default xyz) or angle (a tilt about the AXES, "
        "default y) at FRACTION of LINK, with Gaussian NOISE (m or rad); written to "
        "channels.yaml + channels/ (e.g. position:child:0.5:xz:0.001)",
    )
    add_model_options(p)
    add_simulation_options(p)
    add_backend_option(p)
    p.add_argument("--force", action="store_true", help="replace a non-empty output folder")
    return p


def _check_simulate_args(args: argparse.Namespace) -> int:
    """Validate the numeric options; returns T."""
    for flag, v in (("--dt", args.dt), ("--duration", args.duration)):
        if not (math.isfinite(v) and v > 0):
            raise ConfigError(f"{flag}: must be a positive number of seconds, got {v:g}")
    if args.dt >= MAX_DT:
        raise ConfigError(
            f"--dt: {args.dt:g} s is too coarse for a pull (must be below {MAX_DT:g} s)"
        )
    if args.n_traj is not None and args.n_traj < 1:
        raise ConfigError(f"--n-traj: must be at least 1, got {args.n_traj}")
    if args.profile and args.n_traj is not None and args.n_traj != len(args.profile):
        raise ConfigError(
            f"--n-traj {args.n_traj} disagrees with the {len(args.profile)} --profile spec(s) "
            "(one trajectory each)"
        )
    refuse_noise_form(args.noise_force, "--noise-force", "simulate", ("number", "%"),
                      "adds force noise of a size you give: newtons (0.05N) or a share of the "
                      "largest force of the profiles (2%); 'auto' estimates a RECORDED force's "
                      "noise (infer)")  # fmt: skip
    refuse_noise_form(args.noise_displacement, "--noise-displacement", "simulate", ("number",),
                      "adds displacement noise of a size you give, in metres (0.002 or 2mm); "
                      "'auto' is for commands that infer it")  # fmt: skip
    if args.grasp_fraction is not None and not (0.0 < args.grasp_fraction <= 1.0):
        raise ConfigError(
            "--grasp-fraction: must be in (0, 1] (a fraction of the branch length), got "
            f"{args.grasp_fraction:g}"
        )
    check_simulation_options(args)
    lo, hi = args.peak_range
    if lo > hi:
        raise ConfigError(f"--peak-range: LO must not exceed HI, got {lo:g},{hi:g}")
    try:
        return n_steps(args.duration, args.dt)
    except ConfigError:
        raise ConfigError(
            f"--duration {args.duration:g} s at --dt {args.dt:g} s gives "
            f"{int(args.duration / args.dt)} sample(s); at least 3 are needed"
        ) from None


def run_simulate(args: argparse.Namespace) -> int:
    n_t = _check_simulate_args(args)
    from ..sim.observe import ChannelSpec

    channel_specs = [ChannelSpec.parse(c) for c in (getattr(args, "channel", None) or [])]
    check_command_size("simulate", args)  # before any work: --duration 1e12 is an error now
    inputs = [args.tree, getattr(args, "params_json", None), args.model]
    check_output_dir(args.out, args.force, inputs=inputs)  # before anything is read
    tree = load_tree(args.tree)
    if args.model is not None or args.repair_inertia is not None or tree.model is not None:
        tree = attach_model(tree, args.model, args.repair_inertia)
    if args.grasp_fraction is not None:
        tree = tree.with_grasp(args.grasp_fraction)
    seq = np.random.SeedSequence(args.seed)  # independent streams: parameters, profiles, noise
    rng_params, rng_profiles, rng_noise = (np.random.default_rng(s) for s in seq.spawn(3))
    theta = parse_params(tree, args.params, args.params_json)
    drawn = theta is None
    if drawn:
        kp, kd = default_true_params(tree, rng_params)
    else:
        kp, kd = theta[: tree.n_inferred], theta[tree.n_inferred :]
    if args.profile:
        specs = list(args.profile)
    else:
        specs = random_specs(
            args.profiles or "mixed", args.n_traj or 8, args.duration, args.peak_range, rng_profiles
        )
    forces = np.stack([from_spec(s, args.duration, args.dt) for s in specs])  # [B, T]
    assert forces.shape[1] == n_t
    args.noise_force_N = _noise_force_newtons(args.noise_force, forces)

    _prepare_jax()
    rollout, sim = simulate_batch(
        tree,
        kp,
        kd,
        forces,
        args.dt,
        args.max_sim_dt,
        args.backend,
        _say,
        force_interp=args.force_interp or "linear",
        sim_tolerance=args.sim_tolerance,
    )
    print_model_report(sim.model_report)
    names = [f"traj_{i:03d}.csv" for i in range(len(specs))]
    stable = np.asarray(rollout.stable)[0]
    if not stable.all():
        bad = [f"{names[i]} ({specs[i]})" for i in np.flatnonzero(~stable)]
        raise SimulationError(
            f"the simulation blew up for {len(bad)} of {len(specs)} trajectories: "
            f"{'; '.join(bad)}; with {_fmt_params(tree, kp, kd)}: lower the peak forces "
            "(--peak-range), the step (--max-sim-dt) or check the parameters and the tree's "
            "units"
        )
    _check_noise_against_data(args, forces, np.asarray(rollout.tau)[0])
    trajs = synthetic_trajectories(
        rollout, forces, args.dt, names, args.noise_force_N, args.noise_displacement, rng_noise
    )
    source = (
        "drawn (default_true_params)"
        if drawn
        else ("--params" if args.params is not None else str(args.params_json))
    )
    true_params = true_params_record(tree, kp, kd, source)
    config = _simulate_config(args, tree, specs, n_t, sim)
    channels = ()
    if channel_specs:
        from ..sim.observe import synthetic_channels

        for c in channel_specs:
            if c.link not in tree.names:
                raise ConfigError(
                    f"--channel {c.kind}:{c.link}: unknown point '{c.link}'; the tree's links: "
                    f"{', '.join(tree.names)}"
                )
        channels = synthetic_channels(sim, kp, kd, forces, names, channel_specs, rng_noise)
        config["channels"] = [c._asdict() for c in channel_specs]
    with staged_output_dir(args.out, args.force, inputs=inputs) as stage:
        if channels:
            from ..data.channel_files import write_channels

            write_channels(stage, channels)
        for name, traj in zip(names, trajs):
            write_trajectory(stage / name, traj)  # provenance: config.json (specs, noise)
        dump_tree(tree, stage / "tree.yaml")
        write_true_params(stage / TRUE_PARAMS_FILE, true_params)
        atomic_write_json(stage / "config.json", config)
    print(
        f"simulated {len(specs)} trajectories of {n_t} samples (dt {args.dt:g} s, {sim.substeps} "
        f"simulation step(s) of {sim.sim_dt:.3g} s each) on tree '{tree.name}'"
    )
    _print_simulation(simulation_summary(sim))
    print(f"  true parameters: {_fmt_params(tree, kp, kd)}")
    peak = float(np.max(np.abs(np.asarray(rollout.tau))))
    print(
        f"  largest displacement {peak:.3g} m; wrote {args.out}/ ({names[0]} .. {names[-1]}, "
        "tree.yaml, true_params.json, config.json)"
    )
    return EXIT_OK


def _noise_force_newtons(value, forces) -> float:
    """--noise-force in newtons: ``P%`` is P% of the largest |force| of the profiles (the
    data set's largest force, as `infer --noise-force P%` reads the written data)."""
    if isinstance(value, str):  # "P%" (refuse_noise_form refused "auto")
        return float(value[:-1]) / 100.0 * float(np.max(np.abs(forces)))
    return float(value)


def _check_noise_against_data(args, forces, tau) -> None:
    """Noise larger than what it is added to is a unit mistake: --noise-force above the
    largest |force| of the profiles, --noise-displacement above the simulated displacement's
    range (issue 27, "Bad input")."""
    from ..model.noise import check_sigma

    check_sigma(
        args.noise_force_N,
        "--noise-force",
        float(np.max(np.abs(forces))),
        allow_zero=True,
        what="the largest force of the profiles",
    )
    check_sigma(
        args.noise_displacement,
        "--noise-displacement",
        float(np.max(tau) - np.min(tau)),
        allow_zero=True,
        what="the range of the simulated displacement",
    )


def _simulate_config(args, tree, specs, n_t, sim) -> dict[str, Any]:
    options = {
        k: (str(v) if isinstance(v, Path) else v)
        for k, v in vars(args).items()
        if not k.startswith("_")
    }
    options.pop("debug", None)
    options.update(  # the values actually used
        n_traj=len(specs),
        profiles=None if args.profile else (args.profiles or "mixed"),
        max_sim_dt=args.max_sim_dt or DEFAULT_MAX_SIM_DT,
    )
    return {
        "command": "simulate",
        "treeinfer_version": __version__,
        "jax_version": jax.__version__,
        "mujoco_version": mujoco.__version__,
        "options": options,
        "seed": args.seed,
        "seed_streams": "numpy SeedSequence(seed).spawn(3): true parameters, profiles, noise",
        "tree": tree.name,
        "grasp": {"branch": tree.grasp_branch, "fraction": tree.grasp_fraction},
        "n_steps": n_t,
        "dt": args.dt,
        "profiles": specs,
        "simulation": {"sim_dt": sim.sim_dt, **simulation_summary(sim)},
    }
