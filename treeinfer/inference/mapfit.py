"""A fast start: the MAP point by Levenberg–Marquardt, its Laplace approximation, and particles
drawn around it.

Particles that start uniformly in the prior box (the paper's initialisation) spend most of a
run travelling to the posterior. Here a few starting points (a Latin hypercube in the box) are
pushed to the posterior mode by a damped Gauss–Newton (Levenberg–Marquardt) iteration on the
simulator's residuals, the best one is kept, and the sampler starts from draws of the Laplace
approximation ``N(theta_map, H^-1)`` around it, so its iterations go into the posterior's shape.

The objective, in theta = [log Kp_1..R, log Kd_1..R] (optionally with log sigma appended), is
the negative log posterior ``nll(theta) - log_prior(theta)``. The likelihood is given as
residuals r(theta) (:class:`ResidualModel`) so its curvature is the generalised Gauss–Newton
matrix ``J^T H_outer J`` (no second derivatives of the simulator, positive semi-definite):

* ``kind="gaussian"``: Gaussian noise with known sigma, ``r = (tau_sim - tau_obs) / sigma``,
  ``nll = ||r||^2 / 2``, gradient ``J^T r``, curvature ``J^T J``.
* ``kind="gaussian_log_sigma"``: the same with sigma unknown, ``theta = [..., log sigma]``,
  ``r = tau_sim - tau_obs``, ``nll = e^{-2s} ||r||^2 / 2 + N s`` (flat prior on ``s = log sigma``);
  the (theta, s) block of the curvature is the exact Hessian of that expression in ``s``.
* ``kind="norm"``: the paper's Boltzmann loss, ``nll = sum_g ||r_g|| / kT`` over groups g (the
  displacement and velocity error of each trajectory); the Hessian of ``||r||`` in r is
  ``(I - u u^T) / ||r||`` with ``u = r / ||r||``, giving ``sum_g J_g^T (I - u_g u_g^T) J_g /
  (kT ||r_g||)``.

The prior enters through its exact gradient and Hessian (autodiff: it is cheap), the Hessian
projected onto the positive semi-definite cone for the steps and the Laplace covariance (the
smoothed box is flat inside and convex outside, so projection only matters for the learned
inequality prior).

The residual Jacobian comes from forward-mode sensitivities of the simulator (``jax.jacfwd``:
all D tangents in one pass, exact), or from central differences (``jacobian="fd"``: one batched
call at 2D + 1 points, the cheaper compile). LM runs on the host in NumPy (D is small): one
jitted program evaluates value, gradient and curvature at all starting points at once.

Why not ``scipy.optimize.least_squares`` or ``jaxopt.LevenbergMarquardt``: neither takes the
Boltzmann loss (a sum of norms, not of squares) or a prior curvature, and scipy would evaluate
one starting point at a time; the loop (:mod:`treeinfer.inference.lm`, shared with the batched fits
of
:mod:`treeinfer.inference.batch`) is 40 lines.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ConfigError
from .laplace import _inverse_psd, laplace_particles, norm_loss_covariance
from .lm import LMResult, levenberg_marquardt

__all__ = [
    "KINDS",
    "LMResult",
    "MapFit",
    "ResidualModel",
    "boltzmann_residuals",
    "fit_map",
    "fit_problem",
    "gaussian_residuals",
    "laplace_particles",
    "latin_hypercube",
    "levenberg_marquardt",
    "norm_loss_covariance",
    "problem_with_gradients",
]

KINDS = ("gaussian", "gaussian_log_sigma", "norm")


class ResidualModel(NamedTuple):
    """The likelihood as residuals (see the module docstring for the three kinds).

    residuals: ``theta [D] -> (r [G, K], ok)``: residual groups (rows) and whether the
      simulation behind them is valid (False: the point gets ``+inf``). For
      ``gaussian_log_sigma`` theta here excludes log sigma.
    kind: one of :data:`KINDS`.
    scale: kT (``norm``); ignored otherwise.
    n_obs: number of real residual entries N (``gaussian_log_sigma``; padding excluded).
    log_sigma_guess: starting log sigma (``gaussian_log_sigma``).
    """

    residuals: Callable
    kind: str
    scale: float = 1.0
    n_obs: int = 0
    log_sigma_guess: float = 0.0


class MapFit(NamedTuple):
    """Result of :func:`fit_map` (NumPy arrays).

    theta: [D] the best MAP point (D includes log sigma for ``gaussian_log_sigma``).
    cov: [D, D] Laplace covariance ``H^-1`` at ``theta``. hessian: [D, D] ``H``.
    neg_log_posterior: ``-log p(theta | data)`` up to a constant, at ``theta``.
    starts, finals: [S, D] starting and final points; values: [S] their final objective.
    converged: [S] whether each start met the tolerance. iterations: LM iterations run.
    lower, upper: [D_model] the prior box (theta units) the starts were drawn from.
    n_model: columns of theta that are model parameters (log Kp, log Kd).
    settings: options of the fit.
    norm_cov: [D, D] for ``kind="norm"`` only (else None): the Gaussian matched to the
      Boltzmann density's spread, :func:`norm_loss_covariance` (the Laplace ``cov`` is far too
      narrow there: the density is cone-shaped at a small-residual mode).
    """

    theta: np.ndarray
    cov: np.ndarray
    hessian: np.ndarray
    neg_log_posterior: float
    starts: np.ndarray
    finals: np.ndarray
    values: np.ndarray
    converged: np.ndarray
    iterations: int
    lower: np.ndarray
    upper: np.ndarray
    n_model: int
    settings: dict
    norm_cov: np.ndarray | None = None


# ---- residual models of the simulator ------------------------------------------------------
def _rollout_one(sim, obs, grasp_fraction):
    from ..model.gains import gains_from_theta
    from ..sim import simulate

    forces = jnp.asarray(obs.force)

    def rollout(theta):
        kp, kd = gains_from_theta(theta[None, :], sim.n_joints)
        out = simulate(sim, kp, kd, forces, grasp_fraction)
        return out.tau[0], out.tau_dot[0], jnp.all(out.stable[0])

    return rollout


def boltzmann_residuals(sim, obs, kT: float, grasp_fraction=None) -> ResidualModel:
    """The paper's loss ``sum_b ||tau_b - tau_obs_b|| + ||tau_dot_b - tau_dot_obs_b||`` over
    ``kT`` as :class:`ResidualModel` (``kind="norm"``, 2B groups of T masked entries, metres and
    metres per second). Matches :func:`treeinfer.model.likelihood.boltzmann_log_likelihood`."""
    from ..model.temperature import check_kT

    kT = check_kT(kT)
    rollout = _rollout_one(sim, obs, grasp_fraction)
    mask = np.asarray(obs.mask, float)
    disp, vel = np.asarray(obs.displacement), np.asarray(obs.velocity)

    def residuals(theta):
        tau, tau_dot, ok = rollout(theta)
        m = jnp.asarray(mask, tau.dtype)
        dpos = (tau - jnp.asarray(disp, tau.dtype)) * m
        dvel = (tau_dot - jnp.asarray(vel, tau.dtype)) * m
        return jnp.concatenate([dpos, dvel], axis=0), ok

    return ResidualModel(residuals, "norm", scale=kT)


def gaussian_residuals(sim, obs, sigma: float | None = None, grasp_fraction=None) -> ResidualModel:
    """Gaussian displacement noise: ``r = (tau_sim - tau_obs) / sigma`` ([B, T], masked) for a
    known ``sigma`` (m), or with ``sigma=None`` the raw differences and ``log sigma`` fitted as
    an extra last column of theta (``kind="gaussian_log_sigma"``)."""
    if sigma is not None and not (
        isinstance(sigma, (int, float)) and math.isfinite(sigma) and sigma > 0
    ):
        raise ConfigError(f"sigma: must be a positive number of metres, got {sigma!r}")
    rollout = _rollout_one(sim, obs, grasp_fraction)
    mask = np.asarray(obs.mask, float)
    disp = np.asarray(obs.displacement)
    inv = 1.0 if sigma is None else 1.0 / float(sigma)

    def residuals(theta):
        tau, _, ok = rollout(theta)
        r = (tau - jnp.asarray(disp, tau.dtype)) * jnp.asarray(mask * inv, tau.dtype)
        return r, ok

    if sigma is not None:
        return ResidualModel(residuals, "gaussian")
    spread = float(np.std(disp[mask > 0])) if mask.any() else 1.0
    return ResidualModel(
        residuals,
        "gaussian_log_sigma",
        n_obs=int(mask.sum()),
        log_sigma_guess=math.log(max(0.05 * spread, 1e-6)),
    )


# ---- value, gradient and Gauss-Newton curvature --------------------------------------------
def _jacobian(residual_fn, theta, method: str, rel_step: float | None):
    """(r [G, K], ok, J [G, K, D]) at ``theta [D]``."""
    if method == "jvp":

        def with_aux(th):
            r, ok = residual_fn(th)
            return r, (r, ok)

        jac, (r, ok) = jax.jacfwd(with_aux, has_aux=True)(theta)
        return r, ok, jac
    from ..model.gradients import default_rel_step

    dim = theta.shape[0]
    h = default_rel_step(theta.dtype) if rel_step is None else rel_step
    eye = h * jnp.eye(dim, dtype=theta.dtype)
    points = jnp.concatenate([theta[None], theta + eye, theta - eye])
    rs, oks = jax.vmap(residual_fn)(points)
    two_h = jnp.diagonal((theta + eye) - (theta - eye))
    jac = jnp.moveaxis((rs[1 : dim + 1] - rs[dim + 1 :]) / two_h[:, None, None], 0, -1)
    return rs[0], jnp.all(oks), jac


def _psd(h):
    w, v = jnp.linalg.eigh(0.5 * (h + h.T))
    return (v * jnp.maximum(w, 0.0)) @ v.T


def _terms_one(model: ResidualModel, log_prior, method, rel_step, theta):
    """(objective, gradient [D], curvature [D, D], (gram [G, Dm, Dm], r2 [G])) of ``-log
    posterior`` at ``theta [D]``; ``gram_g = J_g^T J_g`` and ``r2_g = ||r_g||^2`` per residual
    group (for :func:`norm_loss_covariance`)."""
    n_model = theta.shape[0] - (1 if model.kind == "gaussian_log_sigma" else 0)
    th = theta[:n_model]
    r, ok, jac = _jacobian(model.residuals, th, method, rel_step)
    r = r.reshape(-1, r.shape[-1])
    jac = jac.reshape(r.shape[0], r.shape[1], n_model)
    if model.kind == "gaussian":
        flat, jf = r.reshape(-1), jac.reshape(-1, n_model)
        value, grad, curv = 0.5 * flat @ flat, jf.T @ flat, jf.T @ jf
    elif model.kind == "norm":
        norms = jnp.sqrt(jnp.sum(r**2, axis=-1) + jnp.finfo(r.dtype).tiny)  # [G]
        u = r / norms[:, None]
        ju = jnp.einsum("gk,gkd->gd", u, jac)  # u_g^T J_g
        value = jnp.sum(norms) / model.scale
        grad = jnp.sum(ju, axis=0) / model.scale
        jtj = jnp.einsum("gkd,gke->gde", jac, jac)
        curv = jnp.sum((jtj - ju[:, :, None] * ju[:, None, :]) / norms[:, None, None], 0)
        curv = curv / model.scale
    else:  # gaussian_log_sigma
        s = theta[-1]
        w = jnp.exp(-2.0 * s)
        flat, jf = r.reshape(-1), jac.reshape(-1, n_model)
        ss, jtr = flat @ flat, jf.T @ flat
        value = 0.5 * w * ss + model.n_obs * s
        grad = jnp.concatenate([w * jtr, jnp.atleast_1d(model.n_obs - w * ss)])
        top = jnp.concatenate([w * jf.T @ jf, -2.0 * w * jtr[:, None]], axis=1)
        bottom = jnp.concatenate([-2.0 * w * jtr, jnp.atleast_1d(2.0 * w * ss)])[None, :]
        curv = jnp.concatenate([top, bottom], axis=0)
    if log_prior is not None:
        nlp = lambda x: -log_prior(x[None, :])[0]
        pv, pg = jax.value_and_grad(nlp)(th)
        ph = _psd(jax.hessian(nlp)(th))
        value = value + pv
        grad = grad.at[:n_model].add(pg)
        curv = curv.at[:n_model, :n_model].add(ph)
    ok = ok & jnp.isfinite(value) & jnp.all(jnp.isfinite(grad)) & jnp.all(jnp.isfinite(curv))
    value = jnp.where(ok, value, jnp.inf)
    grad = jnp.where(ok, grad, 0.0)
    curv = jnp.where(ok, curv, 0.0)
    groups = (jnp.einsum("gkd,gke->gde", jac, jac), jnp.sum(r**2, axis=-1))
    return value, grad, curv, groups


def latin_hypercube(n: int, lower, upper, seed: int = 0) -> np.ndarray:
    """``[n, D]`` Latin-hypercube points in the box ``[lower, upper]`` (``scipy.stats.qmc``)."""
    from scipy.stats import qmc

    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    u = qmc.LatinHypercube(d=lower.size, seed=np.random.default_rng(seed)).random(n)
    return qmc.scale(u, lower, upper)


def fit_map(
    model: ResidualModel,
    log_prior: Callable | None,
    lower,
    upper,
    n_starts: int = 8,
    seed: int = 0,
    starts=None,
    jacobian: str = "jvp",
    rel_step: float | None = None,
    max_iterations: int = 60,
    tolerance: float = 1e-6,
    max_step: float = 1.0,
    agree: int | None = None,
) -> MapFit:
    """Levenberg–Marquardt from ``n_starts`` Latin-hypercube points of the prior box.

    Args:
      model: the likelihood as residuals (:func:`boltzmann_residuals`, :func:`gaussian_residuals`
        or your own :class:`ResidualModel`).
      log_prior: batched ``theta [P, D_model] -> [P]`` (e.g. ``problem.log_prior``) or None.
      lower, upper: [D_model] box (theta units) for the starting points.
      starts: [S, D_model] explicit starting points instead of the hypercube.
      jacobian: ``"jvp"`` (forward-mode sensitivities, exact) or ``"fd"`` (central differences).
      max_iterations: LM iterations (each is one batched evaluation at all starts).
      tolerance: stop a start when its objective falls by less than ``tolerance * (1 + |f|)``
        on an accepted step, or its step is below ``tolerance`` in every coordinate.
      max_step: largest change of any coordinate in one step (log units: a factor e).
      agree: stop early once this many starts have converged to the best value found so far
        (objective within ``sqrt(tolerance) * (1 + |f|)`` of the lowest of all starts): that
        many independent starts ending at one minimum, with no start lower, is taken as the
        mode (None: run until every start has converged or ``max_iterations``). Starts still
        travelling are abandoned, so a lower mode that only they would reach is missed.

    Returns a :class:`MapFit`; its ``cov`` is ``H^-1`` at the best point, with ``H`` the
    Gauss–Newton curvature of the likelihood plus the prior's (PSD-projected) Hessian.
    """
    if jacobian not in ("jvp", "fd"):
        raise ConfigError(f"jacobian: expected 'jvp' or 'fd', got {jacobian!r}")
    if model.kind not in KINDS:
        raise ConfigError(
            f"residual model kind: expected one of {', '.join(KINDS)}, got {model.kind!r}"
        )
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    if lower.shape != upper.shape or lower.ndim != 1 or np.any(~(upper > lower)):
        raise ConfigError("lower/upper: need two [D] arrays with upper > lower")
    if agree is not None and not (isinstance(agree, int) and agree >= 1):
        raise ConfigError(f"agree: must be an integer >= 1 or None, got {agree!r}")
    if starts is None:
        if not (isinstance(n_starts, int) and n_starts >= 1):
            raise ConfigError(f"n_starts: must be an integer >= 1, got {n_starts!r}")
        starts = latin_hypercube(n_starts, lower, upper, seed)
    starts = np.atleast_2d(np.asarray(starts, float))
    if starts.shape[1] != lower.size:
        raise ConfigError(f"starts: expected {lower.size} columns, got {starts.shape[1]}")
    if model.kind == "gaussian_log_sigma":
        starts = np.concatenate([starts, np.full((len(starts), 1), model.log_sigma_guess)], 1)
    dtype = jnp.asarray(0.0).dtype
    terms = jax.jit(jax.vmap(lambda th: _terms_one(model, log_prior, jacobian, rel_step, th)))

    def evaluate(theta):
        f, g, h, (gram, r2) = terms(jnp.asarray(theta, dtype))
        return f, g, h, gram, r2

    lm = levenberg_marquardt(
        evaluate, starts, max_iterations, tolerance, max_step, agree, n_extras=2
    )
    theta, f, h, (gram, r2), converged, iterations = lm
    best = int(np.argmin(np.where(np.isfinite(f), f, np.inf)))
    if not np.isfinite(f[best]):
        from ..errors import SimulationError

        raise SimulationError(
            "fit_map: every starting point gave an unstable simulation; narrow "
            "the prior box or check the data's units"
        )
    hess = 0.5 * (h[best] + h[best].T)
    cov = _inverse_psd(hess)
    norm_cov = (
        norm_loss_covariance(gram[best], r2[best], model.scale) if model.kind == "norm" else None
    )
    settings = {
        "n_starts": len(starts),
        "seed": seed,
        "jacobian": jacobian,
        "kind": model.kind,
        "max_iterations": max_iterations,
        "tolerance": tolerance,
        "max_step": max_step,
        "agree": agree,
    }
    return MapFit(
        theta[best].copy(),
        cov,
        hess,
        float(f[best]),
        starts,
        theta,
        f,
        converged,
        iterations,
        lower,
        upper,
        lower.size,
        settings,
        norm_cov,
    )


def fit_problem(
    problem, likelihood: str = "boltzmann", sigma: float | None = None, **options
) -> MapFit:
    """:func:`fit_map` on a :class:`treeinfer.inference.problem.Problem`: its simulator, data, kT,
    prior and box. ``likelihood="gaussian"`` uses displacement noise ``sigma`` (m; None: fitted)."""
    gf = problem.settings.get("grasp_fraction")
    if gf is not None and math.isclose(gf, problem.tree.grasp_fraction):
        gf = None  # the simulator's own grasp site: the likelihood's exact path
    if likelihood == "boltzmann":
        model = boltzmann_residuals(problem.sim, problem.obs, problem.kT, gf)
    elif likelihood == "gaussian":
        model = gaussian_residuals(problem.sim, problem.obs, sigma, gf)
    else:
        raise ConfigError(f"likelihood: expected 'boltzmann' or 'gaussian', got {likelihood!r}")
    return fit_map(model, problem.log_prior, problem.lower, problem.upper, **options)


def problem_with_gradients(problem, method: str = "jvp") -> Any:
    """``problem`` with its likelihood gradient computed by ``method`` (``"fd"`` or ``"jvp"``)
    and the choice recorded in ``problem.settings["gradient"]``.

    A bridge until ``make_problem`` takes ``gradient="jvp"`` itself (the integrator wires it)."""
    import dataclasses

    from ..model.gradients import autodiff_value_and_grad, likelihood_value_and_grad, mask_nonfinite

    lik_vg = likelihood_value_and_grad(
        problem.log_likelihood, method, problem.settings.get("rel_step")
    )
    prior_vg = autodiff_value_and_grad(problem.log_prior)

    def value_and_grad(theta):
        (a, ga), (b, gb) = lik_vg(theta), prior_vg(theta)
        return mask_nonfinite(a + b, ga + gb)

    return dataclasses.replace(
        problem, value_and_grad=value_and_grad, settings={**problem.settings, "gradient": method}
    )
