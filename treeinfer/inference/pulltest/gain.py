"""Model error that scales with the response: a slowly varying gain error per channel, on top
of the AR(1) + white residuals of :mod:`.residuals` (``noise="ar1+gain"``).

Why: the chain's extrapolation error on held-out parts of a pull is not a fixed-size wiggle.
The stiffness a first half of the ramp implies is off by some percent further up the ramp
(the root plate softens, the lag and creep fitted on a slow ramp are not those of a faster
one), so the error of the predicted tilt grows with the tilt. An AR(1) of a few seconds fitted
where the tilts are small says nothing about that, and the band is then far too narrow at
the peak; an AR(1) slow enough to cover it carries the ramp itself (:mod:`.residuals`). A
relative error does neither: per channel,

    e(t) = theta(t) g(t) + a(t) + w(t),

``theta`` the model's tilt, ``g`` a stationary Ornstein-Uhlenbeck gain error (sd
``sigma_g``, correlation time ``tau_g`` in :data:`GAIN_TAU_PRIOR`, longer than the AR(1)'s and
short enough that the fitted half of a ramp shows how much the gain wanders, which is what
sets ``sigma_g``), ``a`` the AR(1) part and ``w`` white. It is the model-discrepancy term of
Kennedy and O'Hagan made proportional to the response.

The likelihood is exact: a two-state Kalman filter per channel (states ``g`` and ``a``,
observation ``theta_t g + a + w``), one ``lax.scan`` over the irregular time base, missing
samples predicted through. Written out for the same reason as :func:`.residuals.
ou_white_log_prob` (the observation's coefficient changes at every sample); tests check it
against ``scipy.stats.multivariate_normal`` with the covariance
``diag(theta) K_g diag(theta) + K_a + sigma_w^2 I``.

The predictive band of held-out parts takes ``g`` either by its stationary marginal (sd
``sigma_g``) or by its forecast from the fitted part (:func:`gain_forecast`, through
:func:`gain_band_terms`: the filter's state at the last fitted sample carried forward, i.e. the
Gaussian conditional of ``g`` given the fitted residuals; the posterior predictive proper).
The forecast is narrower just after the fitted part where that part pins the gain, and is the
stationary marginal many correlation times later. :func:`gain_ou_innovations` are the
filter's standardised innovations: the check of an ``ar1+gain`` fit.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "GAIN_SD_PRIOR",
    "GAIN_TAU_PRIOR",
    "gain_forecast",
    "gain_ou_innovations",
    "gain_ou_log_prob",
]

GAIN_SD_PRIOR = (1.0e-3, 0.5)  # sigma_g (a fraction of the tilt): LogUniform
GAIN_TAU_PRIOR = (5.0, 50.0)  # s: LogUniform; beyond the AR(1)'s 5 s, within a fitted half-ramp


def gain_ou_log_prob(resid, theta, mask, time, sigma_w, sigma_a, tau_a, sigma_g, tau_g):
    """Exact log-density (nats) of residuals ``resid`` [C, T] (``mask`` [C, T] False =
    missing) at ``time`` [T] s, with the model's tilts ``theta`` [C, T] as the gain's
    coefficient, per channel ``sigma_w``, ``sigma_a``, ``tau_a``, ``sigma_g``, ``tau_g``
    [C]; summed over channels (module docstring)."""
    import numpyro.distributions as dist

    v, s, m, _ = _filter(resid, theta, mask, time, sigma_w, sigma_a, tau_a, sigma_g, tau_g)
    lp = dist.Normal(0.0, jnp.sqrt(s)).log_prob(v)
    return jnp.sum(jnp.where(m, lp, 0.0))


def gain_ou_innovations(
    resid, theta, mask, time, sigma_w, sigma_a, tau_a, sigma_g, tau_g
) -> np.ndarray:
    """``[C, T]``: the two-state Kalman filter's standardised one-step innovations
    ``v / sqrt(S)`` (NaN where missing), arguments as :func:`gain_ou_log_prob`. Under the
    model they are i.i.d. N(0, 1) (the Cholesky whitening of the residuals, in time order):
    their lag-1 autocorrelation is the check of an ``ar1+gain`` fit
    (:func:`.residuals.lag1_autocorrelation`; the raw residuals are correlated by design)."""
    v, s, m, _ = _filter(resid, theta, mask, time, sigma_w, sigma_a, tau_a, sigma_g, tau_g)
    z = np.asarray(v / jnp.sqrt(s))
    return np.where(np.asarray(m), z, np.nan).T


def _filter(resid, theta, mask, time, sigma_w, sigma_a, tau_a, sigma_g, tau_g):
    """The filter's innovations ``v`` and their variances ``s`` [T, C], and ``mask`` [T, C]."""
    r = jnp.moveaxis(jnp.asarray(resid), -1, 0)  # [T, C]
    h = jnp.moveaxis(jnp.asarray(theta), -1, 0)
    m = jnp.moveaxis(jnp.asarray(mask, bool), -1, 0)
    r = jnp.where(m, r, 0.0)
    h = jnp.where(m, h, 0.0)  # a missing sample's tilt may be NaN: never used, kept finite
    time = jnp.asarray(time, r.dtype)
    dt = jnp.concatenate([jnp.zeros(1, r.dtype), jnp.diff(time)])
    q_stat = jnp.stack([jnp.asarray(sigma_g) ** 2, jnp.asarray(sigma_a) ** 2], -1)  # [C, 2]
    tau = jnp.stack([jnp.asarray(tau_g), jnp.asarray(tau_a)], -1)
    sw2 = jnp.asarray(sigma_w) ** 2

    def step(carry, x):
        mean, cov = carry  # [C, 2], [C, 2, 2]
        rt, ht, mt, d = x
        rho = jnp.exp(-d / tau)  # [C, 2]
        mp = rho * mean
        cp = (
            rho[:, :, None] * cov * rho[:, None, :]
            + jnp.eye(2) * ((1 - rho**2) * q_stat)[:, :, None]
        )
        obs = jnp.stack([ht, jnp.ones_like(ht)], -1)  # [C, 2]
        pc = jnp.einsum("cij,cj->ci", cp, obs)  # P H^T
        s = jnp.einsum("ci,ci->c", obs, pc) + sw2
        v = rt - jnp.einsum("ci,ci->c", obs, mp)
        k = pc / s[:, None]
        mean = jnp.where(mt[:, None], mp + k * v[:, None], mp)
        cov = jnp.where(mt[:, None, None], cp - k[:, :, None] * pc[:, None, :], cp)
        return (mean, cov), (v, s)

    c = r.shape[1]
    mean0 = jnp.zeros((c, 2), r.dtype)
    cov0 = jnp.eye(2) * q_stat[:, :, None]  # stationary start (the first step has dt = 0)
    last, (v, s) = jax.lax.scan(step, (mean0, cov0), (r, h, m, dt))
    return v, s, m, last


def gain_forecast(
    resid, theta, mask, time, sigma_w, sigma_a, tau_a, sigma_g, tau_g, later
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """The gain error's forecast from the fitted part: its mean and variance ``[C, F]`` at
    times ``later`` [F] s (at or after ``time[-1]``), given the residuals of the fitted
    samples (arguments as :func:`gain_ou_log_prob`): the filter's state at the last fitted
    sample, ``m_T`` and ``P_T``, carried forward by the Ornstein-Uhlenbeck process,
    ``rho m_T`` and ``rho^2 P_T + (1 - rho^2) sigma_g^2`` with ``rho = exp(-(t - t_T) /
    tau_g)``. Just after the fitted part it says what the fitted part showed of the gain;
    many correlation times later it is the stationary marginal ``(0, sigma_g^2)``."""
    *_, (mean, cov) = _filter(resid, theta, mask, time, sigma_w, sigma_a, tau_a, sigma_g, tau_g)
    lag = jnp.asarray(later) - jnp.asarray(time)[-1]  # [F]
    rho = jnp.exp(-jnp.maximum(lag, 0.0)[None, :] / jnp.asarray(tau_g)[:, None])  # [C, F]
    sg2 = jnp.asarray(sigma_g)[:, None] ** 2
    return rho * mean[:, :1], rho**2 * cov[:, :1, 0] + (1 - rho**2) * sg2


def gain_band_terms(pred, params: dict, time, fit_tilt=None) -> tuple[np.ndarray, np.ndarray]:
    """The gain error in a predictive band, per draw: its mean and sd ``[S, C, T]`` for the
    model's tilts ``pred`` [S, C, T] at ``time`` [T] s and the draws' ``params`` (``sigma_w``,
    ``sigma_a``, ``tau_ar``, ``sigma_g``, ``tau_g``, each [S, C]). Without ``fit_tilt``: the
    stationary marginal (mean 0, sd ``sigma_g``) everywhere. With ``fit_tilt`` [C, n], the
    recorded tilts of the first ``n`` samples (the fitted part): after them, each draw's
    :func:`gain_forecast` from its own residuals there; on them, the stationary marginal."""
    pred = np.asarray(pred)
    sg = np.asarray(params["sigma_g"])
    mean = np.zeros_like(pred)
    sd = np.broadcast_to(sg[:, :, None], pred.shape).copy()
    if fit_tilt is None:
        return mean, sd
    fit_tilt = np.asarray(fit_tilt, float)
    n = fit_tilt.shape[1]
    time = np.asarray(time, float)
    mask = np.isfinite(fit_tilt)
    resid = np.where(mask, fit_tilt[None] - pred[:, :, :n], 0.0)
    keys = ("sigma_w", "sigma_a", "tau_ar", "sigma_g", "tau_g")
    fc = jax.vmap(gain_forecast, in_axes=(0, 0, None, None, 0, 0, 0, 0, 0, None))
    m, v = fc(resid, pred[:, :, :n], mask, time[:n], *(params[k] for k in keys), time[n:])
    mean[:, :, n:] = np.asarray(m)
    sd[:, :, n:] = np.sqrt(np.maximum(np.asarray(v), 0.0))
    return mean, sd
