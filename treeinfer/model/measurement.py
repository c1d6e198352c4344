"""The measurement model: recorded = simulated + noise (the generative likelihoods of
:mod:`treeinfer.model.likelihood`), and the data layout its programs take as an argument
(observations padded to a shape bucket and masked)."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from ..data.trajectories import Observations
from ..errors import ConfigError
from ..sim import Rollout, Simulator, simulate
from . import noise
from .gains import (  # noqa: F401  (re-exported: they lived here before)
    gains_from_theta,
    natural_units,
    noise_columns,
    noise_params_from_theta,
    predictive_noise_kind,
    theta_from_gains,
)
from .gradients import finite_difference_jvp

# ----------------------------------------------------------------------------- measurement model


def measurement_log_likelihood(
    sim: Simulator,
    obs: Observations,
    kind: str = "gaussian",
    sigma_x: float | None = None,
    sigma_v: float | None = None,
    df: float = noise.DEFAULT_STUDENT_T_DF,
    grasp_fraction=None,
    rel_step: float | None = None,
    black_box: bool = True,
    force_basis=None,
    integration=None,
):
    """Generative log-likelihood ``theta [N, D] -> [N]`` (nats): displacement noise model.

    ``log p(D | theta) = sum_{b,t real} log p_noise(x_obs[b,t] - tau[b,t](theta); sigma_x)
    [+ sum log p_noise(v_obs - tau_dot; sigma_v)]``; ``-inf`` for rows with an unstable rollout.

    Args:
      kind: ``"gaussian"``, ``"student_t"`` (df ``df``) or ``"ar1"`` (white + AR(1)), see
        :mod:`treeinfer.model.noise`.
      sigma_x: m, fixed displacement noise; None: theta has an extra column ``log sigma_x``.
        Noise columns follow the 2R gains in the order of :func:`noise_columns` (ar1 always has
        ``log sigma_c, logit rho``); their priors are separate (:func:`likelihood_terms`).
      sigma_v: m/s, velocity noise; None (default) leaves the velocity out.
      black_box: True wraps the simulator in :func:`finite_difference_jvp` (central differences,
        ``rel_step``); False lets JAX differentiate through the simulator (checks only).
      force_basis: :class:`treeinfer.model.force_noise.ForceNoiseBasis` of the training pulls
        (gaussian only): the displacement residual of each pull is then
        ``MVN(0, C_b + sigma_x^2 I)`` with ``C_b`` the force-noise-induced covariance
        (:mod:`treeinfer.model.force_noise`).
      integration: None, or ``(rms, shape)``: the simulator's measured discretisation error
        (:mod:`treeinfer.model.integration_error`): ``shape`` ``[B, T]`` (m) is removed from the
        simulated displacement and ``rms`` (m) added to sigma_x in quadrature.
    """
    if kind not in noise.NOISE_KINDS:
        raise ConfigError(
            f"likelihood: expected one of {', '.join(noise.NOISE_KINDS)}, got {kind!r}"
        )
    if not math.isclose(float(obs.dt), sim.obs_dt, rel_tol=1e-6):
        raise ConfigError(
            f"trajectories have dt={obs.dt} s but the simulator was built for {sim.obs_dt} s"
        )
    df = noise.check_df(df)
    use_v = sigma_v is not None
    if use_v:
        sigma_v = noise.check_sigma(sigma_v, "noise_velocity")
    if sigma_x is not None:
        sigma_x = noise.check_sigma(sigma_x, "noise_displacement", noise.displacement_range(obs))
    if force_basis is not None:
        if kind != "gaussian" or use_v:
            raise ConfigError(
                "noise_force: the force-noise term needs --likelihood gaussian without a velocity "
                f"term (got likelihood {kind!r}, velocity term {'on' if use_v else 'off'})"
            )
        if np.shape(force_basis.values)[-2:] != tuple(np.shape(obs.displacement)):
            raise ConfigError(
                f"force_basis: built for pulls of shape {np.shape(force_basis.values)}, the data "
                f"have {tuple(np.shape(obs.displacement))}"
            )
    return _measurement_loglik(
        sim, obs, kind, sigma_x, sigma_v, df, grasp_fraction, rel_step, black_box, force_basis,
        integration=integration,
    )  # fmt: skip


def _measurement_loglik(
    sim,
    obs,
    kind,
    sigma_x,
    sigma_v,
    df,
    grasp_fraction,
    rel_step,
    black_box,
    force_basis,
    n_steps=None,
    integration=None,
):
    """:func:`measurement_log_likelihood` after its checks: ``obs`` (and ``force_basis``) may be
    traced arrays here (the sampler programs that take the data as arguments,
    :meth:`LikelihoodTerms.loglik_of`); the other arguments are checked values. ``n_steps``:
    None, or the unpadded length of ``obs`` padded past it (:func:`padded_rollout`)."""
    r = sim.n_joints
    dtype = sim.dtype
    forces = jnp.asarray(obs.force, dtype)
    x_obs = jnp.asarray(obs.displacement, dtype)
    v_obs = jnp.asarray(obs.velocity, dtype)
    mask = jnp.asarray(obs.mask, bool)
    use_v = sigma_v is not None

    def rollout(theta_gains):  # [M, 2R] -> [M, C, B, T], NaN where unstable
        kp, kd = gains_from_theta(theta_gains, r)
        if n_steps is None:
            ro = simulate(sim, kp, kd, forces, grasp_fraction)
        else:
            ro = padded_rollout(sim, kp, kd, forces, grasp_fraction, n_steps, mask)
        out = jnp.stack([ro.tau, ro.tau_dot], axis=1) if use_v else ro.tau[:, None]
        return jnp.where(ro.stable[:, None, :, None], out, jnp.nan)

    sim_fn = finite_difference_jvp(rollout, rel_step) if black_box else rollout

    density = _noise_density(kind, sigma_x, sigma_v, df, mask, force_basis, 2 * r, integration)

    def loglik(theta: jax.Array) -> jax.Array:
        theta = jnp.asarray(theta)
        out = sim_fn(theta[:, : 2 * r])
        dv = v_obs - out[:, 1] if use_v else None
        return density(x_obs - out[:, 0], dv, theta)

    return loglik


def _noise_density(kind, sigma_x, sigma_v, df, mask, force_basis, n_gains: int, integration=None):
    """``(dx [N, B, T], dv [N, B, T] or None, theta [N, D]) -> [N]``: the generative noise
    density of the recorded-minus-simulated displacement ``dx`` (and velocity ``dv``), the noise
    columns read from theta after its ``n_gains`` gains; ``-inf`` where not finite (NaN marks an
    unstable rollout). One function for the problem's likelihood and the start pipeline's host
    evaluation of rollout residuals (:meth:`LikelihoodTerms.residual_loglik`), so both compute
    the same density. ``integration``: None or ``(rms, shape)``, the simulator's measured
    discretisation error (:mod:`treeinfer.model.integration_error`: ``shape`` removed from the
    simulated displacement, ``rms`` a floor in quadrature with sigma_x)."""
    from .integration_error import corrected_residual, floored_scale

    floor, e_shape = (None, None) if integration is None else integration

    def density(dx, dv, theta):
        theta = jnp.asarray(theta)
        if e_shape is not None:
            dx = corrected_residual(dx, mask, e_shape)
        c = n_gains
        if sigma_x is None:
            sx, c = jnp.exp(theta[:, c]), c + 1
        else:
            sx = jnp.full(theta.shape[:1], sigma_x, dx.dtype)
        sx = floored_scale(sx, floor)
        if force_basis is not None:
            from . import force_noise  # numpyro: imported where the term is used

            resid = jnp.where(mask, dx, 0.0)
            total = force_noise.mvn_log_prob(resid, force_basis, sx, theta[:, :n_gains])
        elif kind == "ar1":
            sc, rho = jnp.exp(theta[:, c]), jax.nn.sigmoid(theta[:, c + 1])
            total = noise.ar1_white_log_prob(dx, mask, sx, sc, rho)
        else:
            lp = noise.residual_log_prob(dx, sx[:, None, None], kind, df)
            total = jnp.sum(jnp.where(mask, lp, 0.0), axis=(-2, -1))
        if sigma_v is not None and dv is not None:
            sv = jnp.asarray(sigma_v, dx.dtype)
            lpv = noise.residual_log_prob(dv, sv, predictive_noise_kind(kind), df)
            total = total + jnp.sum(jnp.where(mask, lpv, 0.0), axis=(-2, -1))
        return jnp.where(jnp.isfinite(total), total, -jnp.inf)

    return density


def observation_data(obs: Observations, grasp_fraction=None, shape=None) -> dict:
    """``obs [B, T]`` padded to ``shape`` ``(B', T')`` (None: as it is) and masked
    (:func:`treeinfer.sim.startup.bucket_observations`), as the pytree of arrays a program takes as
    its data argument: ``force``, ``displacement``, ``velocity`` ([B', T'], the default float
    dtype), ``mask`` ([B', T'] bool), ``n_steps`` (int32 scalar, the unpadded T) and, when
    ``grasp_fraction`` is one fraction per trajectory, ``grasp`` [B'] (padded rows, at rest,
    take the last fraction)."""
    b, t = np.shape(obs.force)
    if shape is not None:
        from ..sim.startup import bucket_observations

        obs = bucket_observations(obs, *(int(n) for n in shape))
    d = {
        "force": jnp.asarray(np.asarray(obs.force)),
        "displacement": jnp.asarray(np.asarray(obs.displacement)),
        "velocity": jnp.asarray(np.asarray(obs.velocity)),
        "mask": jnp.asarray(np.asarray(obs.mask, bool)),
        "n_steps": jnp.asarray(t, jnp.int32),
    }
    if grasp_fraction is not None and np.ndim(grasp_fraction) == 1:
        g = np.asarray(grasp_fraction, float)
        if g.size != b:
            raise ConfigError(f"grasp_fraction: {g.size} fractions for {b} trajectories")
        rows = np.shape(obs.force)[0]
        d["grasp"] = jnp.asarray(np.concatenate([g, np.full(rows - b, g[-1])]))
    return d


def padded_rollout(sim: Simulator, kp, kd, forces, grasp_fraction, n_steps, mask) -> Rollout:
    """:func:`treeinfer.sim.simulate` of observations padded past their length ``n_steps``
    (a traced int32 is fine) and masked (``mask [B', T']``), equal on the real samples to the
    rollout of the unpadded data: the velocity at sample ``n_steps - 1`` is the second-order
    one-sided difference the unpadded rollout ends with (:func:`treeinfer.sim.velocity`), not
    the central difference the padded steps would give (up to 3e-4 of the Boltzmann log
    density, ``tests/test_sampler_buckets.py``); and ``stable`` counts real rows only (a padded
    row, at rest, has no data). Written here, not in the simulator, because only the padded
    programs need it; the same correction as :func:`treeinfer.inference.fast`'s."""
    ro = simulate(sim, kp, kd, forces, grasp_fraction)
    x = ro.tau
    inv = 1.0 / (2.0 * sim.obs_dt)  # treeinfer.data.trajectories.velocity_from_displacement's

    def at(i):
        return jax.lax.dynamic_index_in_dim(x, i, axis=-1, keepdims=True)

    last = (3.0 * at(n_steps - 1) - 4.0 * at(n_steps - 2) + at(n_steps - 3)) * inv
    end = jnp.arange(x.shape[-1]) == n_steps - 1
    tau_dot = jnp.where(end, jnp.where(ro.stable[..., None], last, 0.0), ro.tau_dot)
    real_row = jnp.any(jnp.asarray(mask, bool), axis=-1)  # [B']
    return Rollout(tau=x, tau_dot=tau_dot, stable=ro.stable | ~real_row)


def data_observations(data: dict, dt: float) -> Observations:
    """:class:`Observations` back from :func:`observation_data`'s pytree (arrays may be traced;
    ``dt`` s is static)."""
    return Observations(data["force"], data["displacement"], data["velocity"], data["mask"], dt)


def _padded_basis(basis, mask: np.ndarray):
    """The force-noise basis of pulls padded to ``mask [B', T']`` (:func:`observation_data`)
    from the unpadded pulls' ``basis`` [B, T, T]: ``C`` is zero in the rows and columns of
    padded samples (force noise exists on real samples only, and the displacement before T
    does not depend on the force after it), so the padded eigenbasis is ``U`` beside the
    identity with eigenvalues 0 there, and a padded pull's is the identity. The same density
    as the Jacobian of the padded pulls would give, without computing it (a forward-mode pass
    of T' tangents per pull)."""
    from .force_noise_local import is_stacked, split, stack

    if is_stacked(basis):  # one reference per lobe (force_noise_local): each padded alike
        return stack(_padded_basis(b, mask) for b in split(basis))
    u, lam = np.asarray(basis.vectors), np.asarray(basis.values)
    b, t = lam.shape
    nb, nt = mask.shape
    vectors = np.broadcast_to(np.eye(nt), (nb, nt, nt)).copy()
    values = np.zeros((nb, nt))
    vectors[:b, :t, :t] = u
    values[:b, :t] = lam
    slope = None
    if basis.slope is not None:  # no force noise on padded samples: zero slope there
        slope = np.zeros((nb, nt, np.shape(basis.slope)[-1]))
        slope[:b, :t] = np.asarray(basis.slope)
    return type(basis)(
        vectors, values, (~np.asarray(mask, bool)).sum(axis=1), slope, basis.theta_ref
    )
