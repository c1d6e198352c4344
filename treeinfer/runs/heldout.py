"""A finished run scored on held-out recordings: the non-k-fold path of ``treeinfer evaluate``
as one library call (``treeinfer batch`` uses it for the coverage column of its table)."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from ..data.pulls import data_grasp_fractions
from ..data.trajectories import read_trajectory_dir
from ..errors import ConfigError
from ..evaluation.predictive import evaluate_trajectories, force_noise_for, noise_for
from .config import read_true_params
from .folder import LoadedRun


def held_out_metrics(run: LoadedRun, data_dir: str | os.PathLike) -> dict:
    """Metrics (:func:`treeinfer.evaluation.predictive.evaluate_trajectories`: ``pct_outside``
    of the 95% predictive band, ``ci_width`` in m, ``predictive_nll_per_point``, ``n_points``,
    ...) of ``run``'s posterior on the recordings of ``data_dir``, each predicted at its own
    grasp point (the folder's ``pulls.yaml``) or else at the run's; with the run's recorded
    simulator. ConfigError if the recordings' time step is not the run's."""
    from ..inference.static import model_with_pulls

    data_dir = Path(data_dir)
    trajs = read_trajectory_dir(data_dir)
    dt = trajs[0].dt
    if not math.isclose(dt, run.sim.obs_dt, rel_tol=1e-6):
        raise ConfigError(
            f"{data_dir}: trajectories have dt={dt:g} s but run {run.path} was inferred at "
            f"dt={run.sim.obs_dt:g} s; resample them to the run's step"
        )
    sources = [t.source for t in trajs]
    grasp = run.grasp_fraction
    own = data_grasp_fractions(data_dir, run.tree, sources, True, True)
    if own is not None:  # each recording at its own grasp point
        grasp = own
    model, grasp = model_with_pulls(run.model, data_dir, sources, grasp, tree=run.tree)
    sigma, kind = noise_for(run.theta, run.sim.n_joints, run.config.get("problem"))
    metrics, _, _ = evaluate_trajectories(
        run.sim,
        run.theta,
        list(run.labels),
        trajs,
        run.kT,
        grasp,
        read_true_params(run.tree, data_dir),
        np.asarray(run.stable),
        noise_sigma=sigma,
        noise_kind=kind,
        model=model,
        force_noise=force_noise_for(run.config.get("problem")),
    )
    return metrics
