"""``treeinfer demo``: the whole pipeline on the built-in example (simulate, infer, evaluate)."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from .. import runs
from ..data.forces import DEFAULT_PEAK_RANGE, from_spec, random_specs
from ..data.trajectories import (
    TRUE_PARAMS_FILE,
    true_params_record,
    write_trajectory,
    write_true_params,
)
from ..errors import ConfigError, SimulationError
from ..evaluation.predictive import band_arrays, evaluate_trajectories, noise_for, write_evaluation
from ..io.atomic import check_output_dir, staged_output_dir
from ..sim.synthetic import default_true_params, simulate_batch, synthetic_trajectories
from ..tree.description import dump_tree, load_tree
from .common import (
    COMMAND_HELP,
    EXIT_OK,
    _base_config,
    _fmt_params,
    _metrics_md,
    _prepare_jax,
    _print_metrics,
    _print_posterior,
    _print_simulation,
    _print_warnings,
    _say,
    add_command_parser,
    add_simulation_options,
    check_simulation_options,
)
from .infer import INFER_DEFAULTS
from .options import add_formats_option, displacement_noise, figure_names, refuse_noise_form

DEMO_NOISE = 0.002  # m: the pulls' noise with a generative likelihood and no --noise-displacement
DEMO_ITERATIONS = 300
# the demo's start: with the paper's uniform start its 300 iterations ended with "log density
# still rising" and "KSD still falling" warnings; from the Laplace fit they end converged
DEMO_INIT = "auto"  # the start pipeline, as `treeinfer infer` (issue 27)
DEMO_REINIT = 100  # iterations of the straggler remedy (issue 11: the demo had 8 of 32 stuck)

# ==== demo ========================================================================================
_DEMO_EPILOG = """\
examples:
  treeinfer demo                       # a few minutes on a laptop CPU
  treeinfer demo --out my-demo --seed 2
  treeinfer demo --quick               # tiny sizes: checks the installation in about a minute
  treeinfer demo --noise-displacement 0.001   # 1 mm noise, sigma_x given
  treeinfer demo --likelihood boltzmann       # the paper's loss on noise-free pulls

By default (as `treeinfer infer`) the demo adds white displacement noise to every pull (std
--noise-displacement, default 2 mm) and infers with the Gaussian measurement model (also with
--likelihood student_t|ar1): sigma_x is inferred unless --noise-displacement gives it, and the
reported bands are predictive (simulation + noise). --likelihood boltzmann uses the paper's loss
on noise-free pulls; --noise-displacement then only adds the noise to the pulls.

Stuck particles: the demo re-initialises particles stuck far below the bulk during the first
--reinit-stragglers iterations (default 100 of 300; 0 turns the remedy off), so its intervals
do not rest on them; any left at the end are counted and warned about.

Writes DIR/data/train and DIR/data/test (synthetic trajectories with true_params.json, as
`treeinfer simulate` writes), DIR/run (the run folder of `treeinfer infer`), DIR/evaluation (as
`treeinfer evaluate` writes, on the unseen test trajectories) and DIR/demo.json.
"""


def configure_demo(subparsers) -> argparse.ArgumentParser:
    p = add_command_parser(
        subparsers,
        "demo",
        help=COMMAND_HELP["demo"],
        description="Simulate training and unseen test pulls of the built-in two-branch tree with "
        "known stiffness and damping, infer the posterior with NNSVGD, predict the unseen pulls "
        "with 95% bands and print how well the bands cover them and how close the posterior is "
        "to the truth.",
        epilog=_DEMO_EPILOG,
    )
    p.add_argument(
        "--out", type=Path, default=Path("treeinfer-demo"), metavar="DIR", help="output folder"
    )
    p.add_argument(
        "--quick", action="store_true", help="tiny sizes (seconds of sampling; for tests)"
    )
    p.add_argument(
        "--seed",
        type=int,
        default=0,
        help="seed of the true parameters, the profiles and the sampler",
    )
    p.add_argument(
        "--force", action="store_true", help="replace the contents of a non-empty output folder"
    )
    p.add_argument(
        "--likelihood",
        choices=("boltzmann", "gaussian", "student_t", "ar1"),
        default="gaussian",
        help="gaussian (default, as `treeinfer infer`), student_t or ar1: a generative noise "
        "model, the pulls get white displacement noise and the bands are predictive; "
        "boltzmann: the paper's loss on noise-free pulls",
    )
    p.add_argument(
        "--noise-displacement",
        type=displacement_noise,
        default=None,
        metavar="M",
        help=f"displacement noise std added to the pulls, m (0.002 or 2mm; cm, um) (default "
        f"{DEMO_NOISE * 1e3:g}mm with a generative likelihood, none with boltzmann); given to a "
        "generative likelihood as a fixed sigma_x (otherwise sigma_x is inferred)",
    )
    p.add_argument(
        "--reinit-stragglers",
        type=int,
        default=None,
        metavar="N",
        help="re-initialise stuck particles next to good ones up to iteration N (default "
        f"{DEMO_REINIT} of {DEMO_ITERATIONS}; 0: off)",
    )
    p.add_argument(
        "--init",
        choices=("auto", "importance", "uniform", "laplace"),
        default=DEMO_INIT,
        help="initial particles, as for `treeinfer infer --init`: 'auto' (the default: screen, "
        "MAP fit, importance sampling; the sampler runs only if the weights fail their check, "
        "and stops once the answer stops changing), 'importance', 'laplace' (around a "
        "Levenberg-Marquardt MAP fit) or 'uniform' in the prior box (the paper's)",
    )
    add_simulation_options(p)
    add_formats_option(p, "figures (run/plots, evaluation/bands.png)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def _write_synthetic(
    out: Path, tree, trajs, specs, true_params: dict, force: bool, what: str
) -> None:
    with staged_output_dir(out, force) as stage:
        for tr in trajs:
            write_trajectory(stage / tr.source, tr)  # header first; provenance: the run's config
        dump_tree(tree, stage / "tree.yaml")
        write_true_params(stage / TRUE_PARAMS_FILE, true_params)


def _add_noise(trajs, sigma: float, rng: np.random.Generator):
    """Copies of ``trajs`` with white Gaussian noise of std ``sigma`` (m) on the displacement
    (the velocity column is dropped: differentiating the noise would swamp it)."""
    out = []
    for tr in trajs:
        x = np.asarray(tr.displacement, float) + sigma * rng.standard_normal(
            np.shape(tr.displacement)
        )
        out.append(tr._replace(displacement=x, velocity=None))
    return out


def run_demo(args: argparse.Namespace) -> int:
    # Sizes: the whole demo should take about a minute on a 2-core laptop CPU (tune here).
    n_train, n_test = 3, 3  # trajectories (training, unseen test)
    duration, dt = 2.0, 0.02  # s
    particles, iterations = 32, DEMO_ITERATIONS
    sampler = "nnsvgd"
    checkpoint_every = 25
    reinit = DEMO_REINIT
    if args.quick:  # tiny: for tests and a first check of an installation
        n_train, n_test, duration, particles, iterations, checkpoint_every = 2, 2, 0.8, 8, 3, 0
        reinit = 0
    if args.reinit_stragglers is not None:
        if args.reinit_stragglers < 0:
            raise ConfigError(f"--reinit-stragglers: must be >= 0, got {args.reinit_stragglers}")
        reinit = args.reinit_stragglers
    likelihood = args.likelihood
    generative = likelihood != "boltzmann"
    refuse_noise_form(
        args.noise_displacement, "--noise-displacement", "demo", ("number",),
        "adds displacement noise of a size you give, in metres (0.002 or 2mm)",
    )  # fmt: skip
    data_noise = args.noise_displacement
    if data_noise is not None:
        from ..model.noise import check_sigma

        check_sigma(data_noise, "--noise-displacement")
    elif generative:
        data_noise = DEMO_NOISE

    if args.seed < 0:
        raise ConfigError(f"--seed: must be >= 0, got {args.seed}")
    out: Path = args.out
    check_output_dir(out, args.force, "demo")
    _prepare_jax()
    tree_file = Path(__file__).resolve().parents[1] / "examples" / "two_branch.yaml"
    tree = load_tree(tree_file)
    if args.noise_displacement is not None:
        from ..evaluation.checks import grasp_reach
        from ..model.noise import check_sigma

        # the grasp point cannot move more than twice its distance to a hinge: a noise above
        # that is larger than any pull's range (a unit mistake)
        check_sigma(
            data_noise,
            "--noise-displacement",
            2.0 * grasp_reach(tree),
            what="the largest displacement the tree's grasp point can reach",
        )
    rng_params, rng_profiles = (
        np.random.default_rng(s) for s in np.random.SeedSequence(args.seed).spawn(2)
    )
    kp, kd = default_true_params(tree, rng_params)
    specs = random_specs("mixed", n_train + n_test, duration, DEFAULT_PEAK_RANGE, rng_profiles)
    forces = np.stack([from_spec(s, duration, dt) for s in specs])
    _say(
        f"demo: simulating {n_train} training and {n_test} unseen test pulls of {duration:g} s "
        f"on '{tree.name}' "
        f"with {_fmt_params(tree, kp, kd)}"
    )
    check_simulation_options(args)
    interp = args.force_interp or "linear"
    rollout, _ = simulate_batch(
        tree,
        kp,
        kd,
        forces,
        dt,
        args.max_sim_dt,
        log=_say,
        force_interp=interp,
        sim_tolerance=args.sim_tolerance,
    )
    if not np.asarray(rollout.stable).all():
        raise SimulationError(
            "demo: the synthetic pulls blew up; this is a bug in the demo's settings"
        )
    trajs = synthetic_trajectories(
        rollout, forces, dt, [f"traj_{i:03d}.csv" for i in range(len(specs))]
    )
    if data_noise:
        trajs = _add_noise(trajs, data_noise, rng_profiles)
        _say(f"demo: added white displacement noise of {data_noise * 1e3:g} mm to every pull")
    true_params = true_params_record(
        tree, kp, kd, f"demo (default_true_params, seed {args.seed})", log_units=False
    )
    out.mkdir(parents=True, exist_ok=True)
    data_train, data_test = out / "data" / "train", out / "data" / "test"
    _write_synthetic(
        data_train, tree, trajs[:n_train], specs[:n_train], true_params, args.force, "training pull"
    )
    _write_synthetic(
        data_test,
        tree,
        trajs[n_train:],
        specs[n_train:],
        true_params,
        args.force,
        "unseen test pull",
    )

    inputs = runs.load_run_inputs(tree_file, data_train, model_kind="dynamic")
    config = runs.infer_config(
        tree_file,
        data_train,
        out / "run",
        sampler=sampler,
        particles=particles,
        iterations=iterations,
        kT=INFER_DEFAULTS["kT"],
        seed=args.seed,
        eta=INFER_DEFAULTS["eta"],
        grasp_fraction=None,
        max_unstable_share=INFER_DEFAULTS["max_unstable_share"],
        checkpoint_every=checkpoint_every,
        force=args.force,
        force_interp=interp,
        max_sim_dt=args.max_sim_dt,
        sim_tolerance=args.sim_tolerance,
        likelihood=likelihood,
        noise_displacement=args.noise_displacement if generative else None,
        reinit_stragglers=reinit,
        inputs=inputs,
        init=args.init,
    )
    config["via"] = "demo"
    config["figure_formats"] = list(args.formats or ("png",))
    # with --init auto the sampler runs only when the start pipeline's particles are not the
    # posterior already (importance weights trusted, or resample-move settled): say so
    start = (
        f"the start pipeline (importance sampling, then resample-move), else {sampler} with "
        f"{particles} particles x up to {iterations} iterations"
        if args.init == "auto"
        else f"{sampler} with {particles} particles x {iterations} iterations from a "
        f"{args.init} start"
    )
    _say(
        f"demo: {start}, {likelihood} likelihood"
        + (f", stuck particles re-initialised up to iteration {reinit}" if reinit else "")
    )
    cache = runs.SimulatorCache()
    outcome = runs.run_inference(
        config, progress=not args.no_progress, log=_say, cache=cache, inputs=inputs
    )
    run = runs.load_run(out / "run", cache)
    truth = np.concatenate([kp, kd])
    test = trajs[n_train:]
    sigma, kind = noise_for(run.theta, run.sim.n_joints, run.config.get("problem"))
    m, pred, obs = evaluate_trajectories(
        run.sim,
        run.theta,
        list(run.labels),
        test,
        run.kT,
        None,
        truth,
        run.stable,
        noise_sigma=sigma,
        noise_kind=kind,
    )
    eval_config = _base_config("evaluate", args)
    eval_config.update(
        run=str((out / "run").resolve()),
        data_files=runs.data_manifest(data_test),
        dt=dt,
        via="demo",
    )
    md = [
        f"# treeinfer demo: NNSVGD posterior ({likelihood}) on unseen test pulls",
        "",
    ] + _metrics_md("unseen test trajectories", m)
    write_evaluation(
        out / "evaluation",
        {"run": str(out / "run"), "data": str(data_test), "metrics": m},
        band_arrays([(pred, obs)]),
        [tr.source for tr in test],
        dt,
        eval_config,
        args.force,
        md,
        formats=args.formats or ("png",),
    )
    demo = {
        "sizes": {
            "n_train": n_train,
            "n_test": n_test,
            "duration_s": duration,
            "dt_s": dt,
            "particles": particles,
            "iterations": iterations,
            "sampler": sampler,
            "quick": bool(args.quick),
            "likelihood": likelihood,
            "noise_displacement_data_m": data_noise,
            "reinit_stragglers": reinit,
            "init": args.init,
        },
        "seed": args.seed,
        "true_params": true_params,
        "versions": runs.versions(),
        "posterior": outcome.summary["posterior"],
        "unseen_test_metrics": m,
        "convergence_warnings": outcome.summary["convergence_warnings"],
        "stragglers": outcome.summary.get("stragglers"),
    }
    runs.write_json(out / "demo.json", demo)

    print(f"true parameters: {_fmt_params(tree, kp, kd)}")
    _print_simulation(outcome.summary.get("simulation"))
    _print_posterior(outcome.summary)
    _print_metrics(m, f"unseen test trajectories ({n_test})")
    _print_warnings(outcome.summary["convergence_warnings"])
    print(
        f"wrote {out}/ (data/train, data/test, run/, evaluation/, demo.json); see "
        f"{out}/run/plots and "
        f"{out}/evaluation/{figure_names('bands', args.formats)}"
    )
    return EXIT_OK
