"""The run service: sample a posterior and write the run folder, resume an interrupted run,
cross-validate a run's settings (k-fold). Uses the command's cache (simulators and compiled
sampler programs, :class:`~treeinfer.runs.cache.SimulatorCache`), or makes one per call.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from ..errors import ConfigError, OutputExistsError, SimulationError
from ..evaluation.training_fit import _training_fit
from ..io.atomic import check_output_dir, clean_stale_staging
from ..io.jsonio import jsonable as _jsonable
from ..io.jsonio import read_json, write_json
from ..io.ownership import move_aside
from ..io.provenance import config_hash, tree_to_dict_json
from ..tree.description import Tree, dump_tree, load_tree, tree_to_dict
from .cache import SimulatorCache
from .checkpoint import (
    CHECKPOINT_FILE,
    PARTIAL_SUFFIX,
    Checkpointer,
    load_checkpoint,
    partial_dir,
    state_template,
)
from .config import (
    RUN_FORMAT,
    RunConfig,
    RunInputs,
    check_data_unchanged,
    load_run_inputs,
    read_true_params,
    sampler_settings,
)
from .folder import _run_summary, save_run
from .posterior import (  # noqa: F401 -- re-exported: the old import path keeps working
    MAX_MCMC_DRAWS,
    _merged_trace,
    _summarised_posterior,
)
from .problem import (  # noqa: F401 -- re-exported: the old import path keeps working
    _data_checks,
    _quasi_static_check,
    build_problem,
)
from .start import (  # noqa: F401
    LAPLACE_LM_ITERATIONS,
    LAPLACE_SCALE,
    _check_init,
    _start,
    held_evaluator,
)

# ==== inference ===================================================================================
# --init values whose particles start near the posterior, and the convergence stop they use
FITTED_STARTS = ("auto", "importance", "laplace")
FITTED_CONVERGENCE = {"min_iterations": 20, "window": 10}


class InferOutcome(NamedTuple):
    """What :func:`run_inference` produced.

    The run folder, its config and summary, the posterior."""

    run_dir: Path
    config: dict
    summary: dict
    posterior: Any


def _inputs(config: dict) -> list[str]:
    """The run's input paths, which ``--force`` must never replace."""
    o = config["options"]
    return [p for p in (o.get("tree"), o.get("data"), o.get("model"), o.get("prior_from")) if p]


def _prepare_fresh(config: dict, inputs: RunInputs | None, log: Callable[[str], None]):
    """The run folder, its staging folder and the run's inputs (``inputs`` if given: the ones
    :func:`~.config.infer_config` hashed, else read now)."""
    from .integrity import check_partial

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
                f"{partial}: an interrupted run is waiting there; continue it with `treeinfer "
                f"infer --resume {run_dir}`, or pass --force to discard it and start over"
            )
        move_aside(partial, log, "interrupted run")
    o = config["options"]
    if inputs is None:
        inputs = load_run_inputs(
            o["tree"],
            o["data"],
            o.get("model"),
            o.get("repair_inertia"),
            o.get("model_kind"),
            o.get("tie"),
            o.get("tie_scale"),
        )
    elif tree_to_dict_json(tree_to_dict(inputs.tree)) != tree_to_dict_json(config["tree_dict"]):
        raise ConfigError(
            "run_inference: the inputs' tree is not the config's (pass the RunInputs given to "
            "infer_config)"
        )
    elif [f["name"] for f in inputs.files] != [f["name"] for f in config["data"]["files"]]:
        raise ConfigError(
            "run_inference: the inputs' data files are not the config's (pass the RunInputs "
            "given to infer_config)"
        )
    return run_dir, partial, inputs.tree, list(inputs.trajectories), inputs.truth


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
    from .integrity import check_partial

    why = check_partial(partial)
    if why is not None:
        raise ConfigError(f"{partial}: not resumable: {why}")
    return p, partial


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
    inputs: RunInputs | None = None,
    amortised: tuple[Callable, dict] | None = None,
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
      allow_implausible_data: sample even if the plausibility checks
      (:mod:`treeinfer.evaluation.checks`)
        find errors in the data (they are logged and recorded in summary.json).
      inputs: the tree and data :func:`~.config.infer_config` was given (a new run; read again
        from the config's paths if None).
      amortised: ``(start, report)`` of :func:`treeinfer.amortised.amortised_start` (``infer
        --amortised``, a new run): ``start(problem, config, log)`` is tried before the start
        pipeline and its checked posterior used if it gives one; else the run goes on as
        without it. ``report`` (filled by ``start``) is summary.json's ``amortised``.

    The summary's ``fit`` (``status`` ok | warning | poor_fit, ``reasons``, ``measures``) judges
    the training fit (:func:`treeinfer.evaluation.checks.fit_verdict_from_run`); the CLI exits 4 on
    ``poor_fit`` unless ``--allow-poor-fit``.

    Raises:
      SimulationError: more than ``max_unstable_share`` of the final particles are unstable
        (``RUN.partial/`` is kept: resume with a larger ``max_unstable_share`` to write it anyway).
    """
    from ..inference.problem import initial_particles

    cache = SimulatorCache() if cache is None else cache
    if resume is None:
        if config is None:
            raise ConfigError("run_inference: give a config (new run) or resume=RUN")
        cfg = RunConfig.from_json(config)  # the given config.json, validated once
        config = cfg.to_json()
        run_dir, partial, tree, trajs, truth = _prepare_fresh(config, inputs, log)
        data_findings = _data_checks(config, tree, trajs, log, allow_implausible_data)
        problem = build_problem(config, tree, trajs, cache, log=log)
        _quasi_static_check(problem, config, log)
        _check_init(problem, config["options"])
        if problem.noise is not None:
            log(f"likelihood: {problem.noise.description}")
        # --init laplace/importance: drawn before the sampler is recorded (MH's proposal)
        ready_start = None if amortised is None else amortised[0](problem, config, log)
        if ready_start is not None:
            start = None
        else:
            if amortised is not None:
                log(f"amortised posterior not used ({amortised[1].get('reason')}): falling back "
                    "to the simulator-based path")  # fmt: skip
            ready_start, start = _start(problem, config, log, programs=cache.programs)
        cfg = dataclasses.replace(
            cfg, problem=problem.settings, sampler_record=sampler_settings(config, start)
        )
        cfg = dataclasses.replace(cfg, config_hash=config_hash(cfg.to_json()))
        config = cfg.to_json()
        partial.mkdir(parents=True)
        try:
            dump_tree(tree, partial / "tree.yaml")
            write_json(partial / "config.json", config)  # written last: it marks a resumable run
        except BaseException:  # e.g. a full disk: leave no RUN.partial that cannot be resumed
            shutil.rmtree(partial, ignore_errors=True)
            raise
        previous = None
    else:
        from .integrity import validate_run_config

        run_dir, partial = _resume_paths(resume)
        config = read_json(partial / "config.json", "the interrupted run's config")
        if config.get("format") != RUN_FORMAT or "config_hash" not in config:
            raise ConfigError(
                f"{partial / 'config.json'}: not a treeinfer run config (format "
                f"{config.get('format')!r})"
            )
        validate_run_config(config, partial / "config.json", resumable=True)
        RunConfig.from_json(config)  # its options, validated as a new run's are
        if config_hash(config) != config["config_hash"]:
            raise ConfigError(
                f"{partial / 'config.json'}: was edited (its hash no longer matches); start a "
                "new run"
            )
        check_output_dir(run_dir, config["options"]["force"], "run", inputs=_inputs(config))
        clean_stale_staging(run_dir, log)
        for stale in partial.glob(".*.tmp"):  # a temporary file of a write cut short by a kill
            stale.unlink(missing_ok=True)
        tree = load_tree(partial / "tree.yaml")
        if tree_to_dict_json(tree_to_dict(tree)) != tree_to_dict_json(config["tree_dict"]):
            raise ConfigError(
                f"{partial / 'tree.yaml'}: differs from the tree in config.json (edited?); start "
                "a new run"
            )
        trajs = check_data_unchanged(config)
        truth = read_true_params(tree, config["data"]["dir"])
        data_findings = _data_checks(config, tree, trajs, log, allow_implausible_data)
        problem = build_problem(config, tree, trajs, cache, resumed=True)
        # sim_step says how the step was chosen (the rebuilt simulator takes the recorded one);
        # runs recorded before force interpolation existed rebuild with "hold" (build_problem)
        now = {k: v for k, v in problem.settings.items() if k != "sim_step"}
        then = {k: v for k, v in config["problem"].items() if k != "sim_step"}
        if "force_interp" not in then and now.get("force_interp") == "hold":
            now.pop("force_interp")
        if _jsonable(now) != _jsonable(then) or sampler_settings(config) != config["sampler"]:
            raise ConfigError(
                f"{partial}: this treeinfer derives other problem or sampler settings from the "
                f"run's options than the interrupted run did (recorded {config['problem']}, now "
                f"{problem.settings}); it cannot continue it exactly: start a new run"
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
    if resume is None:
        ready, theta0 = ready_start, start
    else:
        ready, theta0 = None, None
    if previous is None and ready is None and theta0 is None:
        # a resumed run that stopped before its first checkpoint: draw its start again
        ready, theta0 = _start(problem, config, log, programs=cache.programs)
    if ready is not None:  # --init importance: the weighted draws are the posterior
        posterior = ready
    else:
        posterior = _sample(
            problem, config, partial, previous, theta0, progress, cache, on_checkpointer
        )

    trace = _merged_trace(posterior.run, previous)
    posterior = _summarised_posterior(posterior, problem, trace, o)
    # the start pipeline's compiled rollout program simulates the particles, where it ran
    fit = _training_fit(problem, posterior, config, held_evaluator(problem, posterior, cache))
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
    formats = tuple(config.get("figure_formats") or ("png",))  # infer --formats
    # the figures are drawn on a second thread while the summary and verdict are computed
    figures = _run_figures(problem, posterior, config, trace, fit, truth, formats)
    summary = _run_summary(problem, posterior, config, trace, fit, truth)
    if ready is not None:
        _importance_diagnostics(summary, posterior)
    if amortised is not None and resume is None:
        summary["amortised"] = {**amortised[1], "fallback": not amortised[1].get("used")}
    from ..evaluation.checks import fit_verdict_from_run

    verdict = fit_verdict_from_run(problem, posterior, fit, noise_sigma=_fitted_noise(problem))
    if fit.get("prediction") is not None:  # observation channels: their own checks and bands
        from ..evaluation.channel_checks import channel_verdict

        verdict, fit["channel_bands"] = channel_verdict(
            verdict, problem, posterior, fit["stable"], trajs
        )
    summary["fit"] = verdict.as_dict()
    summary["status"] = verdict.status
    summary["data_checks"] = data_findings
    prior_notes = (problem.settings.get("prior_from") or {}).get("integrity_notes")
    if prior_notes:  # infer --prior-from RUN --allow-modified: what changed in RUN
        summary["integrity_notes"] = list(prior_notes)
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
        formats=formats,
        figures=figures,
    )
    shutil.rmtree(partial, ignore_errors=True)
    return InferOutcome(run_dir, config, summary, posterior)


def _run_figures(problem, posterior, config: dict, trace: dict, fit: dict, truth, formats):
    """:class:`~.figures.RunFigures` of the run (drawn on a second thread from now on)."""
    from .figures import RunFigures
    from .folder import run_bandwidths

    sampler = config["options"]["sampler"]
    return RunFigures(
        posterior, problem, trace, np.asarray(fit["stable"], bool), truth, fit,
        [f["name"] for f in config["data"]["files"]], sampler,
        bandwidth=run_bandwidths(trace, sampler), formats=formats,
    )  # fmt: skip


def _sample(problem, config, partial: Path, previous, theta0, progress, cache, on_checkpointer):
    """The sampler's run of :func:`run_inference` (from ``previous``'s checkpoint if any, else
    from ``theta0`` or the sampler's own start), checkpointing into ``partial``."""
    from ..inference.problem import infer

    o = config["options"]
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
        cache=cache.programs,
        **_convergence_options(o, problem),
        **({} if theta0 is None else {"initial_theta": theta0}),
        **_warmup_option(config),
    )
    done = int(posterior.run.settings.get("n_iterations_done", o["iterations"]))
    if checkpointer.last_iteration != done:
        # the end state too: if anything below fails (or is interrupted), --resume skips sampling
        checkpointer(done, posterior.run.final_state)
    return posterior


def _importance_diagnostics(summary: dict, posterior) -> None:
    """``--init importance`` used as the posterior: summary.json's diagnostics are the importance
    weights' (Pareto k_hat, effective sample size), not a sampler trace's (it has one state)."""
    run = posterior.run.settings
    summary["diagnostics_kind"] = "importance"
    summary["diagnostics"] = {k: run[k] for k in ("khat", "ess", "n_draws", "lm_iterations")}
    summary["convergence_warnings"] = [
        w for w in summary["convergence_warnings"] if not w.startswith("diagnostics unavailable")
    ]


def _fitted_noise(problem) -> float | None:
    """The displacement noise sigma (m) the noise model fitted, if it has one (settings key
    ``noise_sigma``); None otherwise (then the fit verdict skips the residual test)."""
    v = (getattr(problem, "settings", None) or {}).get("noise_sigma")
    try:
        return float(v) if v is not None else None
    except (TypeError, ValueError):
        return None


def _warmup_option(config: dict, start=None) -> dict:
    """The recorded learning-rate warm-up (``--init laplace``/``importance`` with SVGD/NNSVGD),
    if any, and MH's Laplace-shaped proposal (recorded; or from ``start``, a k-fold refit's own
    Laplace particles)."""
    recorded = config.get("sampler", {}).get("options", {})
    w = recorded.get("warmup")
    out = {"warmup": int(w)} if w else {}
    if start is not None and config["options"].get("sampler") == "mh":
        recorded = sampler_settings(config, start)["options"]
    if isinstance(recorded.get("proposal_scale"), list):
        out["proposal_scale"] = np.asarray(recorded["proposal_scale"], float)
    return out


def _convergence_options(o: dict, problem) -> dict:
    """``stop_when`` / ``reinit_stragglers`` for :func:`~treeinfer.inference.problem.infer` from a
    run's options (issue 11: --stop-when-converged, --reinit-stragglers N)."""
    from ..inference.diagnostics import ConvergenceCriterion, ReinitStragglers

    out = {}
    if o.get("stop_when_converged"):
        fitted = o.get("init", "uniform") in FITTED_STARTS
        # particles from a fitted start are already near the posterior: the check may come
        # sooner and compare shorter windows than after a start spread over the prior box
        out["stop_when"] = ConvergenceCriterion(**(FITTED_CONVERGENCE if fitted else {}))
    if o.get("reinit_stragglers", 0) > 0:
        out["reinit_stragglers"] = ReinitStragglers(
            int(o["reinit_stragglers"]), problem.lower, problem.upper
        )
    return out


def infer_posterior(
    config: dict,
    tree: Tree,
    trajectories,
    progress: bool = True,
    cache: SimulatorCache | None = None,
    log: Callable[[str], None] = lambda msg: None,
):
    """(problem, posterior) for ``config``'s settings on ``trajectories`` (no run folder): the
    k-fold protocol reuses a run's settings this way."""
    from ..inference.problem import infer

    cache = SimulatorCache() if cache is None else cache
    problem = build_problem(config, tree, trajectories, cache, log=log)
    o = config["options"]
    ready, theta0 = _start(problem, config, log, programs=cache.programs)
    if ready is not None:
        return problem, ready
    posterior = infer(
        problem,
        o["sampler"],
        n_particles=o["particles"],
        n_iterations=o["iterations"],
        seed=o["seed"],
        progress=progress,
        cache=cache.programs,
        **_convergence_options(o, problem),
        **({} if theta0 is None else {"initial_theta": theta0}),
        **_warmup_option(config, theta0),
    )
    return problem, posterior
