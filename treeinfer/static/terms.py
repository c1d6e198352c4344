"""Likelihood terms of any :class:`~treeinfer.static.Model` (static model, stiffness only,
per-recording pulls): the Boltzmann loss and the generative noise models of
:mod:`treeinfer.likelihood`, on the model's own rollout and theta layout.

:func:`treeinfer.likelihood.likelihood_terms` builds its terms on the paper's rollout of
``theta = [log Kp, log Kd]`` pulled down at the tree's grasp. Here the same choices (kind, kT
or ``"auto"``, sigma_x given or inferred, the noise priors, settings and description) come from
it, and only the simulation is replaced: theta is ``[model gains (layout.dim), noise columns]``
and the displacement is :func:`~treeinfer.static.model_rollout`'s. The noise model's densities
are the same numpyro ones (:func:`treeinfer.noise.residual_log_prob`,
:func:`treeinfer.noise.ar1_white_log_prob`).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from .. import noise
from ..errors import ConfigError
from ..gradients import autodiff_value_and_grad, central_difference, finite_difference_jvp
from ..likelihood import DEFAULT_KT, likelihood_terms, log_likelihood_from_rollout
from ..sim import Simulator
from ..trajectories import Observations
from .model import Model, model_rollout


def full_theta(layout, theta):
    """``[N, layout.dim + E]`` -> ``[N, 2R + E]``: the gains in the full ``[log Kp, log Kd]``
    layout (damping at its fixed value when not inferred), then the same noise columns."""
    theta = jnp.atleast_2d(jnp.asarray(theta))
    d = layout.dim
    return jnp.concatenate([layout.full_theta(theta[:, :d]), theta[:, d:]], axis=-1)


def model_likelihood_terms(
    sim: Simulator,
    model: Model,
    obs: Observations,
    kind: str = "boltzmann",
    *,
    kT: float | str = DEFAULT_KT,
    sigma_x: float | None = None,
    grasp_fraction=None,
    gradient: str = "fd",
    rel_step: float | None = None,
):
    """:class:`treeinfer.likelihood.LikelihoodTerms` of ``model`` on ``obs``.

    Args:
      model: the run's model (kind, layout, per-profile branch and direction).
      kind, kT, sigma_x, rel_step: as :func:`treeinfer.likelihood.likelihood_terms`.
      grasp_fraction: None, a scalar or [B] (each recording's own point).
      gradient: ``"fd"`` (black box: central differences of the Boltzmann loss, or the
        simulator wrapped in :func:`~treeinfer.gradients.finite_difference_jvp` for the
        generative kinds) or ``"autodiff"`` (through the simulator).

    Returns:
      the terms with ``log_likelihood: theta [N, layout.dim + E] -> [N]`` (nats) and the noise
      columns' prior on theta's columns after the model's gains.
    """
    if not math.isclose(float(obs.dt), sim.obs_dt, rel_tol=1e-6):
        raise ConfigError(
            f"trajectories have dt={obs.dt} s but the simulator was built for {sim.obs_dt} s"
        )
    base = likelihood_terms(
        sim, obs, kind, kT=kT, sigma_x=sigma_x, grasp_fraction=grasp_fraction, gradient=gradient
    )
    d = model.layout.dim
    forces = jnp.asarray(obs.force, sim.dtype)

    def rollout(gains):
        return model_rollout(sim, model, gains, forces, grasp_fraction)

    if kind == "boltzmann":
        kT_value = base.kT

        def loglik(theta):
            return log_likelihood_from_rollout(rollout(jnp.asarray(theta)[:, :d]), obs, kT_value)

        vg = (
            central_difference(loglik, rel_step=rel_step)
            if gradient == "fd"
            else autodiff_value_and_grad(loglik)
        )
        return base._replace(log_likelihood=loglik, value_and_grad=vg)

    loglik = _measurement(rollout, obs, d, kind, base.sigma_x, gradient == "fd", rel_step)
    extra = None
    if base.extra_log_prior is not None:
        prior = base.extra_log_prior

        def extra(theta):
            return prior(full_theta(model.layout, theta))

    return base._replace(
        log_likelihood=loglik, value_and_grad=autodiff_value_and_grad(loglik), extra_log_prior=extra
    )


def _measurement(rollout, obs, d, kind, sigma_x, black_box, rel_step):
    """``theta [N, d + E] -> [N]``: the displacement noise model on ``rollout``'s tau (the
    same terms as :func:`treeinfer.likelihood.measurement_log_likelihood`, velocity term off)."""
    x_obs = jnp.asarray(obs.displacement)
    mask = jnp.asarray(obs.mask, bool)
    df = noise.DEFAULT_STUDENT_T_DF

    def tau(gains):  # [M, d] -> [M, B, T], NaN where unstable
        ro = rollout(gains)
        return jnp.where(ro.stable[..., None], ro.tau, jnp.nan)

    sim_fn = finite_difference_jvp(tau, rel_step) if black_box else tau

    def loglik(theta):
        theta = jnp.asarray(theta)
        out = sim_fn(theta[:, :d])
        c = d
        if sigma_x is None:
            sx, c = jnp.exp(theta[:, c]), c + 1
        else:
            sx = jnp.full(theta.shape[:1], sigma_x, out.dtype)
        resid = x_obs.astype(out.dtype) - out
        if kind == "ar1":
            sc, rho = jnp.exp(theta[:, c]), jax.nn.sigmoid(theta[:, c + 1])
            total = noise.ar1_white_log_prob(resid, mask, sx, sc, rho)
        else:
            lp = noise.residual_log_prob(resid, sx[:, None, None], kind, df)
            total = jnp.sum(jnp.where(mask, lp, 0.0), axis=(-2, -1))
        return jnp.where(jnp.isfinite(total), total, -jnp.inf)

    return loglik
