"""The Boltzmann likelihood of force-deformation trajectories (paper eq. 4-6).

Per trajectory b the loss is the plain L2 distance of position and velocity trajectories,

    L_b(theta) = ||tau_sim - tau_gt||_2 + ||tau_dot_sim - tau_dot_gt||_2,

and the log-likelihood of i.i.d. trajectories is ``log p(D | theta) = -sum_b L_b(theta) / kT``
(the normaliser ``Z`` drops out of every sampler we use).

Parameterisation: samplers work on ``theta = [log Kp_1..R, log Kd_1..R]``. Kp and Kd span
orders of magnitude, so a log scale gives every particle the same relative resolution, makes
one finite-difference step (and one SVGD bandwidth) fit all of them, and keeps gains positive.

Choosing kT: ``kT`` is the loss that costs one nat of log-density, i.e. it sets how sharply the
data constrain the posterior. A good value is the loss you would expect from measurement noise
alone at the true parameters: with displacement noise sigma (m) on T samples at step dt,
``E[L] ~ sigma * sqrt(T) * (1 + 1 / (sqrt(2) * dt))`` (the second term is the finite-difference
velocity's noise), see :func:`suggest_kT`. Smaller kT gives narrower posteriors (and overconfident
bands if the model is wrong); larger kT wider ones. The default, ``DEFAULT_KT = 0.05``, is that
rule for ~1 mm noise on a few hundred 10 ms samples (a clean simulated set-up or a good robot).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from .errors import ConfigError
from .sim import Rollout, Simulator, simulate
from .trajectories import Observations

DEFAULT_KT = 0.05


def gains_from_theta(theta: jax.Array, n_joints: int) -> tuple[jax.Array, jax.Array]:
    """``theta [..., 2R]`` (log Kp then log Kd) -> (Kp [..., R] N m/rad, Kd [..., R] N m s/rad)."""
    return jnp.exp(theta[..., :n_joints]), jnp.exp(theta[..., n_joints:])


def theta_from_gains(kp, kd) -> np.ndarray:
    """Inverse of :func:`gains_from_theta` (numpy, for configs and true parameters)."""
    kp, kd = np.asarray(kp, float), np.asarray(kd, float)
    if np.any(~np.isfinite(kp)) or np.any(~np.isfinite(kd)) or np.any(kp <= 0) or np.any(kd <= 0):
        raise ConfigError(f"Kp and Kd must be finite and positive, got Kp={kp.tolist()}, Kd={kd.tolist()}")
    return np.concatenate([np.log(kp), np.log(kd)], axis=-1)


def trajectory_loss(rollout: Rollout, obs: Observations) -> jax.Array:
    """``L_b`` for every parameter set and trajectory: [P, B] (metres + metres per second).

    Time steps outside ``obs.mask`` (padding of shorter trajectories) do not count."""
    mask = jnp.asarray(obs.mask, rollout.tau.dtype)
    dpos = (rollout.tau - jnp.asarray(obs.displacement, rollout.tau.dtype)) * mask
    dvel = (rollout.tau_dot - jnp.asarray(obs.velocity, rollout.tau.dtype)) * mask
    return jnp.sqrt(jnp.sum(dpos**2, -1)) + jnp.sqrt(jnp.sum(dvel**2, -1))


def log_likelihood_from_rollout(rollout: Rollout, obs: Observations, kT: float) -> jax.Array:
    """``-sum_b L_b / kT`` [P]; ``-inf`` for a parameter set with any unstable rollout."""
    ll = -jnp.sum(trajectory_loss(rollout, obs), axis=-1) / kT
    return jnp.where(jnp.all(rollout.stable, axis=-1), ll, -jnp.inf)


def boltzmann_log_likelihood(sim: Simulator, obs: Observations, kT: float = DEFAULT_KT, grasp_fraction=None):
    """Batched log-likelihood ``theta [N, 2R] -> [N]``: one simulator call for all N rows.

    Args:
      sim: the compiled tree (its ``obs_dt`` must equal the data's dt).
      obs: stacked training trajectories (:func:`treeinfer.trajectories.stack_trajectories`).
      kT: temperature (see the module docstring for how to choose it).
      grasp_fraction: where the data were recorded along the grasped branch (None: the tree's).
    """
    check_kT(kT)
    if not math.isclose(float(obs.dt), sim.obs_dt, rel_tol=1e-6):
        raise ConfigError(f"trajectories have dt={obs.dt} s but the simulator was built for {sim.obs_dt} s")
    forces = jnp.asarray(obs.force)

    def loglik(theta: jax.Array) -> jax.Array:
        kp, kd = gains_from_theta(theta, sim.n_joints)
        return log_likelihood_from_rollout(simulate(sim, kp, kd, forces, grasp_fraction), obs, kT)

    return loglik


def check_kT(kT) -> float:
    try:
        kT = float(kT)
    except (TypeError, ValueError):
        raise ConfigError(f"kT: expected a positive number, got {kT!r}") from None
    if not math.isfinite(kT) or kT <= 0:
        raise ConfigError(f"kT: must be a finite positive number, got {kT}")
    return kT


def suggest_kT(sigma_displacement: float, n_steps: int, dt: float) -> float:
    """Expected loss of one trajectory at the true parameters under white displacement noise
    ``sigma`` (m) when velocity is differentiated from displacement (see module docstring)."""
    return float(sigma_displacement * math.sqrt(n_steps) * (1.0 + 1.0 / (math.sqrt(2.0) * dt)))
