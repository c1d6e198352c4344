"""theta <-> gains: the paper's parameterisation ``theta = [log Kp (R), log Kd (R), extras]``.

A module of its own, below the likelihood, so that everything that maps particles to gains
(the likelihood, the MAP fit, the force-noise term) imports it without an import cycle."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .errors import ConfigError


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
