"""The run's fit to its training data (:func:`_training_fit`): every particle simulated on the
recordings it was inferred from, the parameter and predictive bands, the metrics the fit verdict
and ``summary.json`` report. Split from :mod:`treeinfer.evaluation.predictive` (module size);
the run layer (:func:`treeinfer.runs.run_inference`) calls it once per run."""

from __future__ import annotations

import math

import numpy as np

from ..errors import SimulationError
from .predictive import (
    Prediction,
    _per_trajectory_loglik,
    force_noise_for,
    noise_for,
    predict_run,
)

__all__ = ["_training_fit"]


def _fit_bucket(problem, grasp):
    """``(observations, grasp, padded)`` the training fit runs on: padded to the run's shape
    bucket (``problem.settings["shape_bucket"]``: ``--init importance`` runs and samplers that
    take the data as an argument), so that its programs (prediction, bands, NLL, and the small
    array operations between them) have the bucket's shape and a new data set of the bucket
    reuses them; the data's own for unbucketed runs, static models and force-noise runs (whose
    band adds each point's force-induced variance, not computed for padded steps)."""
    bucket = problem.settings.get("shape_bucket")
    if (
        bucket is None
        or getattr(problem, "model", None) is not None
        or force_noise_for(problem.settings) is not None
    ):
        return problem.obs, grasp, False
    from ..sim.startup import bucket_observations

    obs = problem.obs
    padded = bucket_observations(obs, *bucket)
    if isinstance(grasp, (list, tuple)) or np.ndim(grasp) == 1:  # one per row: repeat the last
        g = np.asarray(grasp, float)
        grasp = g[np.minimum(np.arange(padded.force.shape[0]), len(g) - 1)]
    return padded, grasp, True


def _cut(pred: Prediction, rows: int, steps: int, dt: float) -> Prediction:
    """``pred`` of padded observations cut to the data's ``rows`` and ``steps``; the velocity
    at the last real sample one-sided, as an unpadded prediction has it
    (:func:`treeinfer.sim.velocity`), not the central difference the padded steps gave."""

    def cut(x):
        return None if x is None or np.ndim(x) == 0 else np.asarray(x)[..., :rows, :steps]

    tau_dot = np.array(pred.tau_dot[:, :rows, :steps])
    if steps >= 3:
        x = pred.tau[:, :rows]
        one_sided = (3.0 * x[..., steps - 1] - 4.0 * x[..., steps - 2] + x[..., steps - 3]) / (
            2.0 * dt
        )
        tau_dot[..., steps - 1] = np.where(pred.stable[:, None], one_sided, 0.0)
    return pred._replace(
        tau=cut(pred.tau),
        tau_dot=tau_dot.astype(pred.tau_dot.dtype),
        lower=cut(pred.lower),
        upper=cut(pred.upper),
        mean=cut(pred.mean),
        predictive_lower=cut(pred.predictive_lower),
        predictive_upper=cut(pred.predictive_upper),
        force_variance=cut(pred.force_variance),
    )


def _held_rollout(evaluator, problem, obs, grasp, theta):
    """The :class:`treeinfer.sim.Rollout` of ``theta`` on the training data from ``evaluator``
    (the start pipeline's :class:`~treeinfer.inference.fast_evaluator.BatchEvaluator`, whose
    program is compiled already: a prediction program of its own cost the training fit 7 of the
    default command's 100 CPU-s cold, 2 of 90 warm, BENCHMARKS.md), or None where it cannot
    stand in for :func:`treeinfer.inference.problem.predict`: other rows or steps than the data's,
    unobserved or non-finite points (the residual program knows the rollout at observed points
    only), another grasp point. Its values agree with ``predict``'s to float32 rounding (the
    traced-substeps form of the same loop, as ``predict(..., traced_substeps=True)``)."""
    from ..sim import Rollout

    if evaluator is None or obs is not problem.obs or getattr(problem, "model", None) is not None:
        return None
    mask = np.asarray(obs.mask, bool)
    data = (np.asarray(obs.displacement, float), np.asarray(obs.velocity, float))
    if not (mask.all() and all(np.isfinite(x).all() for x in data)):
        return None
    own = problem.settings.get("grasp_fraction")
    if isinstance(own, (list, tuple)) or isinstance(grasp, (list, tuple)) or np.ndim(grasp):
        return None
    same = (grasp is None and (own is None or math.isclose(own, problem.tree.grasp_fraction))) or (
        grasp is not None and own is not None and math.isclose(grasp, own)
    )
    if not same:
        return None
    tau, tau_dot, ok = evaluator.rollout(np.asarray(theta, float))
    return Rollout(tau, tau_dot, np.broadcast_to(ok[:, None], tau.shape[:2]))


def _training_fit(problem, posterior, config, evaluator=None) -> dict:
    """The run's fit to its training data: ``{"stable" [P], "prediction"`` (:class:`Prediction`,
    None when too few particles are stable), ``"metrics"}``. ``evaluator``: the start
    pipeline's :class:`~treeinfer.inference.fast_evaluator.BatchEvaluator` if the run layer
    holds it (its compiled program simulates the particles, :func:`_held_rollout`)."""
    pred_ok = np.isfinite(posterior.log_density)
    sim = problem.sim
    from .metrics import summarize

    sigma, kind = noise_for(posterior.theta, sim.n_joints, problem.settings)
    rollout_pred = None
    grasp = config["options"]["grasp_fraction"]
    recorded = problem.settings.get("grasp_fraction")  # e.g. each recording's own (pulls.yaml)
    if grasp is None and (isinstance(recorded, (list, tuple)) or problem.model is not None):
        grasp = recorded
    obs, grasp, padded = _fit_bucket(problem, grasp)
    model = getattr(problem, "model", None)
    held = None if padded else _held_rollout(evaluator, problem, obs, grasp, posterior.theta)
    try:
        rollout_pred = predict_run(
            sim,
            posterior.theta,
            obs.force,
            grasp,
            pred_ok,
            noise_sigma=sigma,
            noise_kind=kind,
            model=model,
            force_noise=force_noise_for(problem.settings),
            traced_substeps=padded,
            rollout=held,
        )
    except SimulationError:
        pass  # too few stable particles: the stable-share check reports it
    if rollout_pred is None:
        return {"stable": np.zeros(len(posterior.theta), bool), "prediction": None, "metrics": None}
    if padded:  # the real samples' velocity as unpadded (the loss below uses it)
        rows, steps = np.shape(problem.obs.force)
        cut = _cut(rollout_pred, rows, steps, float(problem.obs.dt))
        tau_dot = np.array(rollout_pred.tau_dot)
        tau_dot[:, :rows, steps - 1] = cut.tau_dot[..., steps - 1]
        full = rollout_pred._replace(tau_dot=tau_dot)
    else:
        full = cut = rollout_pred
    # padded rows have no real sample: a zero log-likelihood, which the sum over rows ignores
    ll = _per_trajectory_loglik(full, obs, problem.kT)
    metrics = summarize(
        full.tau,
        obs.displacement,
        mask=obs.mask,
        valid=rollout_pred.valid,
        log_likelihood=ll,
        noise_sigma=sigma,
        noise_kind=kind,
        extra_variance=rollout_pred.force_variance,
    )
    if rollout_pred.force_variance is not None:
        metrics["band_includes_force_noise"] = True  # as evaluate's metrics.json
    return {"stable": rollout_pred.valid, "prediction": cut, "metrics": metrics}
