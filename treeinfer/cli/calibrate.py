"""``treeinfer calibrate``: simulation-based calibration of the posterior on a tree
(:mod:`treeinfer.calibration`)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from ..calibration import (
    COVERAGE_LEVELS,
    SBC_LIKELIHOODS,
    SBC_SAMPLERS,
    SBCConfig,
    config_record,
    run_tree_sbc,
    write_outputs,
)
from ..errors import ConfigError
from ..io.atomic import atomic_write_json, check_output_dir, staged_output_dir
from ..io.limits import check_command_size
from ..tree.description import dump_tree, load_tree
from .common import (
    COMMAND_HELP,
    EXIT_OK,
    _prepare_jax,
    _say,
    add_backend_option,
    add_command_parser,
)
from .options import (
    AUTO,
    add_formats_option,
    displacement_noise,
    force_noise,
    length,
    refuse_noise_form,
)

_D = SBCConfig()

_CALIBRATE_EPILOG = f"""\
examples:
  treeinfer calibrate --tree two_branch.yaml --out sbc --datasets 20 --particles 16
  treeinfer calibrate --tree two_branch.yaml --out sbc-gpu --datasets 256 --chunk 128 \\
      --particles 32 --smc-particles 256 --smc-levels 96 --seed 1

What it does (Talts et al. 2018): for each of --datasets data sets, draw Kp, Kd of the inferred
joints from the smoothed box prior (and sigma_x from log sigma_x ~ Normal(log
--noise-prior-center, --sigma-prior-scale) unless --noise-displacement fixes it), simulate
--n-traj pulls under fresh random force profiles, add noise of the --likelihood model, run
inference with that same model, and rank the truth among the --particles posterior draws. A
calibrated posterior gives uniform ranks and central intervals that cover the truth as often as
their level says ({", ".join(f"{a:.0%}" for a in COVERAGE_LEVELS)} reported).

Sampler: smc (default) starts --smc-particles exact prior draws per data set and tempers them
to the posterior (adaptive temperature ladder of --smc-levels levels, systematic resampling,
--smc-mutations random-walk MH moves per level with the cloud's covariance, --smc-final moves at
the end); --particles of the final cloud are ranked. Likelihood only: one simulation per particle
and move. mh (the previous default) climbs to the best mode with Adam and runs MH chains there;
it misses separated modes and failed SBC on the GPU. svgd ranks the final SVGD particles. All
data sets of a chunk run in one jitted program (--chunk data sets at once: hundreds on a GPU, a
few on a CPU).

Output folder (built aside, appears complete or not at all): sbc_summary.json (uniformity
p-values per parameter: chi-square on equal bins and Kolmogorov-Smirnov of the fractional ranks,
pass/fail at 1% with a Bonferroni correction; the coverage table with 99% binomial bands;
timings), ranks.csv, draws.npz (truths and draws in log units), config.json (every option, the
seed, versions), tree.yaml, plots/rank_histograms.png, plots/coverage.png.
"""


def _force_share(value) -> float:
    """Parsed ``--noise-force`` -> the share of each data set's largest force. Only the ``P%``
    form (or 0, no noise): each calibration data set scales its noise to its own peak force."""
    refuse_noise_form(
        value if value not in (0, 0.0) else "0%", "--noise-force", "calibrate", ("%",),
        "scales the force noise to each data set's largest force: give a share, e.g. 2% "
        "(newtons and 'auto' are forms of the same option in infer and simulate)",
    )  # fmt: skip
    return 0.0 if value in (0, 0.0) else float(value[:-1]) / 100.0


def configure_calibrate(subparsers) -> argparse.ArgumentParser:
    p = add_command_parser(
        subparsers,
        "calibrate",
        help=COMMAND_HELP["calibrate"],
        description="Simulation-based calibration: draw parameters from the prior, simulate noisy "
        "pulls, infer, and test whether the truths' ranks among the posterior draws are uniform "
        "and the central intervals cover as often as they claim.",
        epilog=_CALIBRATE_EPILOG,
    )
    p.add_argument("--tree", type=Path, required=True, help="tree description (YAML/JSON)")
    p.add_argument(
        "--out",
        type=Path,
        required=True,
        metavar="DIR",
        help="output folder (must be empty or absent unless --force)",
    )
    p.add_argument(
        "--datasets",
        type=int,
        default=_D.datasets,
        metavar="N",
        help="simulated data sets (>= 200 for the uniformity target)",
    )
    p.add_argument(
        "--likelihood",
        choices=SBC_LIKELIHOODS,
        default=_D.likelihood,
        help="noise model the data are simulated with AND inferred with "
        "(as `treeinfer infer --likelihood`)",
    )
    p.add_argument(
        "--noise-displacement",
        type=displacement_noise,
        default=None,
        metavar="M|auto",
        help="displacement noise sigma_x, m (0.002 or 2mm; cm, um), fixed and known to "
        "inference; 'auto' (default): drawn from its prior and inferred jointly, as `infer` does",
    )
    p.add_argument(
        "--noise-prior-center",
        type=length,
        default=_D.noise_prior_center,
        metavar="M",
        help="m (or 2mm), centre of the sigma_x prior when it is inferred",
    )
    p.add_argument(
        "--sigma-prior-scale",
        type=float,
        default=_D.sigma_prior_scale,
        metavar="S",
        help="std of the log sigma_x prior when it is inferred",
    )
    p.add_argument(
        "--student-t-df",
        type=float,
        default=_D.student_t_df,
        metavar="DF",
        help="degrees of freedom for --likelihood student_t",
    )
    p.add_argument(
        "--sampler",
        choices=SBC_SAMPLERS,
        default=_D.sampler,
        help="sampler: smc (default): adaptive tempered SMC from the prior, near-exact draws "
        "that keep every mode; mh: Adam to the best mode, then random-walk MH chains there "
        "(misses other modes); svgd: the SVGD particles themselves",
    )
    p.add_argument(
        "--smc-particles",
        type=int,
        default=_D.smc_particles,
        metavar="N",
        help="SMC cloud size per data set (>= --particles; --particles of them are ranked)",
    )
    p.add_argument(
        "--smc-levels",
        type=int,
        default=_D.smc_levels,
        metavar="K",
        help="SMC temperature levels (the last is forced to beta = 1; more levels after beta "
        "reaches 1 are extra moves)",
    )
    p.add_argument(
        "--smc-mutations",
        type=int,
        default=_D.smc_mutations,
        metavar="M",
        help="random-walk MH steps per SMC level",
    )
    p.add_argument(
        "--smc-final",
        type=int,
        default=_D.smc_final,
        metavar="M",
        help="MH steps at beta = 1 after the SMC ladder",
    )
    p.add_argument(
        "--particles",
        type=int,
        default=_D.particles,
        metavar="P",
        help="posterior draws L ranked per data set, >= 2 (mh/svgd: the particles)",
    )
    p.add_argument(
        "--iterations",
        type=int,
        default=_D.iterations,
        metavar="N",
        help="Adam ascent (mh) or SVGD (svgd) iterations, >= 1",
    )
    p.add_argument(
        "--learning-rate",
        type=float,
        default=_D.learning_rate,
        metavar="X",
        help="Adam learning rate (log units per step; mh: decays 100x)",
    )
    p.add_argument(
        "--mh-warmup",
        type=int,
        default=_D.mh_warmup,
        metavar="N",
        help="adaptive MH warm-up steps per chain (mh), discarded",
    )
    p.add_argument(
        "--mh-steps",
        type=int,
        default=_D.mh_steps,
        metavar="N",
        help="fixed-proposal MH steps per chain after the warm-up (mh)",
    )
    p.add_argument(
        "--n-traj",
        type=int,
        default=_D.n_traj,
        metavar="N",
        help="pulls per data set (random 'mixed' force profiles, as `simulate`)",
    )
    p.add_argument(
        "--test-traj",
        type=int,
        default=0,
        metavar="B",
        help="unseen test pulls per data set: adds the share of noisy test points "
        "inside the 95%% predictive band (0: none)",
    )
    p.add_argument(
        "--noise-force",
        type=force_noise,
        default="0%",
        metavar="P%",
        help="force noise on the recorded forces: P%% of each data set's largest force (2%%; "
        "the N and 'auto' forms of this option in infer/simulate have no meaning here); not "
        "in the inference model, so SBC is exact only at 0%%",
    )
    p.add_argument("--duration", type=float, default=_D.duration, metavar="S", help="s per pull")
    p.add_argument("--dt", type=float, default=_D.dt, metavar="S", help="s between samples")
    p.add_argument(
        "--seed",
        type=int,
        default=_D.seed,
        metavar="S",
        help="seed of the truths, profiles, noise, initial particles and sampler",
    )
    p.add_argument(
        "--max-sim-dt",
        type=float,
        default=None,
        metavar="S",
        help="s, upper bound on the simulation step (default 0.005)",
    )
    p.add_argument(
        "--chunk",
        type=int,
        default=_D.chunk,
        metavar="C",
        help="data sets per jitted program call (GPU: 64-256; CPU: a few)",
    )
    add_backend_option(p)
    p.add_argument("--force", action="store_true", help="replace an existing output folder")
    add_formats_option(p, "figures (plots/rank_histograms, plots/coverage)")
    p.add_argument(
        "--allow-large",
        action="store_true",
        help="go past the size limit (treeinfer.io.limits) checked before any work",
    )
    return p


def _config_from_args(args) -> SBCConfig:
    if args.noise_displacement == AUTO:  # the default, said out loud
        args.noise_displacement = None
    if args.max_sim_dt is not None and not (math.isfinite(args.max_sim_dt) and args.max_sim_dt > 0):
        raise ConfigError(
            f"--max-sim-dt: must be a positive number of seconds, got {args.max_sim_dt:g}"
        )
    for flag, v in (
        ("--noise-displacement", args.noise_displacement),
        ("--noise-prior-center", args.noise_prior_center),
    ):
        if v is not None and not (math.isfinite(v) and v > 0):
            raise ConfigError(f"{flag}: must be a finite positive number (metres), got {v:g}")
    cfg = SBCConfig(
        datasets=args.datasets,
        likelihood=args.likelihood,
        noise_displacement=args.noise_displacement,
        noise_prior_center=args.noise_prior_center,
        sigma_prior_scale=args.sigma_prior_scale,
        student_t_df=args.student_t_df,
        sampler=args.sampler,
        particles=args.particles,
        smc_particles=args.smc_particles,
        smc_levels=args.smc_levels,
        smc_mutations=args.smc_mutations,
        smc_final=args.smc_final,
        iterations=args.iterations,
        learning_rate=args.learning_rate,
        mh_warmup=args.mh_warmup,
        mh_steps=args.mh_steps,
        n_traj=args.n_traj,
        duration=args.duration,
        dt=args.dt,
        seed=args.seed,
        max_sim_dt=args.max_sim_dt,
        chunk=args.chunk,
        backend=args.backend,
        test_traj=args.test_traj,
        noise_force=_force_share(args.noise_force),
    )
    try:
        return cfg.check()
    except ConfigError as e:  # name the flag, not the field
        msg = str(e)
        head, _, rest = msg.partition(":")
        raise ConfigError(f"--{head.replace('_', '-')}:{rest}" if rest else msg) from None


def run_calibrate(args: argparse.Namespace) -> int:
    from tqdm.auto import tqdm

    check_command_size("calibrate", args)  # before any work: --datasets 1e9 is an error now
    check_output_dir(args.out, args.force, "calibration", inputs=[args.tree])
    cfg = _config_from_args(args)
    tree = load_tree(args.tree)
    from ..evaluation.checks import grasp_reach
    from ..model.noise import check_sigma

    for flag, v in (
        ("--noise-displacement", cfg.noise_displacement),
        ("--noise-prior-center", cfg.noise_prior_center),
    ):
        if v is not None:  # above any pull's range: a unit mistake (issue 27, "Bad input")
            check_sigma(
                v, flag, 2.0 * grasp_reach(tree), what="the farthest the grasp point can move"
            )
    _prepare_jax()
    _say(
        f"calibrate: {cfg.datasets} data sets of {cfg.n_traj} pulls on '{tree.name}', "
        f"{cfg.likelihood} noise "
        + (
            f"sigma_x = {cfg.noise_displacement:g} m (given)"
            if cfg.noise_displacement
            else f"sigma_x inferred (prior centre {cfg.noise_prior_center:g} m)"
        )
        + f", sampler {cfg.sampler}, {cfg.particles} draws per data set"
    )
    with tqdm(total=cfg.datasets, desc="data sets", unit="set") as bar:

        def progress(done, total):
            bar.update(done - bar.n)

        result = run_tree_sbc(tree, cfg, progress=progress, log=_say)
    record = config_record(args.tree, cfg)
    with staged_output_dir(args.out, args.force, "calibration", inputs=[args.tree]) as stage:
        atomic_write_json(stage / "config.json", record)
        dump_tree(tree, stage / "tree.yaml")
        summary = write_outputs(result, stage, record, formats=args.formats)
    u = summary["uniformity"]
    for lab, t in u["parameters"].items():
        _say(
            f"  {lab:>14}: p(chi2) {t['p_chi2']:.3g}  p(KS) {t['p_ks']:.3g}  "
            f"{'ok' if t['pass'] else 'NOT UNIFORM'}"
        )
    k95 = [r for r in summary["coverage"] if r["level"] == 0.95]
    _say(
        "  95% interval coverage: "
        + ", ".join(f"{r['parameter']} {r['observed']:.0%}" for r in k95)
    )
    t = summary["info"].get("test_inside_95")
    if t:
        _say(
            f"  unseen noisy test points inside the 95% predictive band: median "
            f"{t['predictive']['median']:.1%} (parameter-only band "
            f"{t['parameter']['median']:.1%})"
        )
    _say(
        f"uniformity at {u['alpha']:g} (Bonferroni, per-parameter p > "
        f"{u['per_parameter_threshold']:.2g}): {'PASS' if u['pass'] else 'FAIL'}; "
        f"wrote {args.out}"
    )
    return EXIT_OK
