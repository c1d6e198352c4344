"""Correlated residuals for pulling tests, and the check that says when a fit needs them.

``ar1`` residual model, per channel: white noise (``sigma_w``) plus a stationary AR(1)
component in continuous time (an Ornstein-Uhlenbeck process: sd ``sigma_a``, correlation time
``tau_ar``), so that its correlation between samples ``dt`` apart is ``exp(-dt / tau_ar)`` on
the recordings' irregular time base (steps of 0.1-0.3 s, gaps of seconds). Its covariance is

    Cov(e_i, e_j) = sigma_a^2 exp(-|t_i - t_j| / tau_ar) + sigma_w^2 [i = j]

The correlation time's prior is bounded (:data:`TAU_AR_PRIOR`, up to 5 s): an unbounded one
lets the AR(1) part become a random walk over the whole fit window that carries the ramp
itself and frees the stiffnesses (rho 0.999 per sample in the first study); drifts slower
than that are the mechanical model's job (the creep element, :mod:`.creep`).

:func:`lag1_autocorrelation` is the check: the lag-1 autocorrelation of a fit's residuals
(i.i.d. residuals give about 0 +- 2/sqrt(n)). Above :data:`LAG1_LIMIT` the i.i.d. band and
intervals are too narrow: fit with ``noise="ar1"``. An ``ar1`` fit is checked the same way
on its standardised innovations (:func:`ou_white_innovations`): if they are still correlated,
the AR(1) part is not what the residuals are.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "LAG1_LIMIT",
    "TAU_AR_PRIOR",
    "lag1_autocorrelation",
    "ou_white_innovations",
    "ou_white_log_prob",
]

TAU_AR_PRIOR = (0.05, 5.0)  # s: LogUniform prior of the AR(1) correlation time
LAG1_LIMIT = 0.3  # residual lag-1 autocorrelation above which i.i.d. noise is the wrong model


def ou_white_log_prob(resid, mask, time, sigma_w, sigma_a, tau):
    """Exact log-density (nats) of residuals ``resid`` [C, T] (``mask`` [C, T] False =
    missing) at ``time`` [T] s under the module's covariance, per channel ``sigma_w``,
    ``sigma_a``, ``tau`` [C]; summed over channels.

    A scalar Kalman filter (prediction-error decomposition), one ``lax.scan`` over T. Written
    here rather than using :func:`treeinfer.model.noise.ar1_white_log_prob` because that one
    has one AR coefficient per series (a regular grid) and this one's coefficient follows
    each step's duration; numpyro's ``GaussianStateSpace`` has neither missing samples nor
    varying steps. Missing samples are predicted through without an update (exact: the
    marginal of the observed ones); tests check it against ``scipy.stats.multivariate_normal``."""
    import numpyro.distributions as dist

    v, s, m = _innovations(resid, mask, time, sigma_w, sigma_a, tau)
    lp = dist.Normal(0.0, jnp.sqrt(s)).log_prob(v)
    return jnp.sum(jnp.where(m, lp, 0.0))


def ou_white_innovations(resid, mask, time, sigma_w, sigma_a, tau) -> np.ndarray:
    """``[C, T]``: the Kalman filter's standardised one-step innovations ``v / sqrt(S)`` (NaN
    where missing). Under the model they are i.i.d. N(0, 1): their lag-1 autocorrelation is
    the check of an ``ar1`` fit (the raw residuals of one are correlated by design)."""
    v, s, m = _innovations(resid, mask, time, sigma_w, sigma_a, tau)
    z = np.asarray(v / jnp.sqrt(s))
    return np.where(np.asarray(m), z, np.nan).T


def _innovations(resid, mask, time, sigma_w, sigma_a, tau):
    r = jnp.moveaxis(jnp.asarray(resid), -1, 0)  # [T, C]
    m = jnp.moveaxis(jnp.asarray(mask, bool), -1, 0)
    r = jnp.where(m, r, 0.0)
    time = jnp.asarray(time, r.dtype)
    dt = jnp.concatenate([jnp.zeros(1, r.dtype), jnp.diff(time)])
    sw2, sa2, tau = jnp.asarray(sigma_w) ** 2, jnp.asarray(sigma_a) ** 2, jnp.asarray(tau)

    def step(carry, x):
        mean, var = carry
        rt, mt, d = x
        rho = jnp.exp(-d / tau)
        mp, vp = rho * mean, rho**2 * var + (1.0 - rho**2) * sa2
        s = vp + sw2
        v = rt - mp
        k = vp / s
        mean = jnp.where(mt, mp + k * v, mp)
        var = jnp.where(mt, (1.0 - k) * vp, vp)
        return (mean, var), (v, s)

    zero = jnp.zeros(r.shape[1], r.dtype)
    # stationary start: the first step has dt = 0 (rho = 1) from (mean 0, var sa2)
    _, (v, s) = jax.lax.scan(step, (zero, zero + sa2), (r, m, dt))
    return v, s, m


def lag1_autocorrelation(resid) -> np.ndarray:
    """``[C]``: per channel, the lag-1 autocorrelation of ``resid`` [C, T] (NaN = missing;
    only pairs of consecutive recorded samples count), about its mean."""
    out = []
    for row in np.atleast_2d(np.asarray(resid, float)):
        x = row - np.nanmean(row)
        a, b = x[:-1], x[1:]
        ok = np.isfinite(a) & np.isfinite(b)
        den = np.nansum(x**2) * ok.sum() / max(np.isfinite(x).sum(), 1)
        out.append(float(np.sum(a[ok] * b[ok]) / den) if den > 0 else np.nan)
    return np.asarray(out)
