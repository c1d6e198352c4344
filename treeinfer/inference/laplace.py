"""Particles around a MAP fit (``--init laplace``): the Laplace approximation, and for the
paper's Boltzmann loss (a sum of norms, cone-shaped at its mode) the Gaussian matched to the
linearised loss. Split from :mod:`treeinfer.inference.mapfit`, which re-exports these names."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ConfigError

__all__ = [
    "ProblemLaplace",
    "laplace_particles",
    "mh_proposal",
    "norm_loss_covariance",
    "problem_laplace",
    "problem_laplace_particles",
    "value_hessian",
]


def norm_loss_covariance(
    gram, r2, kT: float, iterations: int = 200, rtol: float = 1e-8
) -> np.ndarray:
    """Covariance ``S [D, D]`` of the Gaussian matched to ``exp(-sum_g ||r_g + J_g d|| / kT)``.

    Why not the Laplace ``H^-1``: the Boltzmann loss is a sum of norms; at a mode whose
    residuals are small (good data, small noise) its curvature ``J^T (I - u u^T) J / ||r||``
    grows without bound and ``H^-1`` is far narrower than the density (the density is a cone
    there, not a Gaussian). This is the variational (iteratively reweighted) Gaussian of the
    linearised loss instead: each norm is replaced by its quadratic upper bound at its expected
    size, ``||x|| <= (||x||^2 + s^2) / (2 s)``, with ``s_g^2 = E||r_g + J_g d||^2 = ||r_g||^2 +
    tr(J_g^T J_g S)`` under ``d ~ N(0, S)``, which gives the fixed point

        S = (sum_g J_g^T J_g / (kT s_g))^-1,  s_g = sqrt(||r_g||^2 + tr(J_g^T J_g S)).

    For one group with ``r = 0`` and a full-rank ``J`` in ``D`` dimensions the exact covariance
    of ``exp(-||J d|| / kT)`` is ``(D + 1) kT^2 (J^T J)^-1`` and the fixed point gives ``D kT^2
    (J^T J)^-1`` (``tests/test_mapfit.py`` checks both); the prior is not included (add the
    box's precision as :func:`laplace_particles` does).

    Args: gram [G, D, D] ``J_g^T J_g``; r2 [G] ``||r_g||^2`` at the mode; kT the temperature.
    """
    gram = np.asarray(gram, float)
    r2 = np.asarray(r2, float)
    dim = gram.shape[-1]
    total = gram.sum(0)
    cov = dim * kT**2 * _inverse_psd(total) / len(gram)  # equal shares: a starting point
    for _ in range(iterations):
        s = np.sqrt(r2 + np.maximum(np.einsum("gde,ed->g", gram, cov), 0.0)) + 1e-300
        new = _inverse_psd(np.einsum("gde,g->de", gram, 1.0 / (kT * s)))
        done = np.max(np.abs(new - cov)) <= rtol * np.max(np.abs(new))
        cov = new
        if done:
            break
    return 0.5 * (cov + cov.T)


def _inverse_psd(h: np.ndarray) -> np.ndarray:
    """``h^-1`` for a symmetric PSD ``h``; directions with no curvature get a large but finite
    variance (1e6 times the largest finite one), so draws stay finite."""
    w, v = np.linalg.eigh(h)
    floor = max(float(w.max()), 1e-300) * 1e-12
    return (v / np.maximum(w, floor)) @ v.T


def fit_precision(fit, use_norm: bool, box_precision: bool) -> np.ndarray:
    """``[D, D]`` precision of a MAP fit's Gaussian: the Boltzmann-matched one (``use_norm``:
    the inverse of ``fit.norm_cov`` on the model columns; the norm loss has no sigma) or the
    Hessian, plus, with ``box_precision``, a uniform-box's variance ``width^2 / 12`` per model
    column as extra precision."""
    if use_norm:
        h = np.zeros((len(fit.theta),) * 2)
        m = fit.n_model
        h[:m, :m] = _inverse_psd(np.asarray(fit.norm_cov, float))
    else:
        h = np.array(fit.hessian, float)
    if box_precision:
        width = np.asarray(fit.upper, float) - np.asarray(fit.lower, float)
        idx = np.arange(fit.n_model)
        h[idx, idx] += 12.0 / width**2
    return h


def particle_covariance(fit, box_precision: bool = True, covariance: str = "auto") -> np.ndarray:
    """``[D, D]`` covariance :func:`laplace_particles` draws with (at ``scale`` 1): the inverse
    of :func:`fit_precision` (``covariance`` as there)."""
    use_norm = covariance == "norm" or (covariance == "auto" and fit.norm_cov is not None)
    return _inverse_psd(fit_precision(fit, use_norm, box_precision))


def laplace_particles(
    key,
    fit,  # treeinfer.inference.mapfit.MapFit (not imported: mapfit imports this module)
    n: int,
    scale: float = 1.0,
    box_precision: bool = True,
    covariance: str = "auto",
) -> jax.Array:
    """``[n, D]`` draws of ``N(fit.theta, scale^2 C)`` around the MAP point.

    ``covariance``: ``"laplace"`` (``C = H^-1``, the Laplace approximation), ``"norm"``
    (``fit.norm_cov``, the Gaussian matched to the Boltzmann loss's cone-shaped density, see
    :func:`norm_loss_covariance`) or ``"auto"`` (``"norm"`` when the fit has it, i.e. for the
    Boltzmann loss, else ``"laplace"``).

    ``box_precision=True`` adds the precision ``12 / width^2`` of the uniform over the prior box
    (a Gaussian with the box's variance) to the model columns before inverting, so directions
    the data leave unidentified (no curvature: the smoothed box is flat inside) are drawn with
    the prior's spread instead of an unbounded one. ``key``: a JAX key."""
    if not (isinstance(n, (int, np.integer)) and n >= 1):
        raise ConfigError(f"n: must be an integer >= 1, got {n!r}")
    if not (scale > 0):
        raise ConfigError(f"scale: must be > 0, got {scale!r}")
    if covariance not in ("auto", "laplace", "norm"):
        raise ConfigError(f"covariance: 'auto', 'laplace' or 'norm', got {covariance!r}")
    if covariance == "norm" and fit.norm_cov is None:
        raise ConfigError("covariance='norm': the fit has no norm_cov (not a Boltzmann loss)")
    cov = particle_covariance(fit, box_precision, covariance) * float(scale) ** 2
    chol = np.linalg.cholesky(cov + 1e-12 * np.eye(len(cov)) * np.trace(cov) / len(cov))
    z = jax.random.normal(key, (int(n), len(fit.theta)))
    return jnp.asarray(fit.theta) + z @ jnp.asarray(chol.T, z.dtype)


# ---- treeinfer problems ------------------------------------------------------------------------
# Any problem (static model, stiffness only, a taper tie, noise columns): the MAP of its own
# log-density and a Hessian from its values. The Levenberg-Marquardt fit of
# treeinfer.inference.mapfit needs the paper's residuals; this needs only ``problem.log_density``
# (batched) and ``problem.value_and_grad``.


class ProblemLaplace(NamedTuple):
    """The Laplace approximation of a problem's posterior.

    Attributes: theta [D] the MAP (theta units); cov [D, D] the covariance (inverse of the
    Hessian of ``-log_density`` at the MAP, plus the box's precision where asked);
    log_density the value at the MAP; steps [D] the difference steps of the Hessian; n_evals
    the log-density evaluations spent."""

    theta: np.ndarray
    cov: np.ndarray
    log_density: float
    steps: np.ndarray
    n_evals: int


CHUNK = 64  # points per log-density call: one batch shape, so a jitted density compiles once


def _values(problem, theta: np.ndarray) -> np.ndarray:
    """``[N]`` log-densities of ``theta [N, D]`` in calls of exactly :data:`CHUNK` points (the
    last padded with copies of its first point); -inf where not finite."""
    theta = np.atleast_2d(np.asarray(theta, float))
    out = []
    for a in range(0, len(theta), CHUNK):
        part = theta[a : a + CHUNK]
        pad = np.concatenate([part, np.repeat(part[:1], CHUNK - len(part), 0)])
        out.append(np.asarray(problem.log_density(jnp.asarray(pad)), float)[: len(part)])
    out = np.concatenate(out)
    return np.where(np.isfinite(out), out, -np.inf)


def value_hessian(problem, theta, steps) -> np.ndarray:
    """``[D, D]`` Hessian of ``problem.log_density`` at ``theta [D]`` by central differences
    of its **values** with per-coordinate ``steps [D]`` (one batched call of ``1 + 2D^2``
    points): ``H_ii = (f(+h_i) - 2 f + f(-h_i)) / h_i^2``, ``H_ij = (f(++)-f(+-)-f(-+)+f(--)) /
    (4 h_i h_j)``. Values, not the gradient: the likelihood's gradient is itself a finite
    difference, and a step at the posterior's own scale averages the float32 noise away."""
    x = np.asarray(theta, float)
    h = np.asarray(steps, float)
    d = x.size
    pts = [x]
    for i in range(d):
        for s in (1, -1):
            pts.append(x + s * h[i] * np.eye(d)[i])
    pairs = [(i, j) for i in range(d) for j in range(i + 1, d)]
    for i, j in pairs:
        for si, sj in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
            pts.append(x + si * h[i] * np.eye(d)[i] + sj * h[j] * np.eye(d)[j])
    f = _values(problem, np.stack(pts))
    hess = np.zeros((d, d))
    for i in range(d):
        hess[i, i] = (f[1 + 2 * i] - 2 * f[0] + f[2 + 2 * i]) / h[i] ** 2
    base = 1 + 2 * d
    for k, (i, j) in enumerate(pairs):
        pp, pm, mp, mm = f[base + 4 * k : base + 4 * k + 4]
        hess[i, j] = hess[j, i] = (pp - pm - mp + mm) / (4 * h[i] * h[j])
    return hess


def best_local_fit(objective, starts, values, order, bounds, max_iterations: int):
    """``(result, n_evals)``: the best of scipy L-BFGS-B minimisations of ``objective`` (value and
    gradient) from ``starts[k]`` for ``k`` in ``order`` whose screening ``values[k]`` is finite,
    within ``bounds``; ``n_evals`` counts the objective's evaluations. Shared by the generic
    and the static model's exact Laplace fits."""
    from scipy.optimize import minimize

    best, n_evals = None, 0
    for k in order:
        if not np.isfinite(values[k]):
            continue
        res = minimize(
            objective,
            starts[k],
            jac=True,
            method="L-BFGS-B",
            bounds=bounds,
            options={"maxiter": int(max_iterations)},
        )
        n_evals += int(res.nfev)
        if best is None or res.fun < best.fun:
            best = res
    return best, n_evals


def problem_laplace(
    problem,
    n_starts: int = 64,
    n_local: int = 3,
    seed: int = 0,
    max_iterations: int = 200,
    box_precision: bool = True,
    extra=None,
) -> ProblemLaplace:
    """MAP and Laplace covariance of ``problem`` (any
    :class:`~treeinfer.inference.problem.Problem`).

    The MAP: the best ``n_local`` of ``n_starts`` uniform random points in the prior box (one
    batched call), each polished by scipy's L-BFGS-B on ``-log_density`` with the problem's own
    gradient (``value_and_grad``), inside the box widened by half its width. The covariance:
    the inverse of ``-H`` from :func:`value_hessian`, its steps set twice (first a hundredth of
    each box width, then each coordinate's Laplace std, so that the differences span the
    posterior's own width); ``box_precision`` adds ``12 / width^2`` (a uniform over the box) so
    directions the data leave flat are drawn with the prior's spread.

    ``extra`` ``[K, D]``: start points of a fit already made (e.g. the grasp-point MAP of a problem
    with observation channels), screened with the random ones (the best ``n_local`` of all are
    polished).

    Raises:
        ConfigError: no start with a finite log-density.
    """

    lower, upper = np.asarray(problem.lower, float), np.asarray(problem.upper, float)
    width = upper - lower
    u = np.random.default_rng(seed).random((max(1, int(n_starts)), lower.size))
    starts = lower + u * width
    if extra is not None and np.size(extra):
        starts = np.concatenate([np.atleast_2d(np.asarray(extra, float)), starts])
    f0 = _values(problem, starts)
    n_evals = len(starts)
    if not np.any(np.isfinite(f0)):
        raise ConfigError("Laplace start: no finite log-density in the prior box")
    order = np.argsort(-f0)[: max(1, int(n_local))]
    bounds = list(zip(lower - 0.5 * width, upper + 0.5 * width))

    def objective(x):
        v, g = problem.value_and_grad(jnp.asarray(x[None]))
        v, g = float(np.asarray(v)[0]), np.asarray(g, float)[0]
        if not np.isfinite(v):
            return 1e30, np.zeros_like(x)
        return -v, -g

    best, n_fit = best_local_fit(objective, starts, f0, order, bounds, max_iterations)
    n_evals += n_fit
    theta = np.asarray(best.x, float)
    prec_box = np.diag(12.0 / width**2) if box_precision else np.zeros((lower.size,) * 2)
    steps = 0.01 * width
    for _ in range(2):
        hess = value_hessian(problem, theta, steps)
        n_evals += 1 + 2 * lower.size**2
        # a difference that left the box or met an unstable rollout (-inf): that entry gets no
        # curvature, i.e. the box's spread (eigh raised LinAlgError on the NaN before)
        hess = np.where(np.isfinite(hess), hess, 0.0)
        cov = _inverse_psd(_psd_part(-hess) + prec_box)
        steps = np.clip(np.sqrt(np.diag(cov)), 1e-6 * width, 0.25 * width)
    return ProblemLaplace(theta, 0.5 * (cov + cov.T), -float(best.fun), steps, n_evals)


def _psd_part(h: np.ndarray) -> np.ndarray:
    """The positive semi-definite part of a symmetric matrix (negative eigenvalues set to 0:
    a saddle or noise direction gets no curvature, i.e. the box's spread)."""
    h = 0.5 * (h + h.T)
    w, v = np.linalg.eigh(h)
    return (v * np.maximum(w, 0.0)) @ v.T


def problem_laplace_particles(key, lap: ProblemLaplace, n: int, scale: float = 1.0):
    """``[n, D]`` draws of ``N(lap.theta, scale^2 lap.cov)`` (``key``: a JAX key)."""
    if not (isinstance(n, (int, np.integer)) and n >= 1):
        raise ConfigError(f"n: must be an integer >= 1, got {n!r}")
    cov = np.asarray(lap.cov, float) * float(scale) ** 2
    chol = np.linalg.cholesky(cov + 1e-12 * np.eye(len(cov)) * np.trace(cov) / len(cov))
    z = jax.random.normal(key, (int(n), len(lap.theta)))
    return jnp.asarray(lap.theta) + z @ jnp.asarray(chol.T, z.dtype)


def mh_proposal(cov, dim: int | None = None) -> np.ndarray:
    """``[D, D]`` Cholesky factor of the random-walk proposal ``(2.38^2 / D) cov`` (Roberts,
    Gelman & Gilks 1997: the optimal scaling for a Gaussian target), for
    :func:`treeinfer.inference.samplers.mh`'s matrix ``proposal_scale``."""
    cov = np.asarray(cov, float)
    d = cov.shape[0] if dim is None else int(dim)
    chol = np.linalg.cholesky(cov + 1e-12 * np.eye(len(cov)) * np.trace(cov) / len(cov))
    return 2.38 / np.sqrt(d) * chol
