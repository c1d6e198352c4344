"""``treeinfer infer``: sample a posterior and write a run folder, or resume one
(:mod:`treeinfer.runs.service`).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from .. import runs
from ..errors import ConfigError
from ..inference.samplers import SAMPLER_NAMES
from ..io.atomic import check_output_dir
from ..runs.config import GRADIENT_CHOICES, INIT_CHOICES
from .common import (
    COMMAND_HELP,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_POOR_FIT,
    _check_share,
    _prepare_jax,
    _print_fit,
    _print_posterior,
    _print_simulation,
    _print_warnings,
    _say,
    add_backend_option,
    add_command_parser,
    add_model_options,
    add_simulation_options,
    print_model_report,
)
from .infer_options import (
    _RUN_OPTIONS,
    INFER_DEFAULTS,
    _check_infer_options,
    _check_meaning_changed,
    _kT_arg,
    check_prior_run,
)
from .options import AUTO, add_formats_option, displacement_noise, force_noise

# ==== infer =======================================================================================
_INFER_EPILOG = """\
examples:
  treeinfer infer --tree two_branch.yaml --data data/train --out runs/nnsvgd
  treeinfer infer --tree two_branch.yaml --data data/train --out runs/mh --sampler mh \\
      --particles 32 --iterations 2000 --seed 3
  treeinfer infer --resume runs/nnsvgd          # continue a killed or interrupted run
  treeinfer infer --tree two_branch.yaml --data data/day2 --out runs/day2 --prior-from runs/nnsvgd

Every *.csv in --data is a training trajectory (one time step for all); a true_params.json there
(as `treeinfer simulate` writes) is marked in the pair plot and compared in summary.json.

The run folder (config.json, tree.yaml, posterior.nc, particles.csv, trace.npz, summary.json,
plots/) is built aside and appears complete or not at all. While sampling, RUN.partial/ beside
it holds the config and a checkpoint every --checkpoint-every iterations; after a crash, a kill
or Ctrl-C, `treeinfer infer --resume RUN` continues from the last checkpoint with the recorded
settings (refusing if a data file changed) and gives the same particles as an uninterrupted run.
"""


def configure_infer(subparsers) -> argparse.ArgumentParser:
    d = INFER_DEFAULTS
    p = add_command_parser(
        subparsers,
        "infer",
        help=COMMAND_HELP["infer"],
        description="Sample the posterior over the stiffness Kp and damping Kd of the tree's "
        "inferred joints given force-deformation trajectories, with NNSVGD (the default: SVGD "
        "with the learned parent-stiffer-than-child prior), SVGD, SGLD, SGHMC or "
        "Metropolis-Hastings, and write a run folder for `treeinfer predict` and `treeinfer "
        "evaluate`. Prints the posterior mean and 95% interval of every parameter, convergence "
        "warnings and the number of unstable particles.",
        epilog=_INFER_EPILOG,
    )
    p.add_argument("--tree", type=Path, help="tree description (YAML/JSON)")
    p.add_argument("--data", type=Path, metavar="DIR", help="folder of training trajectory CSVs")
    p.add_argument(
        "--out",
        type=Path,
        metavar="RUN",
        help="run folder to write (must be empty or absent unless --force)",
    )
    p.add_argument("--sampler", choices=SAMPLER_NAMES, help=f"sampler (default {d['sampler']})")
    p.add_argument(
        "--particles",
        type=int,
        metavar="N",
        help=f"particles (SVGD) or chains (MCMC), >= 2 (default {d['particles']})",
    )
    p.add_argument(
        "--iterations",
        type=int,
        metavar="N",
        help=f"sampler iterations, >= 1 (default {d['iterations']})",
    )
    p.add_argument(
        "--kT",
        type=_kT_arg,
        metavar="X|auto",
        help="with --likelihood boltzmann only: the loss's temperature in loss units (m + m/s) "
        "per nat; smaller = sharper posterior; 'auto': from the data's displacement-noise "
        "estimate, kT = sigma / sqrt(T) * (1 + sqrt(2) dt omega2), printed (default "
        f"{d['kT']:g}, the paper-reproduction value; see treeinfer.model.likelihood)",
    )
    p.add_argument(
        "--likelihood",
        choices=("boltzmann", "gaussian", "student_t", "ar1"),
        help="gaussian (default): recorded = simulated displacement + white noise sigma_x "
        "(inferred unless --noise-displacement) and the recorded force's noise as an "
        "errors-in-variables term (--noise-force auto): calibrated bands; student_t: the same "
        "with heavy tails, for recordings with outliers; ar1: white + AR(1) residuals, for slow "
        "errors the model does not explain; boltzmann: the paper's loss with temperature --kT "
        "(reproducing the paper; its bands are not calibrated)",
    )
    p.add_argument(
        "--noise-displacement",
        type=displacement_noise,
        metavar="M|auto",
        help="displacement noise sigma_x, m (0.002 or 2mm; cm, um), for --likelihood "
        "gaussian/student_t/ar1 or for --kT auto; 'auto' (default): inferred jointly under a "
        "weakly-informative prior, log sigma_x flat from the sensor's resolution (step/sqrt(12) "
        "of a quantised recording, else 1 micron) to the range of the data (--kT auto: "
        "estimated from the data, at the native rate of an upsampled stream); must be positive "
        "and below the data's range",
    )
    p.add_argument(
        "--noise-force",
        type=force_noise,
        metavar="N|P%|auto",
        help="noise std of the RECORDED force per sample, as an errors-in-variables term "
        "(--likelihood gaussian only): N (0.05 or 0.05N; mN, kN), P%% of the largest recorded "
        "|force| (2%%), or 'auto' (estimated from the force's high-frequency residual, floored "
        "at step/sqrt(12) for a quantised load cell, at the native rate of an upsampled stream); "
        "must be positive and below the largest recorded force; predictive bands then include "
        "it (default: 'auto' with --likelihood gaussian where the force noise can be estimated, "
        "else off; see treeinfer.model.force_noise)",
    )
    p.add_argument(
        "--noise-velocity",
        type=float,
        metavar="M_PER_S",
        help="add the velocity term to a generative likelihood, with this noise std in m/s "
        "(default: off; a velocity differentiated from the noisy displacement has noise ~ "
        "sigma_x / (sqrt(2) dt), correlated with it, and adds nothing: give it only for an "
        "independently measured velocity column)",
    )
    p.add_argument(
        "--seed",
        type=int,
        metavar="S",
        help=f"seed of the initial particles and the sampler (default {d['seed']})",
    )
    p.add_argument(
        "--eta",
        type=float,
        metavar="X",
        help="NNSVGD inequality-prior slope, nats per unit of log gain a child exceeds its "
        f"parent (default {d['eta']:g})",
    )
    p.add_argument(
        "--grasp-fraction",
        type=float,
        metavar="F",
        help="where along the grasped branch the data were recorded, in (0, 1] (default: the "
        "tree's grasp)",
    )
    p.add_argument(
        "--max-unstable-share",
        type=float,
        metavar="F",
        help="stop with an error if more than this share of the final particles simulate "
        f"unstably (default {d['max_unstable_share']:g}); may be changed with --resume",
    )
    p.add_argument(
        "--checkpoint-every",
        type=int,
        metavar="N",
        help="write RUN.partial/checkpoint.npz every N iterations; 0: only at the end of "
        f"sampling (default {d['checkpoint_every']})",
    )
    p.add_argument(
        "--resume",
        type=Path,
        metavar="RUN",
        help="continue the interrupted run RUN (all settings come from RUN.partial/config.json)",
    )
    p.add_argument(
        "--force",
        action="store_true",
        default=None,
        help="replace a non-empty RUN (and discard an interrupted RUN.partial)",
    )
    add_backend_option(p, default=None)
    p.add_argument(
        "--amortised",
        type=Path,
        metavar="MODEL",
        help="start from the amortised posterior of `treeinfer amortise --out MODEL` (trained "
        "for this tree and layout of recordings; refused otherwise): milliseconds, then checked "
        "against the simulator (Pareto-smoothed importance weights); if the check fails, the "
        "run falls back to the simulator-based path and says so (summary.json 'amortised')",
    )
    p.add_argument(
        "--prior-from",
        type=Path,
        metavar="RUN",
        help="an earlier run whose posterior becomes this run's prior on the joints both infer "
        "(a Gaussian mixture fitted to its particles; the box prior stays for the others); "
        "its files are checked against its checksums first",
    )
    p.add_argument(
        "--allow-modified",
        action="store_true",
        default=None,
        help="use the --prior-from run even if its files changed since `infer` wrote them "
        "(checksums in its manifest); recorded in this run's config.json and summary.json",
    )
    p.add_argument(
        "--prior-tail",
        type=float,
        metavar="S",
        help="tail width of the smoothed prior box, as a share of each log-box width; smaller "
        f"keeps intervals closer to the box (default {d['prior_tail']})",
    )
    p.add_argument(
        "--reinit-stragglers",
        type=int,
        metavar="N",
        help="warm-up remedy: up to iteration N, move stuck particles (log density far below "
        "the bulk or far outside the box) next to good ones after every chunk; 0: off (default "
        f"{d['reinit_stragglers']}); the run reports how many remain stuck",
    )
    p.add_argument(
        "--drop-stragglers",
        action="store_true",
        default=None,
        help="leave stuck final particles out of summary.json, particles.csv and the fit "
        "(they are always counted and warned about)",
    )
    p.add_argument(
        "--stop-when-converged",
        action="store_true",
        default=None,
        help="stop before --iterations once the particles' moments (and SVGD's kernelized "
        "Stein discrepancy) stop changing; summary.json says why the run stopped (the default; "
        "--run-all-iterations runs every one)",
    )
    p.add_argument(
        "--run-all-iterations",
        action="store_true",
        help="run every --iterations (the behaviour before the convergence stop became the "
        "default; for timing studies and the paper's protocol)",
    )
    p.add_argument(
        "--mcmc-warmup",
        type=float,
        metavar="SHARE",
        help="MCMC samplers: share of the trace discarded as warm-up before the summaries "
        f"(default {d['mcmc_warmup']})",
    )
    p.add_argument(
        "--mcmc-thin",
        type=int,
        metavar="K",
        help="MCMC samplers: keep every K-th post-warm-up draw of every chain; 0: thin to at "
        "most 1024 draws (default)",
    )
    p.add_argument(
        "--gradients",
        choices=GRADIENT_CHOICES,
        help="likelihood gradient: 'fd' (central differences, 2D + 1 rollouts per particle; the "
        "paper's, default) or 'jvp' (exact forward-mode sensitivities of the simulator)",
    )
    p.add_argument(
        "--init",
        choices=INIT_CHOICES,
        help="initial particles: 'auto' (default): a screen of the prior box, a multi-start "
        "Levenberg-Marquardt MAP fit, then Pareto-smoothed importance sampling around it: its "
        "draws are the posterior, with no sampler iterations, unless Pareto k-hat > 0.7 or too "
        "few effective samples, when the sampler runs from them until the answer stops "
        "changing (falls back to 'uniform' if the fit finds no stable start); 'importance': "
        "the same without the fallback; 'laplace' (around an LM MAP fit); 'uniform' in the "
        "prior box (the paper's). Every value works with every likelihood and model",
    )
    p.add_argument(
        "--shape-buckets",
        choices=("on", "off"),
        help="pad the data to a few bucket shapes (trajectories 1, 2, 3, 4, 6, 8, ...; steps up "
        "to 25%% more) so a new data set of a similar size reuses compiled programs: 'on' "
        "(default; used by --init importance, the log density is unchanged) or 'off'",
    )
    p.add_argument(
        "--model-kind",
        choices=("dynamic", "static"),
        help="'dynamic': time-stepped rollouts, Kp and Kd (default); 'static': the equilibrium "
        "under each force sample, for slow quasi-static pushes: stiffness only, damping not "
        "identified (infer prints a notice when the data look quasi-static)",
    )
    p.add_argument(
        "--tie",
        metavar="TIE",
        help="'taper': stiffness tied along the stem's taper (Kp_j = s * r_j^4 / l_j, Hencky "
        "lumping), one free scale s; 'shape': Kp_j = s * tie_shape_j with the tree file's "
        "inference.tie_shape (written by `treeinfer tree --kind stem`); 'none' drops a tree "
        "file's inference.tie (default: the tree file's); needs stiffness only (--model-kind "
        "static or inference.parameters: [kp])",
    )
    p.add_argument(
        "--tie-scale",
        type=float,
        metavar="TAU",
        help="soften the tie: each joint's log-stiffness deviates from the tie by "
        "Normal(0, TAU) (TAU = 0.1: about 10%%), so untested heights keep honest uncertainty "
        "(default: the tree file's inference.tie_scale, else a hard tie)",
    )
    add_model_options(p)
    add_simulation_options(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_formats_option(p, "run's figures (plots/)")
    p.add_argument(
        "--allow-poor-fit",
        action="store_true",
        help="exit 0 even if the fit checks judge the posterior a poor fit (exit code 4 "
        "otherwise); the verdict stays in summary.json. The verdict comes from posterior "
        "predictive checks on the training data: poor_fit when the 95%% predictive bands "
        "(with the inferred noise) miss far more than 5%% of the points; standardised "
        "residuals off in mean, scale or tails and autocorrelated residuals ('model misfit') "
        "only warn. Boltzmann runs (no noise model): poor_fit when the fit explains less than "
        "half the displacement's variance",
    )
    p.add_argument(
        "--allow-implausible-data",
        action="store_true",
        help="sample even if the plausibility checks find errors in the data (wrong units, "
        "swapped columns, duplicates ...); they are printed and recorded in summary.json",
    )
    return p


def _print_stragglers(strag: dict | None, n_particles) -> None:
    """One line: how many stuck particles were moved during the warm-up and how many remain
    (issue 27: no run ends with stuck particles silently)."""
    if not strag:
        return
    moved, left = int(strag.get("n_reinitialised", 0)), int(strag.get("n_stragglers", 0))
    of = f" of {n_particles}" if n_particles else ""
    if moved or left:
        print(
            f"stuck particles: {moved} re-initialised from the bulk during the warm-up; "
            f"{left}{of} still stuck at the end"
            + (" (summary.json 'stragglers' lists them)" if left else "")
        )


def run_infer(args: argparse.Namespace) -> int:
    _prepare_jax()
    _check_share(args.max_unstable_share)
    progress = not args.no_progress
    holder: dict[str, Any] = {}
    amortised = None
    if args.noise_displacement == AUTO:  # the default, said out loud
        args.noise_displacement = None
    if args.resume is not None:
        given = [flag for dest, flag in _RUN_OPTIONS.items() if getattr(args, dest) is not None]
        if given:
            raise ConfigError(
                "--resume takes every setting from "
                f"{args.resume}{runs.PARTIAL_SUFFIX}/config.json; leave out {', '.join(given)} "
                "(only --max-unstable-share and --no-progress may be given)"
            )
        run_dir, config, inputs = args.resume, None, None
    else:
        missing = [
            f
            for f, v in (("--tree", args.tree), ("--data", args.data), ("--out", args.out))
            if v is None
        ]
        if missing:
            raise ConfigError(
                f"{', '.join(missing)} required (or --resume RUN to continue an interrupted run)"
            )
        o = {
            k: (getattr(args, k) if getattr(args, k) is not None else v)
            for k, v in INFER_DEFAULTS.items()
        }
        o["grasp_fraction"] = args.grasp_fraction
        if args.run_all_iterations:
            if args.stop_when_converged:
                raise ConfigError("--run-all-iterations and --stop-when-converged: give one")
            o["stop_when_converged"] = False
        _check_meaning_changed(args)
        _check_infer_options(o)
        run_dir = args.out
        check_output_dir(  # before anything is read: an output is never one of the inputs
            run_dir, args.force, "run", inputs=[args.tree, args.data, args.model, args.prior_from]
        )
        for note in check_prior_run(args.prior_from, args.allow_modified):  # its integrity
            _say(f"warning: {note}")
        inputs = runs.load_run_inputs(
            args.tree,
            args.data,
            args.model,
            args.repair_inertia,
            o["model_kind"],
            o["tie"],
            o["tie_scale"],
        )
        config = runs.infer_config(
            args.tree,
            args.data,
            args.out,
            force=bool(args.force),
            model=args.model,
            repair_inertia=args.repair_inertia,
            inputs=inputs,
            **o,
        )
        # the figures' formats, read by runs.save_run (kept in the config for --resume)
        config["figure_formats"] = list(args.formats or ("png",))
        if args.amortised is not None:  # the model loaded and checked before anything runs
            from .amortise import amortised_for_infer

            amortised = amortised_for_infer(args, inputs, o)
        plan = f"{o['sampler']} ({o['particles']} particles x {o['iterations']} iterations)"
        if o.get("init") in ("auto", "importance"):  # the sampler runs if the weights fail
            plan = f"importance sampling ({o['particles']} particles), else {plan}"
        _say(f"{len(config['data']['files'])} training trajectories from {args.data}; {plan}")
    try:
        outcome = runs.run_inference(
            config,
            resume=args.resume,
            max_unstable_share=args.max_unstable_share,
            progress=progress,
            log=_say,
            on_checkpointer=lambda cp: holder.__setitem__("cp", cp),
            cache=runs.SimulatorCache(),
            allow_implausible_data=args.allow_implausible_data,
            inputs=inputs,
            amortised=amortised,
        )
    except KeyboardInterrupt:
        cp = holder.get("cp")
        if cp is None:
            _say("interrupted before sampling started; nothing to resume")
        elif cp.last_iteration is None:
            _say(
                f"interrupted before the first checkpoint; `treeinfer infer --resume {run_dir}` "
                "starts the same run again from iteration 0 (settings in "
                f"{runs.partial_dir(run_dir)}/config.json)"
            )
        else:
            _say(
                f"interrupted; the sampler state after iteration {cp.last_iteration} is kept in "
                f"{cp.path}.\ncontinue with:  treeinfer infer --resume {run_dir}"
            )
        return EXIT_INTERRUPTED
    s = outcome.summary
    if s.get("amortised"):
        a = s["amortised"]
        _say("amortised posterior " + ("used: its importance weights pass (Pareto k_hat "
             f"{a['khat']:.2f})" if a["used"] else f"not used ({a.get('reason')}); the "
             "simulator-based path ran instead"))  # fmt: skip
    if s.get("stop_reason", "max_iterations") != "max_iterations":
        _say(f"stopped early: {s['stop_reason']}")
    print_model_report(s.get("model"))
    _print_simulation(s.get("simulation"))
    _print_posterior(s)
    if s.get("damping"):
        print(s["damping"])
    _print_fit(s.get("training_metrics"), "fit to the training data")
    _print_warnings(s["convergence_warnings"])
    _print_stragglers(s.get("stragglers"), s.get("n_particles"))
    fit = s.get("fit") or {}
    status = fit.get("status", "ok")
    print(f"fit verdict: {status}" + "".join(f"\n  - {r}" for r in fit.get("reasons", [])))
    print(
        f"wrote {run_dir}/ (config.json, tree.yaml, posterior.nc, particles.csv, trace.npz, "
        "summary.json, plots/)"
    )
    if status == "poor_fit" and not args.allow_poor_fit:
        _say(
            f"poor fit: the posterior in {run_dir} does not explain the training data (reasons "
            "above); exit code 4 (--allow-poor-fit to accept it)"
        )
        return EXIT_POOR_FIT
    return EXIT_OK
