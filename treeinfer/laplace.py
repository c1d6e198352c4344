"""Particles around a MAP fit (``--init laplace``): the Laplace approximation, and for the
paper's Boltzmann loss (a sum of norms, cone-shaped at its mode) the Gaussian matched to the
linearised loss. Split from :mod:`treeinfer.mapfit`, which re-exports these names."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .errors import ConfigError

__all__ = ["laplace_particles", "norm_loss_covariance"]


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


def laplace_particles(
    key,
    fit,  # treeinfer.mapfit.MapFit (not imported: mapfit imports this module)
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
    use_norm = covariance == "norm" or (covariance == "auto" and fit.norm_cov is not None)
    if use_norm:
        # precision of the matched Gaussian (model columns only; the norm loss has no sigma)
        h = np.zeros((len(fit.theta),) * 2)
        m = fit.n_model
        h[:m, :m] = _inverse_psd(np.asarray(fit.norm_cov, float))
    else:
        h = np.array(fit.hessian, float)
    if box_precision:
        width = np.asarray(fit.upper, float) - np.asarray(fit.lower, float)
        idx = np.arange(fit.n_model)
        h[idx, idx] += 12.0 / width**2
    cov = _inverse_psd(h) * float(scale) ** 2
    chol = np.linalg.cholesky(cov + 1e-12 * np.eye(len(cov)) * np.trace(cov) / len(cov))
    z = jax.random.normal(key, (int(n), len(fit.theta)))
    return jnp.asarray(fit.theta) + z @ jnp.asarray(chol.T, z.dtype)


# ---- treeinfer problems ------------------------------------------------------------------------
