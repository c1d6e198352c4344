"""The Boltzmann likelihood of force-deformation trajectories (paper eq. 4-6).

Per trajectory b the loss is the plain L2 distance of position and velocity trajectories,

    L_b(theta) = ||tau_sim - tau_gt||_2 + ||tau_dot_sim - tau_dot_gt||_2,

and the log-likelihood of i.i.d. trajectories is ``log p(D | theta) = -sum_b L_b(theta) / kT``
(the normaliser ``Z`` drops out of every sampler we use).

Choosing kT: the log-likelihood is ``-sum_b L_b / kT``, summed over trajectories; kT is a
temperature *per trajectory loss* (metres + m/s), and the rule below does not depend on the
number of trajectories B. With white displacement noise sigma (m) on T samples at step dt the
norm ``||r_b||`` of the noise residual is ``~ sigma sqrt(T)``, so a model change ``delta`` moves
``L_b`` by ``~ ||delta||^2 / (2 sigma sqrt(T))`` to second order, while the Gaussian measurement
log-likelihood moves by ``||delta||^2 / (2 sigma^2)``. Equal curvature (posterior widths as under
the generative Gaussian model, i.e. calibrated) needs

    kT = sigma / sqrt(T) * (1 + sqrt(2) * dt * omega2)        (:func:`suggest_kT`)

where the factor ``(1 + sqrt(2) dt omega2)`` accounts for the velocity term, which counts the same
noise a second time; ``omega2`` (1/s^2) is the ratio of the signal's mean squared velocity to its
mean squared displacement (0 drops the correction). ``kT = "auto"`` (:func:`auto_kT`, in
:mod:`treeinfer.model.temperature`) estimates sigma
(:func:`treeinfer.model.noise.estimate_displacement_noise`) and omega2 from the data and applies the
rule. Example: 2 mm noise, 301 samples at 10 ms, omega2 = 0 gives kT = 1.2e-4.

``DEFAULT_KT = 0.05`` is the paper-reproduction setting used by the studies in ``experiments/``;
it is NOT tied to a noise level: by the rule it is the temperature for ~0.4-0.9 m of noise, i.e.
a strongly tempered (wide) posterior. On noisy recordings use ``kT="auto"`` or, better, the

Why a module of its own (issue 26): the paper's loss and its temperature are one job, separate
from the generative measurement models (:mod:`treeinfer.model.measurement`) and from
:func:`treeinfer.model.likelihood.likelihood_terms`, which builds either kind for a problem.
:mod:`treeinfer.model.likelihood` re-exports every name here (they lived there before the split).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from ..data.trajectories import Observations
from ..errors import ConfigError
from ..sim import Rollout, Simulator, simulate
from .gains import gains_from_theta
from .temperature import check_kT

__all__ = [
    "DEFAULT_KT",
    "boltzmann_log_likelihood",
    "log_likelihood_from_rollout",
    "trajectory_loss",
]

DEFAULT_KT = 0.05


def trajectory_loss(rollout: Rollout, obs: Observations) -> jax.Array:
    """``L_b`` for every parameter set and trajectory: [P, B] (metres + metres per second).

    Time steps outside ``obs.mask`` (padding of shorter trajectories) do not count."""
    mask = jnp.asarray(obs.mask, rollout.tau.dtype)
    dpos = (rollout.tau - jnp.asarray(obs.displacement, rollout.tau.dtype)) * mask
    dvel = (rollout.tau_dot - jnp.asarray(obs.velocity, rollout.tau.dtype)) * mask
    return jnp.sqrt(jnp.sum(dpos**2, -1)) + jnp.sqrt(jnp.sum(dvel**2, -1))


def _padded_trajectory_loss(rollout: Rollout, obs: Observations) -> jax.Array:
    """:func:`trajectory_loss` [P, B'] of observations with padded rows (no real sample): the
    same values (0 on a padded row), but the norm of a padded row's zero residual is not
    differentiated (d sqrt(s) / ds is infinite at s = 0: forward or reverse mode would give
    NaN where the unpadded problem has no row at all)."""
    mask = jnp.asarray(obs.mask, rollout.tau.dtype)
    dpos = (rollout.tau - jnp.asarray(obs.displacement, rollout.tau.dtype)) * mask
    dvel = (rollout.tau_dot - jnp.asarray(obs.velocity, rollout.tau.dtype)) * mask
    real = jnp.any(jnp.asarray(obs.mask, bool), axis=-1)  # [B']

    def norm(r):
        s = jnp.sum(r**2, -1)
        return jnp.where(real, jnp.sqrt(jnp.where(real, s, 1.0)), 0.0)

    return norm(dpos) + norm(dvel)


def log_likelihood_from_rollout(rollout: Rollout, obs: Observations, kT: float) -> jax.Array:
    """``-sum_b L_b / kT`` [P]; ``-inf`` for a parameter set with any unstable rollout."""
    ll = -jnp.sum(trajectory_loss(rollout, obs), axis=-1) / kT
    return jnp.where(jnp.all(rollout.stable, axis=-1), ll, -jnp.inf)


def boltzmann_log_likelihood(
    sim: Simulator, obs: Observations, kT: float = DEFAULT_KT, grasp_fraction=None
):
    """Batched log-likelihood ``theta [N, 2R] -> [N]``: one simulator call for all N rows.

    Args:
      sim: the compiled tree (its ``obs_dt`` must equal the data's dt).
      obs: stacked training trajectories (:func:`treeinfer.data.trajectories.stack_trajectories`).
      kT: temperature (see the module docstring for how to choose it).
      grasp_fraction: where the data were recorded along the grasped branch (None: the tree's).
    """
    check_kT(kT)
    if not math.isclose(float(obs.dt), sim.obs_dt, rel_tol=1e-6):
        raise ConfigError(
            f"trajectories have dt={obs.dt} s but the simulator was built for {sim.obs_dt} s"
        )
    # device_put, not jnp.asarray: jax compiles a small program per shape for jnp.asarray of a
    # NumPy array (lax.stage), one XLA compile for every new data length at a cold start
    forces = jax.device_put(obs.force)

    def loglik(theta: jax.Array) -> jax.Array:
        kp, kd = gains_from_theta(theta, sim.n_joints)
        return log_likelihood_from_rollout(simulate(sim, kp, kd, forces, grasp_fraction), obs, kT)

    return loglik
