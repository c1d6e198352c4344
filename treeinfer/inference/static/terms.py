"""Likelihood terms of any :class:`~treeinfer.inference.static.Model` (static model, stiffness only,
per-recording pulls): the Boltzmann loss and the generative noise models of
:mod:`treeinfer.model.likelihood`, on the model's own rollout and theta layout.

:func:`treeinfer.model.likelihood.likelihood_terms` builds its terms on the paper's rollout of
``theta = [log Kp, log Kd]`` pulled down at the tree's grasp. Here the same choices (kind, kT
or ``"auto"``, sigma_x given or inferred, the noise priors, settings and description) come from
it, and only the simulation is replaced: theta is ``[model gains (layout.dim), noise columns]``
and the displacement is :func:`~treeinfer.inference.static.model_rollout`'s. The noise model's
densities are the same numpyro ones (:func:`treeinfer.model.noise.residual_log_prob`,
:func:`treeinfer.model.noise.ar1_white_log_prob`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ...data.trajectories import Observations
from ...errors import ConfigError
from ...model import noise
from ...model.boltzmann import DEFAULT_KT, log_likelihood_from_rollout
from ...model.gradients import autodiff_value_and_grad, central_difference, finite_difference_jvp
from ...model.likelihood import likelihood_terms
from ...sim import Simulator
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
    force_noise: float | None = None,
):
    """:class:`treeinfer.model.likelihood.LikelihoodTerms` of ``model`` on ``obs``.

    Args:
      model: the run's model (kind, layout, per-profile branch and direction).
      kind, kT, sigma_x, rel_step: as :func:`treeinfer.model.likelihood.likelihood_terms`.
      grasp_fraction: None, a scalar or [B] (each recording's own point).
      gradient: ``"fd"`` (black box: central differences of the Boltzmann loss, or the
        simulator wrapped in :func:`~treeinfer.model.gradients.finite_difference_jvp` for the
        generative kinds) or ``"autodiff"`` (through the simulator).
      force_noise: N, the load cell's noise std (e.g. :func:`force_noise_estimate`), or None.
        Given (Gaussian or Student-t only), each recording's displacement noise is
        :func:`effective_noise`: ``sqrt(sigma_x^2 + (force_noise * c_b)^2)`` with ``c_b`` the
        model's compliance at that recording's pull (a noisy force read through the branch's
        compliance; the linearised errors-in-variables model). A push where the branch is soft
        turns the same load-cell noise into more displacement scatter than a stiff one.

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

    if force_noise is not None:
        if kind not in ("gaussian", "student_t"):
            raise ConfigError(f"force noise: works with gaussian or student_t, not {kind!r}")
        if not (math.isfinite(float(force_noise)) and float(force_noise) > 0):
            raise ConfigError(f"force noise: expected a positive std in N, got {force_noise!r}")
        settings = {**base.settings, "force_noise": float(force_noise)}
        base = base._replace(
            settings=settings,
            description=base.description
            + f"; load-cell noise {float(force_noise):.3g} N read through each pull's compliance",
        )
    loglik = _measurement(
        rollout, obs, d, kind, base.sigma_x, gradient == "fd", rel_step, force_noise
    )
    extra = None
    if base.extra_log_prior is not None:
        prior = base.extra_log_prior

        def extra(theta):
            return prior(full_theta(model.layout, theta))

    return base._replace(
        log_likelihood=loglik, value_and_grad=autodiff_value_and_grad(loglik), extra_log_prior=extra
    )


def compliance_slopes(tau, force, mask=None):
    """``[..., B]`` least-squares slopes ``c_b = sum_t tau F / sum_t F^2`` (m/N) of displacement
    ``tau [..., B, T]`` on force ``force [B, T]`` over the real samples (``mask [B, T]``)."""
    f = jnp.asarray(force, tau.dtype)
    m = jnp.ones(f.shape, bool) if mask is None else jnp.asarray(mask, bool)
    num = jnp.sum(jnp.where(m, tau * f, 0.0), axis=-1)
    den = jnp.sum(jnp.where(m, f * f, 0.0), axis=-1)
    return num / jnp.maximum(den, jnp.finfo(tau.dtype).tiny)


def effective_noise(sigma_x, force_noise, tau, force, mask=None):
    """``[N, B]`` displacement noise std (m) ``sqrt(sigma_x^2 + (force_noise * c_b)^2)`` of
    draws with noise ``sigma_x [N]`` (m) and predicted displacements ``tau [N, B, T]`` under
    ``force [B, T]`` (N); ``force_noise`` in N (None: ``sigma_x`` alone)."""
    sx = jnp.asarray(sigma_x, tau.dtype)[:, None]
    if force_noise is None:
        return jnp.broadcast_to(sx, tau.shape[:2])
    c = compliance_slopes(tau, force, mask)
    return jnp.sqrt(sx**2 + (float(force_noise) * c) ** 2)


class StaticForceNoise(NamedTuple):
    """The load-cell term of a static run (``--noise-force`` with ``--model-kind static``) for
    its predictive bands: the same term as its likelihood (:func:`effective_noise`).

    sigma_force: N per force sample (the run's ``force_noise`` setting). description: one line.

    The static model's prediction is linear in the force at small deflections, so a load-cell
    error ``e ~ N(0, sigma_F)`` on a sample moves that sample's predicted displacement by
    ``c e`` (``c`` the pull's compliance, m/N) and no other sample (no dynamics): each point of
    a draw's predictive distribution has variance ``sigma_x^2 + (sigma_F c)^2``. The dynamic
    model's term (:mod:`treeinfer.model.force_noise`) is the same idea with the full force Jacobian.
    """

    sigma_force: float
    description: str = ""

    def point_variance(self, tau, force, mask=None) -> np.ndarray:
        """``[P, B, T]`` m^2: ``(sigma_F c_{p,b})^2`` at every sample of pull b for draw p, with
        ``c_{p,b}`` the least-squares compliance of that draw's predicted displacement ``tau
        [P, B, T]`` (m) on the pull's force ``force [B, T]`` (N) (:func:`compliance_slopes`,
        as the likelihood). Non-finite (unstable draws) -> 0."""
        tau = np.nan_to_num(np.asarray(tau, float))
        force = np.atleast_2d(np.asarray(force, float))
        c = np.asarray(compliance_slopes(jnp.asarray(tau), force, mask), float)  # [P, B]
        var = (float(self.sigma_force) * c) ** 2
        return np.broadcast_to(np.nan_to_num(var)[..., None], tau.shape).copy()

    def settings(self) -> dict:
        """JSON-ready record (the static run's ``force_noise`` setting, N)."""
        return {"force_noise": float(self.sigma_force)}


def static_force_noise_for(settings: dict | None) -> StaticForceNoise | None:
    """The load-cell term of a run from its problem settings: a static run (``model_kind:
    static``) with ``force_noise`` (N) recorded; else None."""
    settings = settings or {}
    sf = settings.get("force_noise")
    if settings.get("model_kind") != "static" or sf is None:
        return None
    return StaticForceNoise(
        float(sf), f"load-cell noise {float(sf):.3g} N read through each pull's compliance"
    )


def force_noise_estimate(data) -> float:
    """The load cell's noise std (N) from the recordings' force signals: the ``--noise-force
    auto`` estimate (:func:`treeinfer.model.force_noise.estimate_force_noise`, robust MAD of second
    differences / sqrt(6); a slow push's force is smooth between samples)."""
    from ...model.force_noise import estimate_force_noise

    return float(estimate_force_noise(noise.as_observations(data)).sigma)


def _measurement(rollout, obs, d, kind, sigma_x, black_box, rel_step, force_noise=None):
    """``theta [N, d + E] -> [N]``: the displacement noise model on ``rollout``'s tau (the
    same terms as :func:`treeinfer.model.likelihood.measurement_log_likelihood`, velocity term
    off)."""
    x_obs = jnp.asarray(obs.displacement)
    mask = jnp.asarray(obs.mask, bool)
    forces = jnp.asarray(obs.force)
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
        if force_noise is not None:  # each pull's own scatter (its compliance)
            scale = effective_noise(sx, force_noise, jnp.nan_to_num(out), forces, mask)
            lp = noise.residual_log_prob(resid, scale[:, :, None], kind, df)
            total = jnp.sum(jnp.where(mask, lp, 0.0), axis=(-2, -1))
        elif kind == "ar1":
            sc, rho = jnp.exp(theta[:, c]), jax.nn.sigmoid(theta[:, c + 1])
            total = noise.ar1_white_log_prob(resid, mask, sx, sc, rho)
        else:
            lp = noise.residual_log_prob(resid, sx[:, None, None], kind, df)
            total = jnp.sum(jnp.where(mask, lp, 0.0), axis=(-2, -1))
        return jnp.where(jnp.isfinite(total), total, -jnp.inf)

    return loglik
