"""The inference problem of a run config (:func:`build_problem`: the cached simulator, the grasp
points of the data, the prior from an earlier run) and the checks before sampling (data
plausibility, quasi-static data). Used by :mod:`.service`, which re-exports it."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from pathlib import Path

import jax
import numpy as np

from ..data.trajectories import Observations, Trajectory, stack_trajectories
from ..errors import ConfigError, TrajectoryFileError
from ..inference.problem import DEFAULT_PRIOR_SIGMA
from ..inference.samplers import sampler_spec
from ..sim.startup import steps_bucket, trajectories_bucket
from ..tree.description import Tree
from .cache import SimulatorCache, simulator_for


def _grasp_fractions(o: dict, tree: Tree, trajectories):
    """The run's --grasp-fraction, else each trajectory's own from its data folder's pulls.yaml
    (one fraction per trajectory), else None (the tree's grasp point)."""
    if o.get("grasp_fraction") is not None or not o.get("data"):
        return o.get("grasp_fraction")
    if isinstance(trajectories, Observations):
        return None
    from ..data.pulls import data_grasp_fractions

    own = data_grasp_fractions(o["data"], tree, [t.source for t in trajectories])
    if own is None:
        return None
    return float(own[0]) if np.allclose(own, own[0]) else [float(g) for g in own]


SHAPE_BUCKET_CHOICES = ("on", "off")
# noise_force_rule of a run whose force-noise reference the start pipeline found
PIPELINE_RULE = "J at the start pipeline's MAP of this errors-in-variables model"


def shape_bucket_for(config: dict, obs: Observations) -> list[int] | None:
    """``[B', T']`` the run's observations are padded to in the programs that take them as
    arguments (:mod:`treeinfer.sim.startup`), or None; recorded as ``shape_bucket`` in the run's
    problem settings (config.json).

    Option ``shape_buckets`` (``on``, the default, or ``off``). This is the bucket of ``--init
    importance``'s rollout program (:class:`treeinfer.inference.fast_evaluator.BatchEvaluator`),
    recorded for those runs here; the samplers' programs take their bucket from
    :func:`sampler_bucket_for` (the same bucket; :func:`treeinfer.inference.problem.make_problem`
    records it with ``sampler_data: "arguments"`` where its target takes the data as an
    argument). The masked padding changes the log density by float rounding only (~1e-6
    relative, ``tests/test_startup.py``, ``tests/test_sampler_buckets.py``). A resumed run
    keeps what it recorded."""
    o = config["options"]
    recorded = config.get("problem")
    if recorded:  # a resumed run: built as recorded (runs from before buckets have none)
        b = recorded.get("shape_bucket")
        return None if b is None else [int(b[0]), int(b[1])]
    choice = o.get("shape_buckets", "on")
    if choice not in SHAPE_BUCKET_CHOICES:
        raise ConfigError(
            f"shape_buckets: expected one of {', '.join(SHAPE_BUCKET_CHOICES)}, got {choice!r}"
        )
    if choice == "off" or o.get("init", "uniform") not in ("auto", "importance"):
        return None
    b, t = np.shape(obs.force)
    return [trajectories_bucket(b), steps_bucket(t)]


def sampler_bucket_for(config: dict, obs: Observations) -> list[int] | None:
    """``[B', T']`` the samplers' programs take the run's observations padded to, as an argument
    (:func:`treeinfer.inference.problem.make_problem`'s ``shape_bucket``), or None (the data are
    constants of the programs, as before). New runs: the buckets of the data's shape
    (:func:`treeinfer.sim.startup.trajectories_bucket`, :func:`~treeinfer.sim.startup.steps_bucket`)
    unless ``shape_buckets`` is ``off``, or the run takes an earlier run's posterior as its
    prior (``prior_from``: that target is not built on the data argument). A resumed run is
    built as recorded: the bucket when its problem settings record ``sampler_data:
    "arguments"``, else None (runs from before, whose samplers embedded the data)."""
    o = config["options"]
    recorded = config.get("problem")
    if recorded:
        b = recorded.get("shape_bucket")
        if b is None or recorded.get("sampler_data") != "arguments":
            return None
        return [int(b[0]), int(b[1])]
    choice = o.get("shape_buckets", "on")
    if choice not in SHAPE_BUCKET_CHOICES:
        raise ConfigError(
            f"shape_buckets: expected one of {', '.join(SHAPE_BUCKET_CHOICES)}, got {choice!r}"
        )
    if choice == "off" or o.get("prior_from"):
        return None
    b, t = np.shape(obs.force)
    return [trajectories_bucket(b), steps_bucket(t)]


# The step's accuracy target of a generative likelihood (sigma_x inferred): this share of the
# data's displacement-noise estimate, within [DEFAULT_SIM_TOLERANCE, MAX_NOISE_TOLERANCE].
NOISE_TOLERANCE_SHARE = 0.1
MAX_NOISE_TOLERANCE = 1e-3  # m


def noise_tolerance(options: dict, obs: Observations) -> float | None:
    """m, the simulation step's accuracy target of a new run without ``--sim-tolerance``: a
    tenth of the displacement noise (the given ``noise_displacement``, else the data's robust
    estimate, :func:`treeinfer.model.noise.estimate_displacement_noise`) for a generative
    likelihood, never finer than the fixed default (0.1 mm) nor coarser than 1 mm; None (the
    fixed default) for the Boltzmann loss (the paper's experiments keep their step) or when the
    noise cannot be estimated.

    Why: the step's error is a model error added to every simulated point; at a tenth of the
    noise's standard deviation it adds 0.5% to the residual variance, invisible next to the
    noise, while the fixed 0.1 mm asks a 2 mm-noise recording for twice the substeps (32
    against 16 on the standard problem: every rollout of the run costs twice as much). The
    step-doubling estimate bounds the error over the whole prior box, so at the posterior it is
    smaller still (``tests/test_noise_tolerance.py`` checks the chosen step against an
    independent integration)."""
    from ..inference.problem import resolve_likelihood
    from ..model.noise import estimate_displacement_noise
    from ..sim import DEFAULT_SIM_TOLERANCE

    try:
        likelihood = resolve_likelihood(options.get("likelihood", "boltzmann"), options["kT"])
    except ConfigError:  # make_problem refuses it, naming the option
        return None
    if likelihood == "boltzmann":
        return None
    sigma = options.get("noise_displacement")
    if sigma is None:
        try:
            sigma = estimate_displacement_noise(obs).sigma
        except ConfigError:
            return None
    try:
        sigma = float(sigma)
    except (TypeError, ValueError):
        return None
    if not (np.isfinite(sigma) and sigma > 0):
        return None
    return float(np.clip(NOISE_TOLERANCE_SHARE * sigma, DEFAULT_SIM_TOLERANCE, MAX_NOISE_TOLERANCE))


def build_problem(
    config: dict,
    tree: Tree,
    trajectories: Sequence[Trajectory] | Observations,
    cache: SimulatorCache | None = None,
    resumed: bool = False,
    log: Callable[[str], None] = lambda msg: None,
):
    """The inference problem of a run config (the cached simulator; a jitted log-density).

    With ``--noise-force``, the force Jacobian's reference point: a resumed run (``resumed``)
    takes the one it recorded; a run whose ``--init`` is ``auto`` or ``importance`` finds it on
    the start pipeline's rollout program
    (:func:`treeinfer.inference.start_pipeline.force_noise_reference`); any other run fits it with
    :func:`treeinfer.model.force_noise_reference.reference_theta`."""
    from ..inference.problem import make_problem

    o = config["options"]
    obs = (
        trajectories
        if isinstance(trajectories, Observations)
        else stack_trajectories(list(trajectories))
    )
    recorded = config.get("problem") or {}  # a resumed run: the settings it was built with
    # runs from before force interpolation existed held the force over each sample
    interp = recorded.get("force_interp", o.get("force_interp", "hold" if recorded else "linear"))
    tolerance = o.get("sim_tolerance")
    # observation channels besides the grasp point (the data folder's channels.yaml): they name
    # their pulls by file name, so the final problem takes the trajectories, not the stack; a
    # k-fold training split holds some of the folder's pulls: their channels only
    table = not isinstance(trajectories, Observations)
    channels = ()
    if table and o.get("data"):
        from ..data.channels import read_channels

        channels = read_channels(o["data"], tree, trajectories, only_these_pulls=True)
    if tolerance is None and not recorded:
        tolerance = noise_tolerance(o, obs)
        if channels:  # a step accurate to a tenth of each channel's noise too
            from ..model.channels import channel_tolerance

            tol_ch = channel_tolerance(channels, tree)
            if tol_ch is not None and (tolerance is None or tol_ch < tolerance):
                log(f"simulation step: accuracy {tol_ch * 1e3:.3g} mm for the channels' noise")
                tolerance = tol_ch
    kind = o.get("model_kind", "dynamic")
    # each recording's own branch, grasp point and direction (the data folder's pulls.yaml)
    from ..inference.static import model_for, model_with_pulls

    model, grasp = model_with_pulls(
        model_for(tree, kind) if kind == "static" else None,
        o.get("data") if table else None,
        [t.source for t in trajectories] if table else [],
        o.get("grasp_fraction"),
        tree=tree,
    )
    pulls = {}
    if model is None:  # every pull down at the tree's grasp branch: the paper's model
        grasp = _grasp_fractions(o, tree, trajectories)
    else:
        grasp = None if grasp is None else np.asarray(grasp, float).tolist()
        pulls = {"direction": model.direction, "grasp_branch": model.grasp_branch}
    # the force Jacobian's program (the largest of the run: about 15 CPU-s to trace and compile on
    # a 2-core CPU) compiled on a second thread while the step is chosen and the reference's
    # screen and first fit run (runs.background)
    recorded_reference = resumed and recorded.get("noise_force_reference") is not None
    pipeline_force = (
        o.get("init", "uniform") in ("auto", "importance")
        and _force_term(o, tree, kind, model, obs) is not None
    )
    jac = _prefetch_force_jacobian(
        cache, tree, obs, grasp, recorded.get("backend", o.get("backend", "auto")), interp,
        pipeline_force and not recorded_reference,
    )  # fmt: skip
    # and the reference fits' rollout program on a third (the step is chosen meanwhile on this one)
    roll = _prefetch_rollout_program(
        cache, tree, obs, grasp, recorded.get("backend", o.get("backend", "auto")), interp,
        shape_bucket_for(config, obs), pipeline_force and not recorded_reference,
    )  # fmt: skip
    sim = simulator_for(
        tree,
        float(obs.dt),
        recorded.get("substeps"),
        recorded.get("backend", o.get("backend", "auto")),
        cache,
        force_interp=interp,
        max_sim_dt=o.get("max_sim_dt"),
        sim_tolerance=tolerance,
        forces=np.asarray(obs.force),
        grasp_fraction=o.get("grasp_fraction"),
    )
    if recorded.get("sim_step"):  # a resumed run: how its step was chosen, as recorded
        sim = dataclasses.replace(sim, step_info=dict(recorded["sim_step"]))
    common = dict(
        kT=o["kT"],
        nn_prior=sampler_spec(o["sampler"]).nn_prior,
        eta=o["eta"],
        prior_sigma=o.get("prior_tail", DEFAULT_PRIOR_SIGMA),
        grasp_fraction=grasp,
        sim=sim,
        gradient=o.get("gradients", "fd"),
        likelihood=o.get("likelihood", "boltzmann"),  # run folders older than issue 11
        noise_displacement=o.get("noise_displacement"),
        noise_force=o.get("noise_force"),
        noise_velocity=o.get("noise_velocity"),
        model_kind=kind,
        shape_bucket=sampler_bucket_for(config, obs),
        **pulls,
    )
    reference = {}
    if recorded_reference:
        rule = str(recorded.get("noise_force_rule", ""))
        reference = {
            "force_noise_reference": np.asarray(recorded["noise_force_reference"], float),
            "force_noise_rule": rule.split("; ", 1)[1] if "; " in rule else rule,
        }
    elif pipeline_force:
        from ..inference.start_pipeline import force_noise_reference

        # the reference fits' problems run on the rollout program only: no sampler target
        fit_only = {**common, "shape_bucket": None}

        def make(ref):
            jac.wait()  # never two threads tracing the same program
            return make_problem(
                tree, obs, **fit_only, force_noise_reference=ref, force_noise_rule=PIPELINE_RULE
            )

        base = make_problem(tree, obs, **{**fit_only, "noise_force": None})
        bucket = shape_bucket_for(config, obs)
        roll.wait()  # its rollout program: compiled on the second thread
        try:
            ref, finals = force_noise_reference(
                make,
                base,
                8,
                int(o.get("seed", 0)),
                None if cache is None else cache.programs,
                log,
                None if bucket is None else tuple(bucket),
            )
        finally:
            jac.wait()
        reference = {"force_noise_reference": ref, "force_noise_rule": PIPELINE_RULE}
        from ..inference.integration_floor import applies, measure_integration_error

        if applies(base, o.get("init")):  # the simulator's error at this MAP: a noise floor
            ie = measure_integration_error(
                base,
                ref,
                None if cache is None else cache.programs,
                None if bucket is None else tuple(bucket),
            )
            log(f"noise floor: {ie.describe()}")
            reference["integration_error"] = ie
    if channels:
        log(f"observation channels: {', '.join(c.name for c in channels)} (channels.yaml)")
        problem = make_problem(tree, list(trajectories), **common, **reference, channels=channels)
    else:
        from ..inference.integration_floor import floor_for_run

        problem = floor_for_run(  # the simulator's error at the MAP as a noise floor
            make_problem(tree, obs, **common, **reference),
            lambda ie: make_problem(tree, obs, **common, **reference, integration_error=ie),
            o.get("init"), recorded if resumed else None, int(o.get("seed", 0)),
            None if cache is None else cache.programs, shape_bucket_for(config, obs), log,
        )  # fmt: skip
    if reference.get("force_noise_rule") == PIPELINE_RULE and not resumed:
        problem = dataclasses.replace(problem, start_hint=finals)
    if o.get("prior_from"):  # the earlier run's posterior as the prior of the shared joints
        from ..inference.sequential import prior_from_run, with_prior
        from .folder import load_run

        # checked as every reader of a run checks it; --allow-modified: what changed is recorded
        earlier = load_run(o["prior_from"], allow_modified=bool(o.get("allow_modified")))
        prior = prior_from_run(earlier, problem.labels)
        problem = with_prior(problem, prior.log_density)
        record = {"run": o["prior_from"], **prior.to_dict()}
        if earlier.notes:
            record["integrity_notes"] = list(earlier.notes)
        settings = {**problem.settings, "prior_from": record}
        problem = dataclasses.replace(problem, settings=settings)
    bucket = shape_bucket_for(config, obs)
    if bucket is not None:
        problem = dataclasses.replace(
            problem, settings={**problem.settings, "shape_bucket": bucket}
        )
    # infer() evaluates log_density once at the end: jitted, the simulator is traced and compiled
    # once
    # (op-by-op it costs tens of seconds); MH samples with the same function.
    return dataclasses.replace(problem, log_density=jax.jit(problem.log_density))


def _prefetch_force_jacobian(cache, tree, obs, grasp, backend, interp, needed: bool):
    """Compile the force Jacobian's program for these pulls on a second thread
    (:func:`treeinfer.runs.background.prefetch`; a no-op unless ``needed`` and a ``cache`` is
    given). Its program takes the gains and the step count as arguments, so it does not depend
    on the accuracy-controlled step that is being chosen meanwhile: it is compiled on a
    simulator of the same settings at one substep, and the cache shares the Jacobian programs of
    all its simulators (:meth:`SimulatorCache.get`), so the run's simulator finds it there
    (``tests/test_background.py``). Taken at log gains 0 and thrown away (``keep=False``; an
    unstable rollout there raises after the compile, which is all that is wanted)."""
    from .background import prefetch

    if not needed or cache is None:
        return _NoPrefetch()
    from ..model.force_noise import force_jacobian

    early = cache.get(tree, float(obs.dt), 1, backend, force_interp=interp)
    theta = np.zeros(2 * early.n_joints)
    forces = np.asarray(obs.force)
    return prefetch(
        lambda: force_jacobian(early, theta, forces, grasp, keep=False), "force-jacobian"
    )


def _prefetch_rollout_program(cache, tree, obs, grasp, backend, interp, bucket, needed: bool):
    """Compile the force-noise reference fits' rollout program
    (:func:`treeinfer.inference.start_pipeline.force_noise_reference`: 8 starts, a batch of
    8 (2g + 1) parameter sets on a CPU) on a second thread, as :func:`_prefetch_force_jacobian`
    does the Jacobian's: its step count is an argument, so a one-substep simulator of the same
    settings compiles the program the run's simulator asks for (the same key in the command's
    program cache, :meth:`treeinfer.sim.Simulator.program_key`), while the step is chosen on the
    main thread. Skipped (nothing lost) for per-pull grasp points."""
    from .background import prefetch

    if not needed or cache is None or isinstance(grasp, list):
        return _NoPrefetch()
    from ..inference.fast_evaluator import compile_rollout_program, default_chunk

    early = cache.get(tree, float(obs.dt), 1, backend, force_interp=interp)
    # as BatchEvaluator reads the problem's grasp point: None is the simulator's own
    gf = None if grasp is None or math.isclose(grasp, tree.grasp_fraction) else float(grasp)
    k = 8 * (4 * early.n_joints + 1)
    chunk = default_chunk(k, 8 * k)
    shape = None if bucket is None else tuple(bucket)
    return prefetch(
        lambda: compile_rollout_program(early, gf, chunk, obs, shape, cache.programs),
        "rollout-program",
    )


class _NoPrefetch:
    def wait(self) -> None:
        pass


def _force_term(o: dict, tree: Tree, kind: str, model, obs):
    """The run's force-noise setting on the paper's dynamic model (None: no term there), the
    default resolved as :func:`treeinfer.inference.problem.make_problem` resolves it."""
    from ..inference.problem import default_noise_force, resolve_likelihood
    from ..inference.static import model_for

    if model is not None or kind != "dynamic" or not model_for(tree, kind).is_paper:
        return None
    likelihood = resolve_likelihood(o.get("likelihood", "boltzmann"), o["kT"])
    return default_noise_force(o.get("noise_force"), likelihood, True, obs)[0]


def _data_checks(
    config: dict, tree: Tree, trajs, log: Callable[[str], None], allow_implausible_data: bool
) -> list[str]:
    """Plausibility checks before sampling (:mod:`treeinfer.evaluation.checks`): errors stop the run
    unless ``allow_implausible_data``; warnings are logged, and so are entries of the data folder
    that are not read (FIFOs, broken links, ``.CSV``). Returns every finding as text
    (summary.json)."""
    from ..evaluation.checks import format_findings, preflight
    from ..io.safe_load import list_data_files

    o = config["options"]
    data_dir = Path(config["data"]["dir"])
    _, skipped = list_data_files(data_dir)
    skipped = [f"warning: {m}" for m in skipped]
    paths = [data_dir / f["name"] for f in config["data"]["files"]]
    errors, warns = preflight(
        tree,
        trajs,
        paths if len(paths) == len(trajs) else None,
        tree_file=o.get("tree"),
        grasp_fraction=o.get("grasp_fraction"),
    )
    drop = _checks_not_applicable(config, tree, [f["name"] for f in config["data"]["files"]])
    errors = [f for f in errors if f.check not in drop]
    warns = [f for f in warns if f.check not in drop]
    if errors and not allow_implausible_data:
        raise TrajectoryFileError(
            "the training data are implausible for this tree:\n"
            + "\n".join([format_findings(errors + warns), *skipped])
            + "\nfix the data (or the tree), or pass --allow-implausible-data to sample anyway"
        )
    for f in errors + warns:
        log(str(f))
    for m in skipped:
        log(m)
    return [str(f) for f in errors + warns] + skipped


def _checks_not_applicable(config: dict, tree: Tree, names: Sequence[str]) -> set[str]:
    """Plausibility checks that do not apply to this run: the simulation cost (the static
    model does not step time), and the cross-file compliance comparison when the data folder's
    pulls.yaml puts the recordings at different grasp points or directions (their compliance
    differs by design, e.g. a stem pushed at three heights)."""
    drop = set()
    if config["options"].get("model_kind", "dynamic") == "static":
        drop.add("simulation-cost")
    from ..data.pulls import PULLS_FILE, load_data_pulls

    data_dir = Path(config["data"]["dir"])
    if names and (data_dir / PULLS_FILE).is_file():
        try:
            pulls = load_data_pulls(data_dir, tree, names)
        except ConfigError:
            return drop  # the problem build reports a bad sidecar, naming the field
        keys = {(p.branch, round(p.fraction, 9), tuple(np.round(p.direction, 9))) for p in pulls}
        if len(keys) > 1:
            drop.add("mixed-units")
    return drop


def _quasi_static_check(problem, config: dict, log: Callable[[str], None]) -> None:
    """Log :func:`treeinfer.inference.static.quasi_static_notice` when the dynamic model is asked to
    fit data sampled far more slowly than the branch's slowest natural period."""
    if config["options"].get("model_kind", "dynamic") != "dynamic":
        return
    from ..inference.static import quasi_static_notice

    try:
        notice = quasi_static_notice(problem.tree, problem.sim, float(problem.obs.dt))
    except Exception as e:  # noqa: BLE001 - a notice must never stop a run
        log(f"note: could not judge whether the data are quasi-static ({type(e).__name__}: {e})")
        return
    if notice:
        log(f"note: {notice}")
