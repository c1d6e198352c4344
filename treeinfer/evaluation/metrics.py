"""Evaluation metrics on plain arrays (paper, section "Evaluation Metrics").

Everything here works on arrays the simulator has already produced; nothing
calls the simulator.

Conventions
-----------
* ``pred``: ``[P, *S]`` predictions from ``P`` posterior particles, particle axis
  first; ``S`` is ``[T]`` for one test trajectory or ``[B, T]`` for ``B`` of them.
  Units are those of the trajectory (metres for displacement).
* ``gt``: ``[*S]`` held-out ground truth, same units.
* ``mask``: ``[*S]`` (or broadcastable) boolean, ``True`` = a real data point;
  use it for padded trajectories of different lengths. Non-finite ``gt`` points
  are always excluded as well.
* ``valid``: ``[P]`` boolean, ``True`` = the particle's simulation was stable.
  Invalid particles, and any particle whose predictions contain a non-finite
  value, are excluded from every statistic (they get weight zero, so shapes
  stay static and the functions stay jittable); :func:`summarize` reports the
  count.

The predictive distribution at each time step is the paper's: a 1-D Gaussian
kernel density estimate (KDE) over the particles' predictions with Scott's
rule bandwidth ``h = std * n**(-1/5)`` (``std`` with ``ddof=1``), identical to
``scipy.stats.gaussian_kde(x)`` / ``jax.scipy.stats.gaussian_kde(x)``. We write
the 1-D closed form ourselves instead of calling ``gaussian_kde`` once per time
step because we need it vectorised over ``[B, T]``, with a particle mask, and
with a defined answer at degenerate steps (all particles equal, e.g. ``t = 0``
where displacement is 0), where ``gaussian_kde`` inverts a singular covariance.

A time step is *degenerate* when the particles' spread is indistinguishable
from floating-point rounding: ``std <= 16 * eps * max|x|`` (this includes
``std == 0``). Its interval is zero-width at the particle mean and it is left
out of the predictive NLL (the KDE is a Dirac there); the count is reported.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import logsumexp

from ..errors import ConfigError
from .bands import (  # noqa: F401 -- re-exported: the old import path keeps working
    KDE1D,
    PredictiveBands,
    PredictiveInterval,
    PredictiveNLL,
    _as_float_pred,
    _check_level,
    _effective_valid,
    _kde_1d,
    _point_mask,
    _require_particles,
    kde_1d,
    noisy_predictive_interval,
    noisy_predictive_nll,
    posterior_predictive_draws,
    predictive_bands,
    predictive_interval,
)

__all__ = [
    "KDE1D",
    "PredictiveBands",
    "PredictiveInterval",
    "PredictiveNLL",
    "TruthCheck",
    "ci_width",
    "fraction_outside",
    "outside",
    "kde_1d",
    "noisy_predictive_interval",
    "noisy_predictive_nll",
    "posterior_nll",
    "posterior_predictive_draws",
    "posterior_vs_truth",
    "predictive_bands",
    "predictive_interval",
    "predictive_nll",
    "summarize",
]


class TruthCheck(NamedTuple):
    """Posterior particles compared with known true parameters (sim-to-sim).

    mean, abs_error, rel_error, lower, upper, in_marginal: ``[D]``.
    in_joint: ``True``/``False``, or ``None`` where the D-dim KDE is undefined
    (covariance singular, e.g. collapsed particles or ``D >= n``).
    log_density_truth, log_density_threshold: D-dim KDE log density at the
    truth and its ``1 - level`` quantile over the particles (NaN if undefined).
    n_valid: particles used.
    """

    mean: np.ndarray
    abs_error: np.ndarray
    rel_error: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    in_marginal: np.ndarray
    in_joint: bool | None
    log_density_truth: float
    log_density_threshold: float
    n_valid: int


# --------------------------------------------------------------------------- interval metrics


def ci_width(lower, upper, mask=None) -> jax.Array:
    """Average interval width ``upper - lower`` over the masked-in points.

    Pooled mean over all (trajectory, time step) points with ``mask`` True, so a
    longer trajectory counts proportionally more. Trajectory units.
    """
    return _ci_width(
        jnp.asarray(lower), jnp.asarray(upper), None if mask is None else jnp.asarray(mask, bool)
    )


@jax.jit
def _ci_width(lower, upper, mask):
    m = jnp.isfinite(lower) & jnp.isfinite(upper)
    if mask is not None:
        m = m & jnp.broadcast_to(mask, lower.shape)
    return jnp.sum(jnp.where(m, upper - lower, 0.0)) / jnp.sum(m)


def fraction_outside(
    lower, upper, gt, mask=None, atol: float = 1e-6, rtol: float = 1e-5
) -> jax.Array:
    """Share of ground-truth points outside ``[lower, upper]``, as a FRACTION in [0, 1].

    (Multiply by 100 for the paper's "% GT outside CI"; :func:`summarize`
    reports both.) A point counts as outside only if it is beyond a bound by
    more than ``atol + rtol * |bound|`` (trajectory units), so a degenerate,
    zero-width step at ``t = 0`` with GT equal up to rounding counts as inside.
    Points with ``mask`` False or non-finite ``gt`` are ignored.
    """
    mask = None if mask is None else jnp.asarray(mask, bool)
    return _fraction_outside(
        jnp.asarray(lower), jnp.asarray(upper), jnp.asarray(gt), mask, atol, rtol
    )


@jax.jit
def _fraction_outside(lower, upper, gt, mask, atol, rtol):
    m = _point_mask(gt, mask)
    return jnp.sum(outside(lower, upper, gt, atol, rtol) & m) / jnp.sum(m)


def outside(lower, upper, x, atol: float = 1e-6, rtol: float = 1e-5):
    """``x`` beyond ``[lower, upper]`` by more than ``atol + rtol * |bound|`` (numpy or jax)."""
    return (x < lower - (atol + rtol * abs(lower))) | (x > upper + (atol + rtol * abs(upper)))


# --------------------------------------------------------------------------- likelihoods


def predictive_nll(pred, gt, mask=None, valid=None) -> PredictiveNLL:
    """NLL of held-out ground-truth points under the per-time-step predictive KDE.

    Exactly: for every data point ``g[b, t]`` (masked-in, finite) the density is
    the same Scott's-rule 1-D Gaussian KDE used for the intervals, built from the
    valid particles' predictions at that ``(b, t)``:
    ``p(g) = (1/n) sum_i N(g; x_i, h^2)``. ``total = -sum_points log p(g)``
    (nats), evaluated with log-sum-exp; ``mean = total / n_points``. Points at
    degenerate steps are skipped and counted in ``n_degenerate``.

    This is a posterior *predictive* NLL on unseen trajectories. The paper's
    Table I "Nll ... of the estimated posterior from 5 random training
    trajectories" is not defined further there; see :func:`posterior_nll` for
    the other reading.

    Args:
      pred: ``[P, *S]``; gt: ``[*S]``; mask: ``[*S]`` bool; valid: ``[P]`` bool.
    """
    pred = _as_float_pred(pred)
    eff = _effective_valid(pred, valid)
    _require_particles(eff)
    gt = jnp.asarray(gt, pred.dtype)
    if gt.shape != pred.shape[1:]:
        raise ConfigError(
            f"gt: expected shape {tuple(pred.shape[1:])} to match pred, got {gt.shape}"
        )
    return _nll(pred, eff, gt, _point_mask(gt, mask))


@jax.jit
def _nll(pred, eff, gt, m) -> PredictiveNLL:
    kde = _kde_1d(pred, eff)
    used = m & ~kde.degenerate
    h = jnp.where(kde.degenerate, 1.0, kde.bandwidth)[..., None]
    g = jnp.where(m, gt, 0.0)[..., None]
    log_k = -0.5 * ((g - kde.points) / h) ** 2 - jnp.log(h) - 0.5 * jnp.log(2.0 * jnp.pi)
    log_p = logsumexp(log_k, b=kde.weights, axis=-1)  # b=0 drops invalid particles safely
    total = -jnp.sum(jnp.where(used, log_p, 0.0))
    n_points = jnp.sum(used)
    return PredictiveNLL(total, total / n_points, n_points, jnp.sum(m & kde.degenerate))


def posterior_nll(log_likelihood, valid=None) -> jax.Array:
    """Posterior NLL: minus the particle average of the training log-likelihood.

    ``log_likelihood``: ``[P]`` or ``[P, B]`` per particle (and per training
    trajectory), the paper's Boltzmann log-likelihood ``-L(theta)/kT`` (eq.
    "likelihood_multiple_def" without the constant ``log Z``). Trailing axes are
    summed (trajectories are i.i.d.), then
    ``nll = -(1/n) sum_{valid i} sum_b log p(tau_b | theta_i)``.

    This is our reading of the paper's Table I "Nll of the estimated posterior
    from 5 random training trajectories"; the paper gives no formula, so report
    which one you use. Invalid particles (``valid`` False or non-finite
    log-likelihood, i.e. unstable simulations) are excluded.
    """
    ll = jnp.asarray(log_likelihood)
    if ll.ndim < 1:
        raise ConfigError(f"log_likelihood: expected shape [P] or [P, B], got {ll.shape}")
    nll, ok = _posterior_nll(ll, None if valid is None else jnp.asarray(valid, bool))
    _require_particles(ok, minimum=1)
    return nll


@jax.jit
def _posterior_nll(ll, valid):
    ll = ll.reshape(ll.shape[0], -1).sum(axis=1)
    ok = jnp.isfinite(ll) if valid is None else jnp.isfinite(ll) & valid
    return -jnp.sum(jnp.where(ok, ll, 0.0)) / jnp.sum(ok), ok


# --------------------------------------------------------------------------- parameters


def posterior_vs_truth(
    particles, truth, level: float = 0.95, valid=None, log: bool = False
) -> TruthCheck:
    """Compare posterior particles with the true parameters (sim-to-sim).

    Args:
      particles: ``[P, D]`` posterior particles.
      truth: ``[D]`` true parameter values, same space as ``particles``.
      level: mass of the marginal intervals and of the joint region.
      valid: optional ``[P]`` bool.
      log: if True, take ``log`` of both particles and truth first (both must be
        positive), so every statistic is in log space. Otherwise the caller's
        space is used as given.

    Returns:
      :class:`TruthCheck` (numpy/Python values). ``rel_error = |mean - truth| / |truth|``.
      Marginal intervals are the central ``level`` intervals of the same 1-D
      Scott's-rule KDE used for trajectories, per dimension. The joint region
      is the ``level`` highest-density region of a D-dim Scott's-rule Gaussian KDE
      (``scipy.stats.gaussian_kde``, full covariance): the truth is inside
      if its KDE density is at least the ``1 - level`` quantile of the KDE
      densities at the particles themselves. Eager (not jittable).
    """
    _check_level(level)
    x = np.asarray(particles, dtype=float)
    t = np.asarray(truth, dtype=float)
    if x.ndim != 2 or t.shape != (x.shape[1],):
        raise ConfigError(f"particles/truth: expected [P, D] and [D], got {x.shape} and {t.shape}")
    if log:
        if np.any(t <= 0) or np.any(x[np.isfinite(x)] <= 0):
            raise ConfigError("posterior_vs_truth(log=True): particles and truth must be positive")
        with np.errstate(invalid="ignore", divide="ignore"):
            x, t = np.log(x), np.log(t)
    eff = np.all(np.isfinite(x), axis=1)
    if valid is not None:
        eff &= np.asarray(valid, bool)
    _require_particles(eff)
    lower, upper, mean = (np.asarray(a, dtype=float) for a in predictive_interval(x, level, eff))
    abs_err = np.abs(mean - t)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel_err = abs_err / np.abs(t)
    in_marg = ~outside(lower, upper, t)  # same tolerance as fraction_outside

    xv = x[eff]
    in_joint, ld_truth, ld_thr = None, float("nan"), float("nan")
    cov = np.atleast_2d(np.cov(xv, rowvar=False))
    eig = np.linalg.eigvalsh(cov) if np.all(np.isfinite(cov)) else np.array([0.0])
    # float32 KDE: treat a covariance that is singular to ~1e-6 relative as undefined
    if xv.shape[0] > x.shape[1] and eig.min() > 1e-6 * max(eig.max(), np.finfo(float).tiny):
        # SciPy's KDE on the host, in float64 (jax.scipy's, which this mirrored, was one more
        # XLA program to compile per run: about 1 s on a 2-core CPU for a few hundred points)
        from scipy.stats import gaussian_kde

        ld = gaussian_kde(xv.T).logpdf(np.column_stack([xv.T, t]))
        ld_parts, ld_truth = ld[:-1], float(ld[-1])
        ld_thr = float(np.quantile(ld_parts, 1.0 - level))
        if np.isfinite(ld_thr):
            in_joint = bool(ld_truth >= ld_thr)
    return TruthCheck(
        mean, abs_err, rel_err, lower, upper, in_marg, in_joint, ld_truth, ld_thr, int(eff.sum())
    )


# --------------------------------------------------------------------------- report


def _f(x) -> float:
    return float(np.asarray(x))


def summarize(
    pred,
    gt,
    *,
    mask=None,
    valid=None,
    level: float = 0.95,
    log_likelihood=None,
    particles=None,
    truth=None,
    labels: Sequence[str] | None = None,
    log_space: bool = False,
    noise_sigma=None,
    noise_kind: str = "gaussian",
    extra_variance=None,
) -> dict:
    """All metrics in one JSON-ready dict (floats, ints, bools, None; nested for parameters).

    Keys: ``level``; ``ci_width`` (trajectory units, pooled over points);
    ``fraction_outside`` (0-1) and ``pct_outside`` (percent, = 100 x fraction);
    ``predictive_nll`` (total nats) and ``predictive_nll_per_point``;
    ``n_points``, ``n_degenerate_points``; ``n_particles``, ``n_valid_particles``,
    ``n_invalid_particles``; with ``log_likelihood`` ``posterior_nll``; with
    ``particles`` and ``truth`` a ``parameters`` dict ``{label: {mean, truth,
    abs_error, rel_error, lower, upper, in_interval}}`` and ``truth_in_joint_region``
    (``None`` if undefined). Arguments as in the functions above.

    With ``noise_sigma`` (scalar or ``[P]`` m; ``noise_kind``) the headline band is the
    PREDICTIVE band (simulations + noise, :func:`noisy_predictive_interval`): ``ci_width``,
    ``pct_outside`` and ``predictive_nll*`` (:func:`noisy_predictive_nll`) refer to it, ``band`` is
    ``"predictive"`` and ``parameter_band`` holds ``ci_width`` / ``pct_outside`` of the
    parameter-only KDE band. Without it ``band`` is ``"parameter"`` (the KDE band, as before).
    ``extra_variance`` (``[*S]`` m^2, the force-noise-induced variance of each point,
    :func:`treeinfer.model.force_noise.point_variance`) widens the predictive band and its NLL.
    """
    pred = jnp.asarray(pred)
    eff = _effective_valid(pred, valid)
    lower, upper, _ = predictive_interval(pred, level, eff)
    frac = fraction_outside(lower, upper, gt, mask)
    pm = _point_mask(np.asarray(gt, float), mask)
    parameter_band = {"ci_width": _f(ci_width(lower, upper, pm)), "pct_outside": 100.0 * _f(frac)}
    if noise_sigma is not None:
        lower, upper, _ = noisy_predictive_interval(
            pred, noise_sigma, level, eff, noise_kind, extra_variance=extra_variance
        )
        frac = fraction_outside(lower, upper, gt, mask)
        nll = noisy_predictive_nll(
            pred, gt, noise_sigma, mask, eff, noise_kind, extra_variance=extra_variance
        )
    else:
        nll = predictive_nll(pred, gt, mask, eff)
    out = {
        "level": float(level),
        "band": "predictive" if noise_sigma is not None else "parameter",
        "parameter_band": parameter_band,
        "ci_width": _f(ci_width(lower, upper, pm)),
        "fraction_outside": _f(frac),
        "pct_outside": 100.0 * _f(frac),
        "predictive_nll": _f(nll.total),
        "predictive_nll_per_point": _f(nll.mean),
        "n_points": int(nll.n_points),
        "n_degenerate_points": int(nll.n_degenerate),
        "n_particles": int(pred.shape[0]),
        "n_valid_particles": int(np.sum(np.asarray(eff))),
        "n_invalid_particles": int(pred.shape[0] - np.sum(np.asarray(eff))),
    }
    if log_likelihood is not None:
        out["posterior_nll"] = _f(posterior_nll(log_likelihood, valid))
    if particles is not None and truth is not None:
        chk = posterior_vs_truth(particles, truth, level, valid, log=log_space)
        d = len(chk.mean)
        names = list(labels) if labels is not None else [f"theta[{i}]" for i in range(d)]
        if len(names) != d:
            raise ConfigError(f"labels: expected {d} names, got {len(names)}")
        t = np.log(np.asarray(truth, float)) if log_space else np.asarray(truth, float)
        out["parameters"] = {
            name: {
                "mean": float(chk.mean[i]),
                "truth": float(t[i]),
                "abs_error": float(chk.abs_error[i]),
                "rel_error": float(chk.rel_error[i]),
                "lower": float(chk.lower[i]),
                "upper": float(chk.upper[i]),
                "in_interval": bool(chk.in_marginal[i]),
            }
            for i, name in enumerate(names)
        }
        out["truth_in_joint_region"] = chk.in_joint
        out["parameter_space"] = "log" if log_space else "natural"
    return out
