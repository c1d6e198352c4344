"""theta's columns: the paper's parameterisation ``theta = [log Kp (R), log Kd (R), noise
columns]``, gains and noise scales in and out, natural units for reports.

A module of its own, below the likelihood, so that everything that maps particles to gains
(the likelihood, the MAP fit, the force-noise term) imports it without an import cycle."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ConfigError


def gains_from_theta(theta: jax.Array, n_joints: int) -> tuple[jax.Array, jax.Array]:
    """``theta [..., 2R (+ extra)]`` (log Kp then log Kd, then e.g. log sigma_x) ->
    (Kp [..., R] N m/rad, Kd [..., R] N m s/rad). Extra noise columns are ignored."""
    return jnp.exp(theta[..., :n_joints]), jnp.exp(theta[..., n_joints : 2 * n_joints])


def theta_from_gains(kp, kd) -> np.ndarray:
    """Inverse of :func:`gains_from_theta` (numpy, for configs and true parameters)."""
    kp, kd = np.asarray(kp, float), np.asarray(kd, float)
    if np.any(~np.isfinite(kp)) or np.any(~np.isfinite(kd)) or np.any(kp <= 0) or np.any(kd <= 0):
        raise ConfigError(
            f"Kp and Kd must be finite and positive, got Kp={kp.tolist()}, Kd={kd.tolist()}"
        )
    return np.concatenate([np.log(kp), np.log(kd)], axis=-1)


def noise_columns(kind: str, infer_sigma_x: bool) -> tuple[str, ...]:
    """Labels of theta's noise columns after the 2R gains, for a likelihood ``kind``.

    Values in theta: ``sigma_x`` and ``sigma_c`` as natural logs (of metres), ``rho`` as
    ``logit(rho)``. gaussian / student_t: ``("sigma_x",)`` or () when sigma_x is given; ar1:
    ``("sigma_x", "sigma_c", "rho")`` or ``("sigma_c", "rho")``; boltzmann: ()."""
    if kind == "ar1":
        return ("sigma_x", "sigma_c", "rho") if infer_sigma_x else ("sigma_c", "rho")
    if kind in ("gaussian", "student_t"):
        return ("sigma_x",) if infer_sigma_x else ()
    return ()


def noise_params_from_theta(theta, n_joints: int, sigma_x: float | None = None):
    """Per-row MARGINAL displacement-noise scale ``[N]`` (m) from ``theta [N, 2R + E]``.

    The layout is read from the number E of noise columns (:func:`noise_columns`): E = 1 is
    ``log sigma_x``; E = 3 is ``log sigma_x, log sigma_c, logit rho`` and E = 2 ``log sigma_c,
    logit rho`` with the fixed ``sigma_x`` (ar1: the marginal scale is
    ``sqrt(sigma_x^2 + sigma_c^2)``); E = 0 broadcasts the fixed ``sigma_x`` (None when there is
    none, e.g. a Boltzmann run without a noise estimate). This is the scale the predictive band
    uses (:func:`predictive_noise_kind` gives its distribution)."""
    theta = jnp.atleast_2d(jnp.asarray(theta))
    c = 2 * n_joints
    e = theta.shape[-1] - c
    if e == 1:
        return jnp.exp(theta[:, c])
    if e == 3:
        return jnp.sqrt(jnp.exp(2 * theta[:, c]) + jnp.exp(2 * theta[:, c + 1]))
    if e == 2:
        if sigma_x is None:
            raise ConfigError("noise_params_from_theta: ar1 with a fixed sigma_x needs sigma_x")
        return jnp.sqrt(float(sigma_x) ** 2 + jnp.exp(2 * theta[:, c]))
    if e != 0:
        raise ConfigError(
            f"theta: expected 2R + 0..3 columns, got {theta.shape[-1]} for R = {n_joints}"
        )
    if sigma_x is None:
        return None
    return jnp.full(theta.shape[:1], float(sigma_x), theta.dtype)


def natural_units(theta, labels) -> np.ndarray:
    """theta ``[N, D]`` -> the same columns in natural units for reports: ``exp`` of every column
    (gains, ``sigma_x``, ``sigma_c``: N m/rad, N m s/rad, m) except ``rho`` (``sigmoid`` of its
    logit). ``labels``: theta's column labels (gains' labels + :func:`noise_columns`)."""
    theta = np.atleast_2d(np.asarray(theta, float))
    labels = list(labels)
    if len(labels) != theta.shape[-1]:
        raise ConfigError(f"labels: expected {theta.shape[-1]} names, got {len(labels)}")
    out = np.exp(theta)
    for j, lab in enumerate(labels):
        if lab == "rho":
            out[:, j] = 1.0 / (1.0 + np.exp(-theta[:, j]))
    return out


def predictive_noise_kind(kind: str) -> str:
    """Distribution of one point's noise for the predictive band: ``student_t`` for student_t,
    ``gaussian`` otherwise (ar1's marginal is Gaussian; Boltzmann runs use the Gaussian with
    the data estimate)."""
    return "student_t" if kind == "student_t" else "gaussian"
