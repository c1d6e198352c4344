"""The paper's real-to-sim protocol (``evaluate --kfold``): infer on k-1 folds with a run's
settings, evaluate on the held-out fold, and say how each refit ended (:func:`fold_warnings`)."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np

from ..data.trajectories import Trajectory
from ..evaluation.predictive import (
    Prediction,
    evaluate_trajectories,
    force_noise_for,
    kfold_splits,
    noise_for,
)
from ..tree.description import Tree
from .cache import SimulatorCache
from .posterior import _merged_trace
from .service import infer_posterior


def fold_warnings(problem, posterior, options: dict | None = None) -> list[str]:
    """What a k-fold refit must not hide (issue 27): how it ended (importance weights or
    sampler, and why the sampler stopped), the sampler's convergence warnings (those ``infer``
    puts in summary.json; ``options``: the run's, for the sampler and its warm-up share),
    stuck particles and posterior mass at the box."""
    from .folder import _diagnostics, _straggler_and_edge

    run = posterior.run
    stop = getattr(run, "stop_reason", None) or "max_iterations"
    done = run.settings.get("n_iterations_done", run.settings.get("n_iterations"))
    out = [f"ended by: {stop}" + (f" after {done} iterations" if done else "")]
    # importance sampling and resample-move (a start pipeline's posterior, no sampler trace:
    # one state) have their own diagnostics in the stop reason, as infer's summary.json does
    if options is not None and not str(stop).startswith(("importance", "resample-move")):
        # the sampler ran: its trace's diagnostics, as a run's summary.json has them
        _, _, diag = _diagnostics(
            options["sampler"],
            _merged_trace(run, None),
            list(problem.labels),
            options.get("mcmc_warmup", 0.5),
        )
        out += diag
    strag, edge = _straggler_and_edge(problem, posterior)
    if strag.get("n_reinitialised"):
        out.append(f"{strag['n_reinitialised']} stuck particles re-initialised in the warm-up")
    return out + list(strag["warnings"]) + list(edge.get("warnings", []))


def fold_channel_metrics(problem, posterior, test, model, grasp, data_dir) -> dict:
    """The held-out fold's observation channels (the data folder's channels.yaml entries on
    its recordings) scored by the fold's posterior: ``{"channels": {name: metrics},
    "channel_pct_outside": pooled share outside the 95% band (% of samples)}``, or {} without
    any. A fold trains on its own pulls' channels (:func:`treeinfer.runs.problem.build_problem`)
    and takes each sensor's noise from them (the held-out channel's ``sensor``, else one at the
    same point)."""
    if data_dir is None:
        return {}
    from ..data.channels import read_channels
    from ..evaluation.channel_bands import channel_bands

    channels = read_channels(data_dir, problem.tree, test, only_these_pulls=True)
    if not channels:
        return {}
    g = None if grasp is None else np.atleast_1d(np.asarray(grasp, float))
    bands = channel_bands(
        problem.sim, posterior.theta, list(problem.labels), channels, test, problem.settings,
        np.isfinite(posterior.log_density), model=model, grasp_fraction=g,
    )  # fmt: skip
    per = {b.channel.name: b.metrics() for b in bands}
    n = sum(c["samples"] for c in per.values())
    pooled = sum(c["pct_outside"] * c["samples"] for c in per.values()) / max(n, 1)
    return {"channels": per, "channel_pct_outside": float(pooled)}


class FoldResult(NamedTuple):
    fold: int
    train: list[str]
    test: list[str]
    metrics: dict
    theta: np.ndarray
    prediction: Prediction
    warnings: tuple = ()  # fold_warnings: how the refit ended, stuck particles, box edges


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
            f"fold {i}/{k}: inferring on {len(train)} trajectories, holding out "
            f"{', '.join(t.source for t in test)}"
        )
        g_train = [float(np.asarray(grasp_fraction)[j]) for j in tr] if per_traj else grasp_fraction
        g_test = np.asarray(grasp_fraction, float)[te] if per_traj else grasp_fraction
        cfg = {**config, "options": {**options, "grasp_fraction": g_train}}
        problem, post = infer_posterior(cfg, tree, train, progress, cache, log)
        warns = fold_warnings(problem, post, cfg["options"])
        for w in warns:
            log(f"fold {i}/{k}: {w}")
        from ..inference.static import model_with_pulls

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
            force_noise=force_noise_for(problem.settings),
        )
        m = {**m, **fold_channel_metrics(problem, post, test, model, g_test, options.get("data"))}
        out.append(
            FoldResult(
                i,
                [t.source for t in train],
                [t.source for t in test],
                m,
                np.asarray(post.theta),
                pred,
                tuple(warns),
            )
        )
    return out
