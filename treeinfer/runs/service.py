"""The run service: sample a posterior and write the run folder, resume an interrupted run,
cross-validate a run's settings (k-fold). Owns the simulator cache of a command.
"""

from __future__ import annotations

import dataclasses
import math
import os
import shutil
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import jax
import numpy as np

from .._io import (
    check_output_dir,
    clean_stale_staging,
)
from ..errors import ConfigError, OutputExistsError, SimulationError, TrajectoryFileError

# ==== problem and posterior =======================================================================
from ..evaluation import Prediction, _training_fit, evaluate_trajectories, kfold_splits, noise_for
from ..inference import DEFAULT_PRIOR_SIGMA
from ..jsonio import jsonable as _jsonable
from ..jsonio import read_json, write_json
from ..samplers import sampler_spec
from ..trajectories import (
    Observations,
    Trajectory,
    read_trajectory_dir,
    stack_trajectories,
)
from ..tree import Tree, dump_tree, load_tree, tree_to_dict
from .cache import SimulatorCache, simulator_for
from .checkpoint import (
    CHECKPOINT_FILE,
    PARTIAL_SUFFIX,
    Checkpoint,
    Checkpointer,
    load_checkpoint,
    partial_dir,
    state_template,
)
from .config import (
    RUN_FORMAT,
    check_data_unchanged,
    load_run_tree,
    read_true_params,
    sampler_settings,
)
from .folder import _run_summary, save_run
from .provenance import config_hash, tree_to_dict_json


def _grasp_fractions(o: dict, tree: Tree, trajectories):
    """The run's --grasp-fraction, else each trajectory's own from its data folder's pulls.yaml
    (one fraction per trajectory), else None (the tree's grasp point)."""
    if o.get("grasp_fraction") is not None or not o.get("data"):
        return o.get("grasp_fraction")
    if isinstance(trajectories, Observations):
        return None
    from ..pulls import data_grasp_fractions

    own = data_grasp_fractions(o["data"], tree, [t.source for t in trajectories])
    if own is None:
        return None
    return float(own[0]) if np.allclose(own, own[0]) else [float(g) for g in own]


def build_problem(
    config: dict,
    tree: Tree,
    trajectories: Sequence[Trajectory] | Observations,
    cache: SimulatorCache | None = None,
):
    """The inference problem of a run config (the cached simulator; a jitted log-density)."""
    from ..inference import make_problem

    o = config["options"]
    obs = (
        trajectories
        if isinstance(trajectories, Observations)
        else stack_trajectories(list(trajectories))
    )
    recorded = config.get("problem") or {}  # a resumed run: the settings it was built with
    # runs from before force interpolation existed held the force over each sample
    interp = recorded.get("force_interp", o.get("force_interp", "hold" if recorded else "linear"))
    sim = simulator_for(
        tree,
        float(obs.dt),
        recorded.get("substeps"),
        recorded.get("backend", o.get("backend", "auto")),
        cache,
        force_interp=interp,
        max_sim_dt=o.get("max_sim_dt"),
        sim_tolerance=o.get("sim_tolerance"),
        forces=np.asarray(obs.force),
        grasp_fraction=o.get("grasp_fraction"),
    )
    if recorded.get("sim_step"):  # a resumed run: how its step was chosen, as recorded
        sim = dataclasses.replace(sim, step_info=dict(recorded["sim_step"]))
    kind = o.get("model_kind", "dynamic")
    # each recording's own branch, grasp point and direction (the data folder's pulls.yaml)
    from ..static import model_for, model_with_pulls

    table = not isinstance(trajectories, Observations)
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
    problem = make_problem(
        tree,
        obs,
        kT=o["kT"],
        nn_prior=sampler_spec(o["sampler"]).nn_prior,
        eta=o["eta"],
        prior_sigma=o.get("prior_tail", DEFAULT_PRIOR_SIGMA),
        grasp_fraction=grasp,
        sim=sim,
        gradient=o.get("gradients", "fd"),
        likelihood=o.get("likelihood", "boltzmann"),  # run folders older than issue 11
        noise_displacement=o.get("noise_displacement"),
        model_kind=kind,
        **pulls,
    )
    if o.get("prior_from"):  # the earlier run's posterior as the prior of the shared joints
        from ..sequential import prior_from_run, with_prior

        prior = prior_from_run(o["prior_from"], problem.labels)
        problem = with_prior(problem, prior.log_density)
        settings = {**problem.settings, "prior_from": {"run": o["prior_from"], **prior.to_dict()}}
        problem = dataclasses.replace(problem, settings=settings)
    # infer() evaluates log_density once at the end: jitted, the simulator is traced and compiled once
    # (op-by-op it costs tens of seconds); MH samples with the same function.
    return dataclasses.replace(problem, log_density=jax.jit(problem.log_density))


# ==== inference ===================================================================================
class InferOutcome(NamedTuple):
    """What :func:`run_inference` produced: the run folder, its config and summary, the posterior."""

    run_dir: Path
    config: dict
    summary: dict
    posterior: Any


def _inputs(config: dict) -> list[str]:
    """The run's input paths, which ``--force`` must never replace."""
    o = config["options"]
    return [p for p in (o.get("tree"), o.get("data")) if p]


def _data_checks(
    config: dict, tree: Tree, trajs, log: Callable[[str], None], allow_implausible_data: bool
) -> list[str]:
    """Plausibility checks before sampling (:mod:`treeinfer.checks`): errors stop the run unless
    ``allow_implausible_data``; warnings are logged, and so are entries of the data folder that
    are not read (FIFOs, broken links, ``.CSV``). Returns every finding as text (summary.json)."""
    from ..checks import format_findings, preflight
    from ..safe_load import list_data_files

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
    from ..pulls import PULLS_FILE, load_data_pulls

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


def _prepare_fresh(config: dict, log: Callable[[str], None]):
    from ..integrity import check_partial

    run_dir = Path(config["options"]["out"])
    partial = partial_dir(run_dir)
    force = config["options"]["force"]
    check_output_dir(run_dir, force, "run", inputs=_inputs(config))
    clean_stale_staging(run_dir, log)
    if partial.exists():
        if not force:
            why = check_partial(partial)
            if why is not None:
                raise OutputExistsError(f"{partial}: an interrupted run is there but {why}")
            raise OutputExistsError(
                f"{partial}: an interrupted run is waiting there; continue it with "
                f"`treeinfer infer --resume {run_dir}`, or pass --force to discard it and start over"
            )
        shutil.rmtree(partial)
    from ..static import run_tree

    o = config["options"]
    tree = run_tree(
        load_run_tree(o["tree"], o.get("model"), o.get("repair_inertia")), o.get("model_kind")
    )
    trajs = read_trajectory_dir(config["options"]["data"])
    truth = read_true_params(tree, config["options"]["data"])
    return run_dir, partial, tree, trajs, truth


def _resume_paths(run_arg: str | os.PathLike) -> tuple[Path, Path]:
    p = Path(run_arg)
    if p.name.endswith(PARTIAL_SUFFIX):
        p = p.with_name(p.name[: -len(PARTIAL_SUFFIX)])
    partial = partial_dir(p)
    if not partial.is_dir():
        if (p / "config.json").is_file():
            raise ConfigError(f"{p}: this run is already complete; there is nothing to resume")
        raise ConfigError(
            f"{partial}: no interrupted run to resume (an interrupted `treeinfer infer --out {p}` "
            f"leaves its checkpoint in {partial.name}/)"
        )
    from ..integrity import check_partial

    why = check_partial(partial)
    if why is not None:
        raise ConfigError(f"{partial}: not resumable: {why}")
    return p, partial


# The Gaussian (Gauss-Newton) Laplace approximation is narrower than the NNSVGD posterior of the
# Boltzmann loss (a sum of norms: its density is cone-shaped, not Gaussian, where the residuals
# are small): on the standard problem, Laplace draws widened 2x give a predictive band within 10%
# of a 400-iteration NNSVGD reference (benchmarks/time_to_posterior.py, BENCHMARKS.md).
LAPLACE_SCALE = 2.0


def _laplace_start(problem, config: dict, log: Callable[[str], None]):
    """Particles around a Levenberg–Marquardt MAP fit (``--init laplace``): its Laplace
    approximation, drawn with the run's seed. The residual Jacobian follows ``--gradients``."""
    from ..mapfit import fit_problem, laplace_particles

    o = config["options"]
    if getattr(problem, "model", None) is not None:
        raise ConfigError(
            "--init laplace: supported for the dynamic model of Kp and Kd only; use --init "
            "uniform with --model-kind static or inference.parameters: [kp]"
        )
    jacobian = "jvp" if o.get("gradients", "fd") == "jvp" else "fd"
    fit = fit_problem(
        problem, "boltzmann", n_starts=6, seed=o["seed"], jacobian=jacobian, max_iterations=25
    )
    std = np.sqrt(np.diag(fit.cov))
    log(
        f"Laplace start: MAP from {len(fit.starts)} starts in {fit.iterations} LM iterations, "
        "log-gain std " + ", ".join(f"{x:.3g}" for x in std)
    )
    return laplace_particles(
        jax.random.fold_in(jax.random.key(o["seed"]), 0x1A9),
        fit,
        o["particles"],
        scale=LAPLACE_SCALE,
    )


def run_inference(
    config: dict | None = None,
    *,
    resume: str | os.PathLike | None = None,
    max_unstable_share: float | None = None,
    progress: bool = True,
    log: Callable[[str], None] = lambda msg: None,
    on_checkpointer: Callable[[Checkpointer], None] | None = None,
    cache: SimulatorCache | None = None,
    allow_implausible_data: bool = False,
) -> InferOutcome:
    """Sample a posterior and write the run folder; or continue an interrupted one (``resume``).

    Args:
      config: from :func:`infer_config` (a new run), or None with ``resume=RUN``.
      resume: a run folder whose ``RUN.partial/`` holds an interrupted run.
      max_unstable_share: override the config's limit on unstable final particles (resume).
      progress: tqdm bar. log: one-line status messages (stderr in the CLI).
      on_checkpointer: called with the :class:`Checkpointer` before sampling starts (the CLI
        keeps it to say where a Ctrl-C left the run).
      cache: the command's :class:`SimulatorCache` (a new one if None).
      allow_implausible_data: sample even if the plausibility checks (:mod:`treeinfer.checks`)
        find errors in the data (they are logged and recorded in summary.json).

    The summary's ``fit`` (``status`` ok | warning | poor_fit, ``reasons``, ``measures``) judges
    the training fit (:func:`treeinfer.checks.fit_verdict_from_run`); the CLI exits 4 on
    ``poor_fit`` unless ``--allow-poor-fit``.

    Raises:
      SimulationError: more than ``max_unstable_share`` of the final particles are unstable
        (``RUN.partial/`` is kept: resume with a larger ``max_unstable_share`` to write it anyway).
    """
    from ..inference import infer, initial_particles

    cache = SimulatorCache() if cache is None else cache
    if resume is None:
        if config is None:
            raise ConfigError("run_inference: give a config (new run) or resume=RUN")
        run_dir, partial, tree, trajs, truth = _prepare_fresh(config, log)
        data_findings = _data_checks(config, tree, trajs, log, allow_implausible_data)
        problem = build_problem(config, tree, trajs, cache)
        _quasi_static_check(problem, config, log)
        if problem.noise is not None:
            log(f"likelihood: {problem.noise.description}")
        config = {**config, "problem": problem.settings, "sampler": sampler_settings(config)}
        config["config_hash"] = config_hash(config)
        partial.mkdir(parents=True)
        try:
            dump_tree(tree, partial / "tree.yaml")
            write_json(partial / "config.json", config)  # written last: it marks a resumable run
        except BaseException:  # e.g. a full disk: leave no RUN.partial that cannot be resumed
            shutil.rmtree(partial, ignore_errors=True)
            raise
        previous = None
    else:
        from ..integrity import validate_run_config

        run_dir, partial = _resume_paths(resume)
        config = read_json(partial / "config.json", "the interrupted run's config")
        if config.get("format") != RUN_FORMAT or "config_hash" not in config:
            raise ConfigError(
                f"{partial / 'config.json'}: not a treeinfer run config (format {config.get('format')!r})"
            )
        validate_run_config(config, partial / "config.json", resumable=True)
        if config_hash(config) != config["config_hash"]:
            raise ConfigError(
                f"{partial / 'config.json'}: was edited (its hash no longer matches); start a new run"
            )
        check_output_dir(run_dir, config["options"]["force"], "run", inputs=_inputs(config))
        clean_stale_staging(run_dir, log)
        for stale in partial.glob(".*.tmp"):  # a temporary file of a write cut short by a kill
            stale.unlink(missing_ok=True)
        tree = load_tree(partial / "tree.yaml")
        if tree_to_dict_json(tree_to_dict(tree)) != tree_to_dict_json(config["tree_dict"]):
            raise ConfigError(
                f"{partial / 'tree.yaml'}: differs from the tree in config.json (edited?); start a new run"
            )
        trajs = check_data_unchanged(config)
        truth = read_true_params(tree, config["data"]["dir"])
        data_findings = _data_checks(config, tree, trajs, log, allow_implausible_data)
        problem = build_problem(config, tree, trajs, cache)
        # sim_step says how the step was chosen (the rebuilt simulator takes the recorded one);
        # runs recorded before force interpolation existed rebuild with "hold" (build_problem)
        now = {k: v for k, v in problem.settings.items() if k != "sim_step"}
        then = {k: v for k, v in config["problem"].items() if k != "sim_step"}
        if "force_interp" not in then and now.get("force_interp") == "hold":
            now.pop("force_interp")
        if _jsonable(now) != _jsonable(then) or sampler_settings(config) != config["sampler"]:
            raise ConfigError(
                f"{partial}: this treeinfer derives other problem or sampler settings from the run's "
                f"options than the interrupted run did (recorded {config['problem']}, now {problem.settings}); "
                "it cannot continue it exactly: start a new run"
            )
        previous = None
        if (partial / CHECKPOINT_FILE).is_file():
            o = config["options"]
            theta0 = initial_particles(problem, o["particles"], o["seed"])
            template = state_template(problem, o["sampler"], theta0, **config["sampler"]["options"])
            previous = load_checkpoint(partial / CHECKPOINT_FILE, template, config["config_hash"])
            log(f"resuming {run_dir} from iteration {previous.iteration} of {o['iterations']}")
        else:
            log(f"{partial} has no checkpoint yet: starting {run_dir} again from iteration 0")
    if max_unstable_share is not None:
        config["options"]["max_unstable_share"] = float(max_unstable_share)

    o = config["options"]
    theta0 = None
    if previous is None and o.get("init", "uniform") == "laplace":
        theta0 = _laplace_start(problem, config, log)
    every = o["checkpoint_every"] or None
    checkpointer = Checkpointer(partial / CHECKPOINT_FILE, config["config_hash"], previous)
    if on_checkpointer is not None:
        on_checkpointer(checkpointer)
    posterior = infer(
        problem,
        o["sampler"],
        n_particles=o["particles"],
        n_iterations=o["iterations"],
        seed=o["seed"],
        progress=progress,
        callback=checkpointer if every else None,
        callback_every=every,
        initial_state=None if previous is None else previous.state,
        start_iteration=0 if previous is None else previous.iteration,
        **_convergence_options(o, problem),
        **({} if theta0 is None else {"initial_theta": theta0}),
    )
    done = int(posterior.run.settings.get("n_iterations_done", o["iterations"]))
    if checkpointer.last_iteration != done:
        # the end state too: if anything below fails (or is interrupted), --resume skips sampling
        checkpointer(done, posterior.run.final_state)

    trace = _merged_trace(posterior.run, previous)
    posterior = _summarised_posterior(posterior, problem, trace, o)
    fit = _training_fit(problem, posterior, config)
    from ..sim import check_stable_share

    try:
        check_stable_share(
            fit["stable"], o["max_unstable_share"], f"the {o['particles']} final particles"
        )
    except SimulationError as e:
        raise SimulationError(
            f"{e} (the limit is --max-unstable-share). The sampler state is kept in {partial}: "
            f"`treeinfer infer --resume {run_dir} --max-unstable-share X` writes the run anyway"
        ) from None
    summary = _run_summary(problem, posterior, config, trace, fit, truth)
    from ..checks import fit_verdict_from_run

    verdict = fit_verdict_from_run(problem, posterior, fit, noise_sigma=_fitted_noise(problem))
    summary["fit"] = verdict.as_dict()
    summary["status"] = verdict.status
    summary["data_checks"] = data_findings
    config = {
        **config,
        "posterior_settings": posterior.settings,
        "finished_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    save_run(
        run_dir,
        tree=tree,
        config=config,
        posterior=posterior,
        problem=problem,
        trace=trace,
        fit=fit,
        summary=summary,
        truth=truth,
        force=o["force"],
        inputs=_inputs(config),
        log=log,
    )
    shutil.rmtree(partial, ignore_errors=True)
    return InferOutcome(run_dir, config, summary, posterior)


def _quasi_static_check(problem, config: dict, log: Callable[[str], None]) -> None:
    """Log :func:`treeinfer.static.quasi_static_notice` when the dynamic model is asked to fit
    data sampled far more slowly than the branch's slowest natural period."""
    if config["options"].get("model_kind", "dynamic") != "dynamic":
        return
    from ..static import quasi_static_notice

    try:
        notice = quasi_static_notice(problem.tree, problem.sim, float(problem.obs.dt))
    except Exception as e:  # noqa: BLE001 - a notice must never stop a run
        log(f"note: could not judge whether the data are quasi-static ({type(e).__name__}: {e})")
        return
    if notice:
        log(f"note: {notice}")


def _fitted_noise(problem) -> float | None:
    """The displacement noise sigma (m) the noise model fitted, if it has one (settings key
    ``noise_sigma``); None otherwise (then the fit verdict skips the residual test)."""
    v = (getattr(problem, "settings", None) or {}).get("noise_sigma")
    try:
        return float(v) if v is not None else None
    except (TypeError, ValueError):
        return None


def _convergence_options(o: dict, problem) -> dict:
    """``stop_when`` / ``reinit_stragglers`` for :func:`~treeinfer.inference.infer` from a run's
    options (issue 11: --stop-when-converged, --reinit-stragglers N)."""
    from ..diagnostics import ConvergenceCriterion, ReinitStragglers

    out = {}
    if o.get("stop_when_converged"):
        out["stop_when"] = ConvergenceCriterion()
    if o.get("reinit_stragglers", 0) > 0:
        out["reinit_stragglers"] = ReinitStragglers(
            int(o["reinit_stragglers"]), problem.lower, problem.upper
        )
    return out


MAX_MCMC_DRAWS = 1024  # --mcmc-thin 0: thin the post-warm-up draws to at most this many


def _summarised_posterior(posterior, problem, trace: dict, o: dict):
    """The particles the run's summaries describe (summary.json, particles.csv, the fit).

    MCMC samplers: every chain's post-warm-up trace (``--mcmc-warmup``), thinned
    (``--mcmc-thin``; 0: to at most MAX_MCMC_DRAWS draws), not only the final states.
    ``--drop-stragglers``: stuck final particles (SVGD) are left out. The sampler's own
    final state stays in ``posterior.run``."""
    from ..diagnostics import find_stragglers, mcmc_draws
    from ..likelihood import gains_from_theta

    theta, logp, extra = posterior.theta, posterior.log_density, {}
    pos, ld = np.asarray(trace["positions"]), np.asarray(trace["log_density"])
    if sampler_spec(o["sampler"]).family == "mcmc" and len(pos) >= 2:
        warm = math.floor(o.get("mcmc_warmup", 0.5) * len(pos))
        thin = int(o.get("mcmc_thin", 0))
        if thin == 0:
            thin = max(1, math.ceil((len(pos) - warm) * pos.shape[1] / MAX_MCMC_DRAWS))
        theta, logp = mcmc_draws(pos, warm, thin, log_density=ld)
        extra = {"mcmc_draws": {"warmup": warm, "thin": thin, "n_draws": int(len(theta))}}
    elif o.get("drop_stragglers"):
        rep = find_stragglers(logp, theta, problem.lower, problem.upper)
        if 0 < rep.n_stragglers < len(theta) - 1:
            theta, logp = theta[~rep.mask], logp[~rep.mask]
            extra = {"dropped_stragglers": True, "n_dropped": rep.n_stragglers}
    if not extra:
        return posterior
    if getattr(problem, "model", None) is not None:
        kp, kd = problem.model.layout.gains(np.asarray(theta))
    else:
        kp, kd = gains_from_theta(theta, problem.sim.n_joints)
    return dataclasses.replace(
        posterior,
        theta=np.asarray(theta),
        kp=np.asarray(kp),
        kd=np.asarray(kd),
        log_density=np.asarray(logp),
        settings={**posterior.settings, **extra},
    )


def infer_posterior(
    config: dict,
    tree: Tree,
    trajectories,
    progress: bool = True,
    cache: SimulatorCache | None = None,
):
    """(problem, posterior) for ``config``'s settings on ``trajectories`` (no run folder): the
    k-fold protocol reuses a run's settings this way."""
    from ..inference import infer

    problem = build_problem(config, tree, trajectories, cache)
    o = config["options"]
    theta0 = None
    if o.get("init", "uniform") == "laplace":
        theta0 = _laplace_start(problem, config, lambda msg: None)
    posterior = infer(
        problem,
        o["sampler"],
        n_particles=o["particles"],
        n_iterations=o["iterations"],
        seed=o["seed"],
        progress=progress,
        **({} if theta0 is None else {"initial_theta": theta0}),
    )
    return problem, posterior


def _merged_trace(run, previous: Checkpoint | None) -> dict:
    """Trace of the whole run: the driver's, preceded on a resumed run by the checkpoints' coarse one."""
    pos, ld, it = run.trace_positions, run.trace_logdensity, run.trace_iterations
    if previous is not None and len(previous.trace_iterations):
        keep = previous.trace_iterations <= previous.iteration
        pos = np.concatenate([previous.trace_positions[keep], pos])
        ld = np.concatenate([previous.trace_logdensity[keep], ld])
        it = np.concatenate([previous.trace_iterations[keep], it])
    first = run.settings["start_iteration"]
    diag = {k: np.asarray(v) for k, v in run.diagnostics.items()}
    n_diag = len(next(iter(diag.values()))) if diag else 0
    return {
        "positions": np.asarray(pos),
        "log_density": np.asarray(ld),
        "iterations": np.asarray(it, np.int64),
        "diagnostics": diag,
        "diag_iterations": np.arange(first + 1, first + 1 + n_diag, dtype=np.int64),
        "resumed_from": None if previous is None else int(previous.iteration),
        "elapsed_s": float(run.elapsed_s),
    }


class FoldResult(NamedTuple):
    fold: int
    train: list[str]
    test: list[str]
    metrics: dict
    theta: np.ndarray
    prediction: Prediction


def kfold(
    config: dict,
    tree: Tree,
    trajectories: Sequence[Trajectory],
    k: int,
    grasp_fraction=None,
    truth=None,
    progress: bool = True,
    log: Callable[[str], None] = lambda m: None,
    cache: SimulatorCache | None = None,
    data_dir: str | os.PathLike | None = None,
) -> list[FoldResult]:
    """The paper's real-to-sim protocol: for each of ``k`` folds, infer on the other folds with
    ``config``'s sampler settings and evaluate on the held-out fold.

    ``grasp_fraction``: None, one fraction, or one per trajectory (split with the folds).
    ``data_dir``: the trajectories' folder (its ``pulls.yaml``; default the run's data)."""
    trajectories = list(trajectories)
    cache = SimulatorCache() if cache is None else cache  # every fold: one simulator
    splits = kfold_splits(len(trajectories), k)
    options = {**config["options"], **({} if data_dir is None else {"data": str(data_dir)})}
    per_traj = grasp_fraction is not None and np.ndim(grasp_fraction) == 1
    out = []
    for i, (tr, te) in enumerate(splits, start=1):
        train = [trajectories[j] for j in tr]
        test = [trajectories[j] for j in te]
        log(
            f"fold {i}/{k}: inferring on {len(train)} trajectories, holding out {', '.join(t.source for t in test)}"
        )
        g_train = [float(np.asarray(grasp_fraction)[j]) for j in tr] if per_traj else grasp_fraction
        g_test = np.asarray(grasp_fraction, float)[te] if per_traj else grasp_fraction
        cfg = {**config, "options": {**options, "grasp_fraction": g_train}}
        problem, post = infer_posterior(cfg, tree, train, progress, cache)
        from ..static import model_with_pulls

        model, g_test = model_with_pulls(  # the held-out recordings' own pulls
            problem.model, options.get("data"), [t.source for t in test], g_test, tree=tree
        )
        m, pred, _ = evaluate_trajectories(
            problem.sim,
            post.theta,
            list(problem.labels),
            test,
            problem.kT,
            g_test,
            truth,
            np.isfinite(post.log_density),
            *noise_for(post.theta, problem.sim.n_joints, problem.settings),
            model=model,
        )
        out.append(
            FoldResult(
                i,
                [t.source for t in train],
                [t.source for t in test],
                m,
                np.asarray(post.theta),
                pred,
            )
        )
    return out
