"""Predictive bands: the per-point KDE of the particles' predictions, its quantiles (the
parameter-only band), and the posterior predictive with measurement noise (the predictive band
and its NLL). Degenerate columns and invalid particles as in :mod:`treeinfer.evaluation.metrics`,
which re-exports every name here."""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import logsumexp, ndtr

from ..errors import ConfigError, SimulationError
from ..model.noise import noise_distribution, residual_log_prob, standard_quantile

# the KDE's constants live with its host twin (which this module imports, not the reverse)
from .bands_host import _BRACKET_BANDWIDTHS, _DEGENERATE_EPS_FACTOR, interval_host

_HOST_MAX_SERIES = 64  # predictive_interval of at most this many series runs on the host


class KDE1D(NamedTuple):
    """Per-time-step 1-D Gaussian KDE, particle axis last.

    points: ``[*S, P]`` particle predictions (invalid ones replaced by 0).
    weights: ``[P]`` normalised weights (0 for invalid particles, ``1/n`` otherwise).
    mean: ``[*S]`` weighted mean of the particles.
    bandwidth: ``[*S]`` Scott's rule bandwidth (0 where degenerate).
    degenerate: ``[*S]`` bool, spread indistinguishable from rounding.
    n_valid: scalar, number of particles used.
    """

    points: jax.Array
    weights: jax.Array
    mean: jax.Array
    bandwidth: jax.Array
    degenerate: jax.Array
    n_valid: jax.Array


class PredictiveInterval(NamedTuple):
    """Central interval of the per-time-step KDE; unpacks as ``lower, upper, mean``.

    All ``[*S]``, trajectory units.
    """

    lower: jax.Array
    upper: jax.Array
    mean: jax.Array


class PredictiveNLL(NamedTuple):
    """Negative log-likelihood of held-out points under the per-step KDE.

    total: sum over all used points (nats).
    mean: ``total / n_points`` (nats per point).
    n_points: number of points used (masked-in, finite, non-degenerate).
    n_degenerate: masked-in finite points skipped because their step is degenerate.
    """

    total: jax.Array
    mean: jax.Array
    n_points: jax.Array
    n_degenerate: jax.Array


# --------------------------------------------------------------------------- helpers


def _is_tracer(x) -> bool:
    return isinstance(x, jax.core.Tracer)


def _check_level(level: float) -> None:
    if not (0.0 < float(level) < 1.0):
        raise ConfigError(f"level: must lie strictly between 0 and 1, got {level}")


def _effective_valid(pred: jax.Array, valid) -> jax.Array:
    """``[P]`` bool: given ``valid`` AND all predictions of the particle finite."""
    if valid is not None:
        valid = jnp.asarray(valid, dtype=bool)
        if valid.shape != (pred.shape[0],):
            raise ConfigError(
                f"valid: expected shape ({pred.shape[0]},) (one flag per particle), got "
                f"{valid.shape}"
            )
    return _finite_and_valid(pred, valid)


# The metrics are usually called eagerly on concrete arrays; jitting the array
# cores (validation stays outside, in Python) turns many op-by-op dispatches,
# each compiled on first use, into one compiled call. Callers may still jit the
# public functions.
@jax.jit
def _finite_and_valid(pred, valid):
    finite = jnp.all(jnp.isfinite(pred.reshape(pred.shape[0], -1)), axis=1)
    return finite if valid is None else finite & valid


def _require_particles(eff_valid: jax.Array, minimum: int = 2) -> None:
    if _is_tracer(eff_valid):
        return  # cannot check under jit; the result will be NaN instead
    n = int(np.sum(np.asarray(eff_valid)))
    if n < minimum:
        raise SimulationError(
            f"only {n} of {eff_valid.shape[0]} particles have a stable, finite simulation; "
            f"need at least {minimum} to build a predictive distribution"
        )


def _point_mask(gt, mask):
    """Finite ``gt`` AND ``mask``; numpy in, numpy out; jax in (also traced), jax out."""
    xp = np if isinstance(gt, np.ndarray) else jnp
    m = xp.isfinite(gt)
    if mask is not None:
        m = m & xp.broadcast_to(xp.asarray(mask, dtype=bool), gt.shape)
    return m


# --------------------------------------------------------------------------- KDE


def _as_float_pred(pred) -> jax.Array:
    pred = jnp.asarray(pred)
    if not jnp.issubdtype(pred.dtype, jnp.floating):
        pred = pred.astype(jnp.result_type(float))
    if pred.ndim < 1 or pred.shape[0] < 2:
        raise ConfigError(f"pred: expected shape [P, ...] with P >= 2 particles, got {pred.shape}")
    return pred


def kde_1d(pred, valid=None) -> KDE1D:
    """Per-time-step Scott's-rule Gaussian KDE of particle predictions.

    Args:
      pred: ``[P, *S]`` particle predictions (trajectory units).
      valid: optional ``[P]`` bool, stable particles.

    Returns:
      :class:`KDE1D`, with the particle axis moved last. Jittable.

    Bandwidth equals ``scipy.stats.gaussian_kde(x).covariance ** 0.5`` at every
    step: weighted mean/variance with 0/1 weights reproduce the unweighted
    ``ddof=1`` statistics of the valid particles, ``neff = n_valid``.
    """
    pred = _as_float_pred(pred)
    eff = _effective_valid(pred, valid)
    _require_particles(eff)
    return _kde_1d(pred, eff)


@jax.jit
def _kde_1d(pred: jax.Array, eff: jax.Array) -> KDE1D:
    n = jnp.sum(eff)
    w = eff.astype(pred.dtype) / jnp.maximum(n, 1)
    x = jnp.moveaxis(jnp.where(eff.reshape((-1,) + (1,) * (pred.ndim - 1)), pred, 0.0), 0, -1)
    mean = jnp.sum(w * x, axis=-1)
    # unbiased weighted variance, as jnp.cov(..., aweights=w, bias=False) / scipy
    var = jnp.sum(w * (x - mean[..., None]) ** 2, axis=-1) / (1.0 - jnp.sum(w**2))
    std = jnp.sqrt(var)
    scale = jnp.max(jnp.where(eff, jnp.abs(x), 0.0), axis=-1)
    degenerate = std <= _DEGENERATE_EPS_FACTOR * jnp.finfo(x.dtype).eps * scale
    bw = jnp.where(degenerate, 0.0, std * n.astype(x.dtype) ** (-1.0 / 5.0))
    # under jit nobody can raise on too few particles: make everything NaN instead
    enough = n >= 2
    mean = jnp.where(enough, mean, jnp.nan)
    bw = jnp.where(enough, bw, jnp.nan)
    degenerate = degenerate & enough
    return KDE1D(x, w, mean, bw, degenerate, n)


def _kde_cdf(kde: KDE1D, h_safe: jax.Array, y: jax.Array) -> jax.Array:
    """Mixture CDF ``sum_i w_i Phi((y - x_i)/h)``; ``y``, ``h_safe``: ``[*S]``."""
    z = (y[..., None] - kde.points) / h_safe[..., None]
    return jnp.sum(kde.weights * ndtr(z), axis=-1)


def _kde_quantile(kde: KDE1D, q: jax.Array, n_iter: int) -> jax.Array:
    """``q``-quantiles ``[Q]`` of the mixture at each step by bisection on its CDF: ``[Q, *S]``."""
    q = q.reshape((-1,) + (1,) * kde.mean.ndim)
    h_safe = jnp.where(kde.degenerate, 1.0, kde.bandwidth)
    valid = kde.weights > 0
    lo = jnp.min(jnp.where(valid, kde.points, jnp.inf), axis=-1) - _BRACKET_BANDWIDTHS * h_safe
    hi = jnp.max(jnp.where(valid, kde.points, -jnp.inf), axis=-1) + _BRACKET_BANDWIDTHS * h_safe
    lo, hi = (
        jnp.broadcast_to(lo, q.shape[:1] + lo.shape),
        jnp.broadcast_to(hi, q.shape[:1] + hi.shape),
    )

    def body(_, bracket):
        lo, hi = bracket
        mid = 0.5 * (lo + hi)
        below = _kde_cdf(kde, h_safe, mid) < q
        return jnp.where(below, mid, lo), jnp.where(below, hi, mid)

    lo, hi = jax.lax.fori_loop(0, n_iter, body, (lo, hi))
    return jnp.where(kde.degenerate, kde.mean, 0.5 * (lo + hi))


def predictive_interval(
    pred, level: float = 0.95, valid=None, n_iter: int = 60
) -> PredictiveInterval:
    """Central ``level`` interval of the per-time-step predictive KDE.

    Args:
      pred: ``[P, *S]`` particle predictions, e.g. ``[P, T]`` or ``[P, B, T]``.
      level: interval mass, 0.95 gives ``[q_2.5%, q_97.5%]``.
      valid: optional ``[P]`` bool, stable particles.
      n_iter: bisection steps (bracket shrinks ``2**n_iter``-fold; 60 reaches
        float64 resolution, float32 much earlier).

    Returns:
      ``(lower, upper, mean)``, each ``[*S]`` in trajectory units. Degenerate
      steps give ``lower == upper == mean``. Jittable (``level``/``n_iter``
      static), vectorised over ``S``.
    """
    _check_level(level)
    pred = _as_float_pred(pred)
    eff = _effective_valid(pred, valid)
    _require_particles(eff)
    alpha = 0.5 * (1.0 - float(level))
    n_series = int(np.prod(pred.shape[1:]))  # not pred[0]: an indexing program to compile
    if not (_is_tracer(pred) or _is_tracer(eff)) and n_series <= _HOST_MAX_SERIES:
        # a few series (parameter intervals): on the host, no program to compile (bands_host)
        lo, hi, mean = interval_host(pred, eff, alpha, int(n_iter), pred.dtype)
        return PredictiveInterval(jnp.asarray(lo), jnp.asarray(hi), jnp.asarray(mean))
    return _interval(pred, eff, alpha, int(n_iter))


@functools.partial(jax.jit, static_argnames=("alpha", "n_iter"))
def _interval(pred, eff, alpha: float, n_iter: int) -> PredictiveInterval:
    kde = _kde_1d(pred, eff)
    lower, upper = _kde_quantile(kde, jnp.array([alpha, 1.0 - alpha], kde.points.dtype), n_iter)
    return PredictiveInterval(lower, upper, kde.mean)


# --------------------------------------------------------------------------- posterior predictive
#
# The posterior predictive of a recording y[b, t] is the mixture over particles p of the noise
# model around each particle's simulation:
#
#     p(y | D) ~ (1/n) sum_p p_noise(y - tau_p[b, t]; sigma_p)        (valid particles only)
#
# (Gaussian or Student-t, :mod:`treeinfer.model.noise`; sigma_p per particle when sigma_x was
# inferred, one value otherwise). Like the parameter band, the finite particle set is smoothed by
# the same Scott's-rule KDE kernel (bandwidth h): each component's scale is sqrt(sigma_p^2 + h^2)
# (exact convolution for Gaussian noise; for Student-t a t with that scale, an approximation).
# So the predictive band is never narrower than the parameter band, and with many particles
# (h -> 0) it is the exact mixture. Its central interval is the PREDICTIVE band (what a new noisy
# recording should fall in); the KDE interval of the tau_p alone (:func:`predictive_interval`) is
# the PARAMETER band (uncertainty of the noise-free displacement). At t = 0, where every particle
# predicts 0, the predictive band is the noise's own interval, never zero-width.


class PredictiveBands(NamedTuple):
    """Both bands, ``[*S]`` each, trajectory units.

    parameter: :class:`PredictiveInterval` of the particles' simulations only (KDE, no noise).
    predictive: :class:`PredictiveInterval` of the posterior predictive (simulation + noise);
      compare recordings with this one ("% outside").
    """

    parameter: PredictiveInterval
    predictive: PredictiveInterval


def _all_host(x, test) -> bool:
    """``test`` (a NumPy predicate) holds at every entry of the concrete array ``x``."""
    return bool(np.all(test(np.asarray(x))))


def _noise_scale(sigma, n_particles: int, dtype) -> jax.Array:
    s = jnp.asarray(sigma, dtype)
    if s.ndim == 0:
        s = jnp.full((n_particles,), s)
    if s.shape != (n_particles,):
        raise ConfigError(f"sigma: expected a scalar or shape ({n_particles},), got {s.shape}")
    # checked on the host: on the device each operation of the check is one more small program
    # to compile (a cold `treeinfer infer` compiled 8 of them here, with extra_variance's below)
    if not _is_tracer(s) and not _all_host(s, lambda a: np.isfinite(a) & (a > 0)):
        raise ConfigError("sigma: noise standard deviations must be finite and positive")
    return s


def noisy_predictive_interval(
    pred,
    sigma,
    level: float = 0.95,
    valid=None,
    kind: str = "gaussian",
    df: float = 4.0,
    n_iter: int = 60,
    extra_variance=None,
) -> PredictiveInterval:
    """Central ``level`` interval of the posterior predictive (simulations + noise).

    Args:
      pred: ``[P, *S]`` particle simulations (m). sigma: scalar or ``[P]`` noise scale (m) per
        particle. kind, df: noise model (:mod:`treeinfer.model.noise`). valid: ``[P]`` bool.
      extra_variance: None, ``[*S]`` m^2 added to every particle's ``sigma_p^2`` at each point
        (the force-noise-induced variance ``diag C`` of a recording driven by a noisy force,
        :func:`treeinfer.model.force_noise.point_variance`), or ``[P, *S]``: particle p's own (the
        static model's load-cell term ``(sigma_F c_p)^2`` through each draw's compliance,
        :class:`treeinfer.inference.static.StaticForceNoise`); part of the predictive band only.

    Returns:
      ``(lower, upper, mean)`` ``[*S]``: quantiles of the mixture
      ``(1/n) sum_p F_noise((y - pred_p) / sqrt(sigma_p^2 + h^2))`` (h: the parameter band's KDE
      bandwidth at that step, 0 where degenerate or P = 1) by bisection, bracketed by the smallest
      and largest component quantile (the mixture quantile lies between them). Works with P = 1.
    """
    _check_level(level)
    pred = jnp.asarray(pred)
    if not jnp.issubdtype(pred.dtype, jnp.floating):
        pred = pred.astype(jnp.result_type(float))
    if pred.ndim < 1:
        raise ConfigError(f"pred: expected shape [P, ...], got {pred.shape}")
    eff = _effective_valid(pred, valid)
    _require_particles(eff, minimum=1)
    s = _noise_scale(sigma, pred.shape[0], pred.dtype)
    alpha = 0.5 * (1.0 - float(level))
    z = jnp.asarray(
        [standard_quantile(alpha, kind, df), standard_quantile(1 - alpha, kind, df)], pred.dtype
    )
    extra = _extra_variance(extra_variance, pred)
    return _noisy_interval(pred, eff, s, z, alpha, kind, float(df), int(n_iter), extra)


def _extra_variance(extra, pred) -> jax.Array:
    """``extra_variance`` (None, ``[*S]`` or per particle ``[P, *S]`` m^2, finite and >= 0) ->
    ``[*S, 1]`` or ``[*S, P]`` (the layout of :func:`_kernel_scale`'s scales)."""
    if extra is None:
        return jnp.zeros(pred.shape[1:] + (1,), pred.dtype)
    e = jnp.asarray(extra, pred.dtype)
    if e.shape not in (pred.shape[1:], pred.shape):
        raise ConfigError(
            f"extra_variance: expected shape {tuple(pred.shape[1:])} or {tuple(pred.shape)} to "
            f"match pred, got {e.shape}"
        )
    if not _is_tracer(e) and not _all_host(e, lambda a: np.isfinite(a) & (a >= 0)):
        raise ConfigError("extra_variance: variances must be finite and >= 0")
    return jnp.moveaxis(e, 0, -1) if e.shape == pred.shape else e[..., None]


def _kernel_scale(pred, eff, s, extra=0.0):
    """Per (step, particle) scale ``sqrt(sigma_p^2 + extra + h^2)`` [*S, P]: the noise of each
    particle (plus the ``extra`` variance [*S, 1] per point or [*S, P] per point and particle
    from :func:`_extra_variance`, e.g. force-noise-induced) convolved with the parameter band's
    KDE kernel (bandwidth h, 0 at degenerate steps or P < 2)."""
    kde = _kde_1d(pred, eff)
    h = jnp.where(kde.degenerate | ~jnp.isfinite(kde.bandwidth), 0.0, kde.bandwidth)
    extra = jnp.asarray(extra)
    return jnp.sqrt(jnp.where(eff, s, 1.0) ** 2 + extra + h[..., None] ** 2), kde


@functools.partial(jax.jit, static_argnames=("alpha", "kind", "df", "n_iter"))
def _noisy_interval(pred, eff, s, z, alpha, kind, df, n_iter, extra):
    scale, kde = _kernel_scale(pred, eff, s, extra)
    x, w = kde.points, kde.weights

    def cdf(y):
        unit = noise_distribution(kind, 1.0, df)
        return jnp.sum(w * unit.cdf((y[..., None] - x) / scale), axis=-1)

    def quantile(q, zq):
        comp = x + scale * zq
        lo = jnp.min(jnp.where(eff, comp, jnp.inf), axis=-1)
        hi = jnp.max(jnp.where(eff, comp, -jnp.inf), axis=-1)
        # widen by a hair so that equal components still bracket the root
        pad = 1e-6 * (jnp.abs(lo) + jnp.abs(hi)) + 1e-12
        lo, hi = lo - pad, hi + pad

        def body(_, br):
            a, b = br
            mid = 0.5 * (a + b)
            below = cdf(mid) < q
            return jnp.where(below, mid, a), jnp.where(below, b, mid)

        a, b = jax.lax.fori_loop(0, n_iter, body, (lo, hi))
        return 0.5 * (a + b)

    mean = jnp.sum(w * x, axis=-1)
    return PredictiveInterval(quantile(alpha, z[0]), quantile(1.0 - alpha, z[1]), mean)


def predictive_bands(
    pred,
    sigma,
    level: float = 0.95,
    valid=None,
    kind: str = "gaussian",
    df: float = 4.0,
    extra_variance=None,
) -> PredictiveBands:
    """Parameter band (KDE of the simulations, :func:`predictive_interval`) AND predictive band
    (simulations + noise, :func:`noisy_predictive_interval`), clearly named. ``pred [P, *S]``,
    ``sigma`` scalar or ``[P]`` (m). The parameter band needs P >= 2. ``extra_variance``
    (``[*S]`` m^2, e.g. force-noise-induced) widens the predictive band only."""
    return PredictiveBands(
        predictive_interval(pred, level, valid),
        noisy_predictive_interval(
            pred, sigma, level, valid, kind, df, extra_variance=extra_variance
        ),
    )


def posterior_predictive_draws(
    key,
    pred,
    sigma,
    n_draws: int = 1,
    valid=None,
    kind: str = "gaussian",
    df: float = 4.0,
) -> jax.Array:
    """Draws of recordings from the posterior predictive: ``[n_draws, P_valid, *S]`` (m).

    Each valid particle's simulation plus an independent draw of its noise model (numpyro
    distribution, scale ``sigma_p``). Eager (the number of valid particles sets the shape)."""
    pred = jnp.asarray(pred)
    eff = np.asarray(_effective_valid(pred, valid))
    _require_particles(jnp.asarray(eff), minimum=1)
    s = _noise_scale(sigma, pred.shape[0], pred.dtype)[eff]
    x = pred[eff]
    s = s.reshape((-1,) + (1,) * (x.ndim - 1))
    e = noise_distribution(kind, 1.0, df).sample(key, (int(n_draws),) + x.shape)
    return x[None] + s[None] * e.astype(x.dtype)


def noisy_predictive_nll(
    pred,
    gt,
    sigma,
    mask=None,
    valid=None,
    kind: str = "gaussian",
    df: float = 4.0,
    extra_variance=None,
) -> PredictiveNLL:
    """NLL of held-out recordings under the posterior predictive (simulations + noise model).

    Per point ``-log p(y) = -log (1/n) sum_p p_noise(y - pred_p; sqrt(sigma_p^2 + h^2))`` (the
    same mixture as :func:`noisy_predictive_interval`), by ``logsumexp``
    over the valid particles; ``total`` sums over all masked-in, finite points (nats), ``mean``
    is per point. Finite for any particle spread (zero included: then it is the noise model's
    own NLL), so it is comparable across runs, samplers and likelihoods that report a noise
    model. ``n_degenerate`` is always 0 here. Args as :func:`noisy_predictive_interval`;
    ``gt [*S]`` m, ``mask [*S]`` bool; ``extra_variance`` as there (point-wise marginals: the
    force-induced correlation between points is not in this per-point NLL).
    """
    pred = jnp.asarray(pred)
    if not jnp.issubdtype(pred.dtype, jnp.floating):
        pred = pred.astype(jnp.result_type(float))
    eff = _effective_valid(pred, valid)
    _require_particles(eff, minimum=1)
    gt = jnp.asarray(gt, pred.dtype)
    if gt.shape != pred.shape[1:]:
        raise ConfigError(
            f"gt: expected shape {tuple(pred.shape[1:])} to match pred, got {gt.shape}"
        )
    s = _noise_scale(sigma, pred.shape[0], pred.dtype)
    extra = _extra_variance(extra_variance, pred)
    return _noisy_nll(pred, eff, s, gt, _point_mask(gt, mask), kind, float(df), extra)


@functools.partial(jax.jit, static_argnames=("kind", "df"))
def _noisy_nll(pred, eff, s, gt, m, kind, df, extra):
    scale, kde = _kernel_scale(pred, eff, s, extra)
    g = jnp.where(m, gt, 0.0)[..., None]
    lp = residual_log_prob(g - kde.points, scale, kind, df)  # [*S, P]
    log_p = logsumexp(lp, b=kde.weights, axis=-1)  # weight 0 drops invalid particles
    total = -jnp.sum(jnp.where(m, log_p, 0.0))
    n_points = jnp.sum(m)
    return PredictiveNLL(total, total / n_points, n_points, jnp.zeros((), n_points.dtype))
