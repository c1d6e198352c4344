"""The run service: sample a posterior and write the run folder, resume an interrupted run,
cross-validate a run's settings (k-fold). Owns the simulator cache of a command.
"""

from __future__ import annotations

import dataclasses
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
)
from ..errors import ConfigError, OutputExistsError, SimulationError

# ==== problem and posterior =======================================================================
from ..evaluation import Prediction, _training_fit, evaluate_trajectories, kfold_splits, noise_for
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
from .config import RUN_FORMAT, check_data_unchanged, read_true_params, sampler_settings
from .folder import _run_summary, save_run
from .provenance import config_hash, tree_to_dict_json


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
    sim = simulator_for(
        tree,
        float(obs.dt),
        recorded.get("substeps"),
        recorded.get("backend", o.get("backend", "auto")),
        cache,
    )
    problem = make_problem(
        tree,
        obs,
        kT=o["kT"],
        nn_prior=sampler_spec(o["sampler"]).nn_prior,
        eta=o["eta"],
        grasp_fraction=o["grasp_fraction"],
        sim=sim,
        likelihood=o.get("likelihood", "boltzmann"),  # run folders older than issue 11
        noise_displacement=o.get("noise_displacement"),
    )
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


def _prepare_fresh(config: dict, log: Callable[[str], None]):
    run_dir = Path(config["options"]["out"])
    partial = partial_dir(run_dir)
    force = config["options"]["force"]
    check_output_dir(run_dir, force, "run")
    if partial.exists():
        if not force:
            raise OutputExistsError(
                f"{partial}: an interrupted run is waiting there; continue it with "
                f"`treeinfer infer --resume {run_dir}`, or pass --force to discard it and start over"
            )
        shutil.rmtree(partial)
    tree = load_tree(config["options"]["tree"])
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
    if not (partial / "config.json").is_file():
        raise ConfigError(f"{partial}: has no config.json; it is not an interrupted treeinfer run")
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
        problem = build_problem(config, tree, trajs, cache)
        if problem.noise is not None:
            log(f"likelihood: {problem.noise.description}")
        config = {**config, "problem": problem.settings, "sampler": sampler_settings(config)}
        config["config_hash"] = config_hash(config)
        partial.mkdir(parents=True)
        dump_tree(tree, partial / "tree.yaml")
        write_json(partial / "config.json", config)  # written last: it marks a resumable run
        previous = None
    else:
        run_dir, partial = _resume_paths(resume)
        config = read_json(partial / "config.json", "the interrupted run's config")
        if config.get("format") != RUN_FORMAT or "config_hash" not in config:
            raise ConfigError(
                f"{partial / 'config.json'}: not a treeinfer run config (format {config.get('format')!r})"
            )
        if config_hash(config) != config["config_hash"]:
            raise ConfigError(
                f"{partial / 'config.json'}: was edited (its hash no longer matches); start a new run"
            )
        check_output_dir(run_dir, config["options"]["force"], "run")
        for stale in partial.glob(".*.tmp"):  # a temporary file of a write cut short by a kill
            stale.unlink(missing_ok=True)
        tree = load_tree(partial / "tree.yaml")
        if tree_to_dict_json(tree_to_dict(tree)) != tree_to_dict_json(config["tree_dict"]):
            raise ConfigError(
                f"{partial / 'tree.yaml'}: differs from the tree in config.json (edited?); start a new run"
            )
        trajs = check_data_unchanged(config)
        truth = read_true_params(tree, config["data"]["dir"])
        problem = build_problem(config, tree, trajs, cache)
        if (
            _jsonable(problem.settings) != _jsonable(config["problem"])
            or sampler_settings(config) != config["sampler"]
        ):
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
    )
    if checkpointer.last_iteration != o["iterations"]:
        # the end state too: if anything below fails (or is interrupted), --resume skips sampling
        checkpointer(o["iterations"], posterior.run.final_state)

    trace = _merged_trace(posterior.run, previous)
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
    )
    shutil.rmtree(partial, ignore_errors=True)
    return InferOutcome(run_dir, config, summary, posterior)


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
    posterior = infer(
        problem,
        o["sampler"],
        n_particles=o["particles"],
        n_iterations=o["iterations"],
        seed=o["seed"],
        progress=progress,
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
) -> list[FoldResult]:
    """The paper's real-to-sim protocol: for each of ``k`` folds, infer on the other folds with
    ``config``'s sampler settings and evaluate on the held-out fold."""
    trajectories = list(trajectories)
    cache = SimulatorCache() if cache is None else cache  # every fold: one simulator
    splits = kfold_splits(len(trajectories), k)
    cfg = {**config, "options": {**config["options"], "grasp_fraction": grasp_fraction}}
    out = []
    for i, (tr, te) in enumerate(splits, start=1):
        train = [trajectories[j] for j in tr]
        test = [trajectories[j] for j in te]
        log(
            f"fold {i}/{k}: inferring on {len(train)} trajectories, holding out {', '.join(t.source for t in test)}"
        )
        problem, post = infer_posterior(cfg, tree, train, progress, cache)
        m, pred, _ = evaluate_trajectories(
            problem.sim,
            post.theta,
            list(problem.labels),
            test,
            problem.kT,
            grasp_fraction,
            truth,
            np.isfinite(post.log_density),
            *noise_for(post.theta, problem.sim.n_joints, problem.settings),
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
