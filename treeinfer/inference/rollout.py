"""Predictions: every parameter set simulated under a force profile (:func:`predict`).

Below :mod:`treeinfer.inference.problem` (which re-exports :func:`predict`), so that evaluation and
the posterior object (:mod:`treeinfer.inference.posterior`, returned by ``infer``) simulate without
importing the module that builds problems and runs samplers."""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ConfigError
from ..model.likelihood import gains_from_theta
from ..sim import Rollout, simulate


def predict(
    sim_or_problem,
    theta,
    forces,
    grasp_fraction=None,
    model=None,
    traced_substeps: bool = False,
) -> Rollout:
    """Simulate every particle ``theta [P, D]`` under ``forces [B, T]``: :class:`Rollout` [P, B, T].

    ``traced_substeps``: the simulator's substeps per observation enter the program as an
    argument, not as a constant, so simulators that differ only in their step (an
    accuracy-controlled step chosen on each data set's forces) share one compiled program; the
    values agree with the default's to float32 rounding (another formulation of the same loop,
    as :class:`treeinfer.inference.fast_evaluator.BatchEvaluator`'s). The dynamic model only.

    ``grasp_fraction`` (scalar or [B]) predicts at another point of the grasped branch.
    ``model``: the run's :class:`treeinfer.inference.static.Model` (static model or stiffness only;
    a problem's own by default), None for the dynamic model of ``[log Kp, log Kd]``.
    Particles whose rollout is unstable have ``stable = False``; drop them before summarising."""
    if hasattr(sim_or_problem, "sim") and hasattr(sim_or_problem, "log_density"):  # a Problem
        sim, model = sim_or_problem.sim, (sim_or_problem.model if model is None else model)
    else:
        sim = sim_or_problem
    theta = jnp.atleast_2d(jnp.asarray(theta))
    if model is None:
        if not 2 * sim.n_joints <= theta.shape[-1] <= 2 * sim.n_joints + 3:
            raise ConfigError(
                f"theta: expected {2 * sim.n_joints} columns (log Kp, log Kd per joint) and up "
                f"to 3 noise columns, got {theta.shape[-1]}"
            )
        theta = theta[:, : 2 * sim.n_joints]  # noise columns do not enter the simulation
    else:
        d = model.layout.dim
        if not d <= theta.shape[-1] <= d + 3:
            raise ConfigError(
                f"theta: expected {d} columns ({', '.join(model.labels)}) and up to 3 noise "
                f"columns, got {theta.shape[-1]}"
            )
        theta = theta[:, :d]
    if grasp_fraction is not None:
        g = np.asarray(grasp_fraction, float)
        if np.any(~np.isfinite(g)) or np.any(g <= 0) or np.any(g > 1):
            raise ConfigError(f"grasp_fraction: must be in (0, 1], got {g.tolist()}")
    forces = jnp.atleast_2d(jnp.asarray(forces))
    if model is not None:
        from .static import model_rollout

        return model_rollout(sim, model, theta, forces, grasp_fraction)  # jitted inside
    kp, kd = gains_from_theta(theta, sim.n_joints)
    if traced_substeps:
        return _predict_traced(sim, kp, kd, forces, grasp_fraction, jnp.int32(sim.substeps))
    return _predict_jit(sim, kp, kd, forces, grasp_fraction)


@partial(jax.jit, static_argnums=0)
def _predict_jit(sim, kp, kd, forces, grasp_fraction):
    return simulate(sim, kp, kd, forces, grasp_fraction)


@partial(jax.jit, static_argnums=0)
def _predict_traced(sim, kp, kd, forces, grasp_fraction, substeps):
    from ..sim import _simulate

    return _simulate(sim, kp, kd, forces, grasp_fraction, substeps=substeps)
