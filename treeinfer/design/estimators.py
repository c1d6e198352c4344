"""Estimators of :mod:`treeinfer.design` (generic in the forward model) and the simulator as
that forward model: FD sensitivities, the Laplace EIG, the linearised target variance, nested
Monte Carlo, and the one jitted program that scores all candidates."""

from __future__ import annotations

import inspect
from collections.abc import Callable, Sequence
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ConfigError
from ..model.gradients import default_rel_step
from ..model.likelihood import gains_from_theta
from ..sim import Simulator, simulate
from .candidates import Candidate

ForwardFn = Callable[[jax.Array], tuple[jax.Array, jax.Array]]
"""``theta [N, D] -> (tau [N, C, T] m, ok [N, C] bool)``: the C candidate pulls at N points."""


# ==== estimators (generic in the forward model) ===================================================
def particle_covariance(theta, valid=None) -> np.ndarray:
    """[D, D] covariance (``ddof=1``) of the valid particles ``theta [P, D]``."""
    theta = np.asarray(theta, float)
    if valid is not None:
        theta = theta[np.asarray(valid, bool)]
    if theta.ndim != 2 or theta.shape[0] < 2:
        raise ConfigError(
            f"particles: need at least 2 valid particles [P, D], got shape {theta.shape}"
        )
    return np.atleast_2d(np.cov(theta, rowvar=False))


def fd_jacobian(forward: ForwardFn, theta: jax.Array, rel_step: float | None = None):
    """Central-difference sensitivities of ``forward`` at ``theta [M, D]`` (log units).

    Evaluates ``forward`` **once** on the ``M * 2D`` points ``theta_m +- h e_d`` and returns
    ``(J [M, C, T, D], ok [M, C])`` with ``J[..., d] = (tau(+h e_d) - tau(-h e_d)) / 2h``
    (the step as represented in floating point); ``ok`` is False where any of the 2D rollouts
    of that particle and candidate was unstable (J is 0 there). ``rel_step`` defaults to
    ``eps ** (1/3)`` of theta's dtype (a relative step in the gains, since theta is a log)."""
    theta = jnp.asarray(theta)
    m, d = theta.shape
    h = default_rel_step(theta.dtype) if rel_step is None else float(rel_step)
    eye = h * jnp.eye(d, dtype=theta.dtype)
    plus = theta[:, None, :] + eye[None]  # [M, D, D]
    minus = theta[:, None, :] - eye[None]
    pts = jnp.concatenate([plus, minus], axis=1).reshape(m * 2 * d, d)
    tau, ok = forward(pts)
    c, t = tau.shape[1], tau.shape[2]
    tau = tau.reshape(m, 2, d, c, t)
    ok = jnp.all(ok.reshape(m, 2, d, c), axis=(1, 2))
    two_h = jnp.diagonal(plus - minus, axis1=1, axis2=2)  # [M, D]
    jac = (tau[:, 0] - tau[:, 1]) / two_h[:, :, None, None]  # [M, D, C, T]
    jac = jnp.where(ok[:, None, :, None], jac, 0.0)
    return jnp.moveaxis(jac, 1, -1), ok


def _sqrt_cov(cov) -> jax.Array:
    """``S`` [D, D] with ``S S^T = cov`` (symmetric square root; eigenvalues clipped at 0, so a
    rank-deficient particle covariance is fine: no information is counted along its null space)."""
    lam, v = jnp.linalg.eigh(jnp.asarray(cov))
    return v * jnp.sqrt(jnp.clip(lam, 0.0, None))[None, :]


def _weighted_mean(x, ok):
    """Mean of ``x [M, C]`` over the particles with ``ok [M, C]``; NaN where none is ok."""
    okf = ok.astype(x.dtype)
    n = jnp.sum(okf, axis=0)
    return jnp.where(n > 0, jnp.sum(jnp.where(ok, x, 0.0), axis=0) / jnp.maximum(n, 1.0), jnp.nan)


def laplace_eig(jac: jax.Array, cov, sigma_x: float, ok=None) -> jax.Array:
    """``0.5 mean_m log det(I + S^T F_mc S)`` [C] nats; ``F = J^T J / sigma_x^2``, ``S S^T = cov``.

    jac: [M, C, T, D] m per log unit; cov: [D, D]; ok: [M, C] (particles left out of the mean
    where False; default all). ``det(I + Sigma F) = det(I + S^T F S)``, the symmetric form."""
    s = _sqrt_cov(cov).astype(jac.dtype)
    js = jnp.einsum("mctd,de->mcte", jac, s) / sigma_x  # whitened sensitivities
    a = jnp.einsum("mcte,mctf->mcef", js, js)
    eye = jnp.eye(a.shape[-1], dtype=a.dtype)
    _, logdet = jnp.linalg.slogdet(eye + a)
    ok = jnp.ones(logdet.shape, bool) if ok is None else jnp.asarray(ok)
    return 0.5 * _weighted_mean(logdet, ok)


def target_variance(jac: jax.Array, jac_target: jax.Array, cov, sigma_x: float, ok=None):
    """Linearised predictive variance of a target before and after each candidate.

    jac: [M, C, T, D] candidate sensitivities; jac_target: [M, T', D] the target's (m per log
    unit); cov: [D, D]; ok: [M, C]. Returns ``(before [C], after [C])`` in m^2: the mean over the
    target's T' samples of ``G_t Sigma G_t^T`` and ``G_t Sigma'_c G_t^T`` with
    ``Sigma'_c = S (I + S^T F_c S)^-1 S^T``, averaged over the ok particles."""
    s = _sqrt_cov(cov).astype(jac.dtype)
    js = jnp.einsum("mctd,de->mcte", jac, s) / sigma_x
    a = jnp.einsum("mcte,mctf->mcef", js, js)  # S^T F S
    eye = jnp.eye(a.shape[-1], dtype=a.dtype)
    gs = jnp.einsum("mtd,de->mte", jac_target, s)  # [M, T', D]
    before = jnp.mean(jnp.sum(gs**2, -1), -1)  # [M]
    # G S (I + A)^-1 S^T G^T, by a solve (I + A is SPD and well conditioned)
    gs_t = jnp.broadcast_to(
        jnp.swapaxes(gs, -1, -2)[:, None], a.shape[:3] + gs.shape[1:2]
    )  # [M, C, D, T']
    sol = jnp.linalg.solve(eye + a, gs_t)
    after = jnp.mean(jnp.einsum("mte,mcet->mct", gs, sol), -1)  # [M, C]
    ok = jnp.ones(after.shape, bool) if ok is None else jnp.asarray(ok)
    return _weighted_mean(jnp.broadcast_to(before[:, None], after.shape), ok), _weighted_mean(
        after, ok
    )


def nested_mc_eig(
    forward: ForwardFn, theta: jax.Array, sigma_x: float, key: jax.Array
) -> jax.Array:
    """Prior-contrastive nested Monte Carlo EIG [C] nats with the particles as prior samples.

    ``mean_n [log p(y_n | theta_n) - log mean_m p(y_n | theta_m)]``, ``y_n = tau(theta_n) + eps_n``;
    Gaussian constants cancel. One ``forward`` call on ``theta [P, D]`` (``P * C`` rollouts);
    particles unstable for a candidate are left out of that candidate's sums. A lower bound on
    the EIG under the particle prior that converges as ``P`` grows; never above ``log P``."""
    tau, ok = forward(jnp.asarray(theta))  # [P, C, T], [P, C]
    return nested_mc_eig_from_rollouts(tau, ok, sigma_x, key)


def nested_mc_eig_from_rollouts(
    tau: jax.Array, ok: jax.Array, sigma_x: float, key: jax.Array
) -> jax.Array:
    """:func:`nested_mc_eig` given the rollouts ``tau [P, C, T]`` m and ``ok [P, C]``."""
    eps = sigma_x * jax.random.normal(key, tau.shape, tau.dtype)
    y = tau + eps
    # squared distances ||y_n - tau_m||^2 for all n, m per candidate: [C, N, M]
    yy = jnp.sum(y**2, -1).T[:, :, None]
    tt = jnp.sum(tau**2, -1).T[:, None, :]
    yt = jnp.einsum("nct,mct->cnm", y, tau)
    d2 = jnp.maximum(yy + tt - 2 * yt, 0.0)
    log_lik = -d2 / (2 * sigma_x**2)  # [C, N, M]
    okc = ok.T  # [C, P]
    log_lik = jnp.where(okc[:, None, :], log_lik, -jnp.inf)
    n_ok = jnp.sum(okc, -1).astype(tau.dtype)
    log_marg = (
        jax.scipy.special.logsumexp(log_lik, axis=-1) - jnp.log(jnp.maximum(n_ok, 1.0))[:, None]
    )
    own = -jnp.sum(eps**2, -1).T / (2 * sigma_x**2)  # [C, N]: log p(y_n | theta_n)
    per = jnp.where(okc, own - log_marg, 0.0)
    return jnp.where(n_ok > 0, jnp.sum(per, -1) / jnp.maximum(n_ok, 1.0), jnp.nan)


# ==== the simulator as the forward model ==========================================================
def _accepts_direction() -> bool:
    return "direction" in inspect.signature(simulate).parameters


def _directions_array(candidates: Sequence[Candidate], sim: Simulator):
    if all(c.direction is None for c in candidates):
        return None
    if not _accepts_direction():
        raise ConfigError(
            "directions: this treeinfer's simulator pulls along gravity only (simulate() has no "
            "direction= argument yet); leave --directions out"
        )
    g = tuple(float(v) for v in sim.gravity_dir)
    return np.asarray([g if c.direction is None else c.direction for c in candidates], float)


def simulator_forward(sim: Simulator, forces, grasp_fraction, direction=None) -> ForwardFn:
    """``forward(theta [N, 2R]) -> (tau [N, C, T], stable [N, C])`` of the C profiles
    ``forces [C, T]`` N at ``grasp_fraction [C]`` (and ``direction [C, 3]``, passed to
    :func:`~treeinfer.sim.simulate` as ``direction=`` when given), one batched call."""
    forces = jnp.asarray(forces)
    grasp = jnp.asarray(grasp_fraction)
    extra = {} if direction is None else {"direction": jnp.asarray(direction)}

    def forward(theta):
        kp, kd = gains_from_theta(theta, sim.n_joints)
        r = simulate(sim, kp, kd, forces, grasp, **extra)
        return r.tau, r.stable

    return forward


@partial(jax.jit, static_argnums=(0, 6))
def _laplace_scores(
    sim, theta, cov, forces, grasp, direction, rel_step, sigma_x, target, onehot=None
):
    """One compiled program: the FD sensitivities of all candidates (and the target) at all
    subsampled particles in one ``simulate`` call, and the scores. ``onehot`` [D]: score the
    variance reduction of that parameter instead (its sensitivity is the unit vector)."""
    if target is not None:  # the target rides along as one more profile of the same batch
        t_forces, t_grasp, t_dir = target
        forces = jnp.concatenate([forces, t_forces[None]], 0)
        grasp = jnp.concatenate([grasp, t_grasp[None]], 0)
        if direction is not None:
            direction = jnp.concatenate([direction, t_dir[None]], 0)
    jac, ok = fd_jacobian(simulator_forward(sim, forces, grasp, direction), theta, rel_step)
    if onehot is not None:
        g = jnp.broadcast_to(onehot.astype(jac.dtype), (jac.shape[0], 1, jac.shape[-1]))
        return jnp.stack(target_variance(jac, g, cov, sigma_x, ok)), jnp.mean(ok, 0)
    if target is None:
        return laplace_eig(jac, cov, sigma_x, ok), jnp.mean(ok, 0)
    ok_t = ok[:, -1:]
    jac_c, ok_c = jac[:, :-1], ok[:, :-1] & ok_t
    before, after = target_variance(jac_c, jac[:, -1], cov, sigma_x, ok_c)
    return jnp.stack([before, after]), jnp.mean(ok_c, 0)


@partial(jax.jit, static_argnums=0)
def _nmc_scores(sim, theta, forces, grasp, direction, sigma_x, key):
    tau, ok = simulator_forward(sim, forces, grasp, direction)(theta)
    return nested_mc_eig_from_rollouts(tau, ok, sigma_x, key), jnp.mean(ok, 0)
