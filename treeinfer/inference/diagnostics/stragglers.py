"""Stuck (straggler) particles: detection, counts and remedies (split from
:mod:`treeinfer.inference.diagnostics`, which re-exports every name)."""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ...errors import ConfigError
from .core import _labels

# --------------------------------------------------------------------------- stragglers
#
# A straggler is a particle stuck far from the bulk: its log density is far below the others'
# (robust z-score, median/MAD, so the stuck particles themselves do not inflate the scale) or it
# sits far outside the prior box. SVGD's repulsion and Adam's per-particle step size can leave
# such particles behind for the whole run; summaries over all particles then inherit them (the
# issue-11 case: 7 of 32 particles at log p ~ -296 with Kd 219-394 for a box [0.05, 10]).

Z_MAX = 5.0  # robust z below -Z_MAX: straggler (5 MADs: a Gaussian bulk has P(z < -5) ~ 3e-7)
FALSE_ALARM = 1e-3  # ... and further below the median than exact posterior draws go (see below)
MAX_BOX_EXCESS = 0.5  # ... or farther outside the box than this share of its width (5 x the
#                       default smoothed-box tail width, 0.1 of the width: prior density e^-12.5
#                       of the box's; mass merely piling at an edge is prior_edge_mass's job)
_MAD_TO_SD = 1.4826  # MAD of a normal distribution x 1.4826 = its standard deviation


class StragglerReport(NamedTuple):
    """Result of :func:`find_stragglers` (host numpy arrays and plain values).

    mask: [P] bool, particle is a straggler (any of the three reasons below).
    low_density: [P] bool, robust z-score of log p below ``-z_max`` and ``min_gap`` nats below
      the median. nonfinite: [P] bool, log p not finite (failed simulation).
    outside_box: [P] bool, farther than ``max_box_excess`` box widths outside the box in some
      coordinate.
    robust_z: [P] ``(log p - median) / (1.4826 MAD)`` (NaN for non-finite log p).
    box_excess: [P] largest distance outside the box over coordinates, in box widths (0 inside).
    n_stragglers, n_particles: counts. warnings: human-readable lines (empty: none found).
    """

    mask: np.ndarray
    low_density: np.ndarray
    nonfinite: np.ndarray
    outside_box: np.ndarray
    robust_z: np.ndarray
    box_excess: np.ndarray
    n_stragglers: int
    n_particles: int
    warnings: list


def chi2_gap(dim: int, n_particles: int, false_alarm: float = FALSE_ALARM) -> float:
    """Nats below the median log density that exact draws from a Gaussian posterior in ``dim``
    dimensions reach with probability ``false_alarm`` among ``n_particles``.

    Near a mode, ``2 (log p_max - log p) ~ chi2_dim``, i.e. ``Gamma(dim / 2)`` in nats: its
    exponential lower tail is much longer than a median/MAD z-score assumes (a 5-MAD cut alone
    flags 5-10% of runs of 32 exact draws at D = 4-12). Returns
    ``Gamma(dim/2).ppf(1 - false_alarm / n_particles) - Gamma(dim/2).median()``.
    """
    from scipy.stats import gamma

    k = dim / 2.0
    return float(gamma.ppf(1.0 - false_alarm / max(n_particles, 1), k) - gamma.median(k))


def straggler_mask(
    log_density,
    theta,
    lower,
    upper,
    *,
    z_max: float = Z_MAX,
    min_gap: float | None = None,
    max_box_excess: float = MAX_BOX_EXCESS,
):
    """Jittable core of :func:`find_stragglers`: ``(mask, low, nonfinite, outside, z, excess)``.

    Args:
      log_density: [P] log posterior density (nats). theta: [P, D] particles (theta units).
      lower, upper: [D] prior box (theta units).
      min_gap: nats below the median a low-density straggler must also be; None (default):
        :func:`chi2_gap` for these D and P.
    All outputs are [P] jax arrays. With fewer than 3 finite particles no particle is
    flagged for low density (a median of two says nothing about which one is stuck).
    """
    ld = jnp.asarray(log_density)
    x = jnp.asarray(theta)
    if min_gap is None:
        min_gap = chi2_gap(x.shape[-1], x.shape[0])
    lo, hi = jnp.asarray(lower, x.dtype), jnp.asarray(upper, x.dtype)
    fin = jnp.isfinite(ld)
    n_fin = jnp.sum(fin)
    # median / MAD over the finite entries (nanmedian ignores the NaNs we put in)
    ldn = jnp.where(fin, ld, jnp.nan)
    med = jnp.nanmedian(ldn)
    mad = jnp.nanmedian(jnp.abs(ldn - med))
    # scale floored at min_gap / z_max: a bulk of near-identical particles would give MAD ~ 0
    scale = jnp.maximum(_MAD_TO_SD * mad, min_gap / z_max)
    z = (ldn - med) / scale
    low = fin & (z < -z_max) & (ld < med - min_gap) & (n_fin >= 3)
    width = hi - lo
    excess = jnp.max(jnp.maximum(jnp.maximum(lo - x, x - hi), 0.0) / width, axis=-1)
    outside = excess > max_box_excess
    mask = low | ~fin | outside
    return mask, low, ~fin, outside, z, excess


@functools.partial(jax.jit, static_argnums=(4, 5, 6))
def _straggler_mask_jit(log_density, theta, lower, upper, z_max, min_gap, max_box_excess):
    return straggler_mask(
        log_density, theta, lower, upper, z_max=z_max, min_gap=min_gap,
        max_box_excess=max_box_excess,
    )  # fmt: skip


def find_stragglers(
    log_density,
    theta,
    lower,
    upper,
    *,
    labels: Sequence[str] | None = None,
    z_max: float = Z_MAX,
    min_gap: float | None = None,
    max_box_excess: float = MAX_BOX_EXCESS,
) -> StragglerReport:
    """Find stuck / straggler particles among final particles.

    Args:
      log_density: [P] log posterior density of each particle (nats; -inf/NaN = failed).
      theta: [P, D] particles (theta units: natural log of Kp, Kd in treeinfer).
      lower, upper: [D] prior box in theta units.
      labels: D parameter names used in the warnings.
      z_max: flag log densities with robust z-score below ``-z_max`` (median/MAD) ...
      min_gap: ... that are also at least this many nats below the median (None:
        :func:`chi2_gap`, farther than exact draws from a Gaussian posterior go but in one
        of ~1000 runs).
      max_box_excess: flag particles farther outside the box than this share of its width.

    Returns:
      :class:`StragglerReport`; its ``warnings`` say how many, why, and the range of the
      stragglers' log density against the bulk's.
    """
    ld = np.asarray(log_density, dtype=float)
    x = np.asarray(theta, dtype=float)
    if ld.ndim != 1 or x.ndim != 2 or x.shape[0] != ld.shape[0]:
        raise ConfigError(
            f"find_stragglers: expected log_density [P] and theta [P, D], got {ld.shape} and "
            f"{x.shape}"
        )
    lo = np.broadcast_to(np.asarray(lower, dtype=float), x.shape[1:])
    hi = np.broadcast_to(np.asarray(upper, dtype=float), x.shape[1:])
    if not np.all(hi > lo):
        raise ConfigError(f"find_stragglers: need lower < upper, got {lo} and {hi}")
    for nm, v in (("z_max", z_max), ("min_gap", min_gap), ("max_box_excess", max_box_excess)):
        if v is not None and not (np.isfinite(v) and v >= 0):
            raise ConfigError(f"find_stragglers: {nm} must be a finite number >= 0, got {v!r}")
    names = _labels(labels, x.shape[1])
    if min_gap is None:  # a number, for the jitted mask (the default's from these shapes)
        min_gap = chi2_gap(x.shape[-1], x.shape[0])
    # one compiled program: called eagerly, its 20-odd operations each compiled (and, on a
    # warm cache, loaded) a program of its own, 0.5-1 s of a cold `treeinfer infer`
    out = _straggler_mask_jit(ld, x, lo, hi, float(z_max), float(min_gap), float(max_box_excess))
    mask, low, nonfin, outside, z, excess = (np.asarray(a) for a in out)
    P = ld.shape[0]
    msgs = []
    bulk = ~mask & np.isfinite(ld)
    if low.any():
        bulk_txt = f"{ld[bulk].min():.4g} ... {ld[bulk].max():.4g}" if bulk.any() else "none"
        msgs.append(
            f"{int(low.sum())} of {P} particles are stuck: log density {ld[low].min():.4g} ... "
            f"{ld[low].max():.4g} against {bulk_txt} for the rest (robust z < -{z_max:g}); "
            "summaries over all particles include them - re-initialise them during warm-up, "
            "drop them, or run longer"
        )
    if outside.any():
        d = np.argmax(np.maximum(np.maximum(lo - x, x - hi), 0.0) / (hi - lo), axis=1)
        worst = [names[i] for i in sorted(set(d[outside].tolist()))]
        msgs.append(
            f"{int(outside.sum())} of {P} particles lie more than {max_box_excess:g} box widths "
            f"outside the prior box (up to {excess[outside].max():.2f} widths; in "
            f"{', '.join(worst)}): the prior's smooth tails let them drift"
        )
    if nonfin.any():
        msgs.append(
            f"{int(nonfin.sum())} of {P} particles have a non-finite log density "
            "(unstable simulation)"
        )
    return StragglerReport(
        mask=mask,
        low_density=low,
        nonfinite=nonfin,
        outside_box=outside,
        robust_z=z,
        box_excess=excess,
        n_stragglers=int(mask.sum()),
        n_particles=P,
        warnings=msgs,
    )


def reinit_stragglers(rng_key, theta, mask, jitter: float = 0.1):
    """Move straggler particles next to randomly chosen good ones (pure, jittable).

    Each particle with ``mask`` True is replaced by a uniformly drawn particle with ``mask``
    False plus Gaussian jitter of ``jitter`` x the good particles' per-coordinate standard
    deviation (so the copies do not coincide with their source: SVGD's kernel would glue
    them). With no good particle, or none flagged, ``theta`` is returned unchanged.

    Args:
      rng_key: JAX key. theta: [P, D]. mask: [P] bool. jitter: >= 0, share of the bulk's spread.
    Returns:
      [P, D] new particles (same dtype).
    """
    x = jnp.asarray(theta)
    mask = jnp.asarray(mask, bool)
    good = ~mask
    n_good = jnp.sum(good)
    k_pick, k_noise = jax.random.split(rng_key)
    p = good / jnp.maximum(n_good, 1)
    idx = jax.random.choice(k_pick, x.shape[0], shape=(x.shape[0],), p=p)
    g = good[:, None]
    mean = jnp.sum(jnp.where(g, x, 0.0), 0) / jnp.maximum(n_good, 1)
    var = jnp.sum(jnp.where(g, jnp.square(x - mean), 0.0), 0) / jnp.maximum(n_good - 1, 1)
    noise = jax.random.normal(k_noise, x.shape, x.dtype) * jitter * jnp.sqrt(var)
    new = x[idx] + noise
    return jnp.where(mask[:, None] & (n_good > 0), new, x)


def drop_stragglers(theta, log_density, mask):
    """Particles without the stragglers: ``(theta [P', D], log_density [P'])`` as numpy."""
    keep = ~np.asarray(mask, bool)
    return np.asarray(theta)[keep], np.asarray(log_density)[keep]


class ReinitStragglers(NamedTuple):
    """Warm-up remedy for :func:`treeinfer.inference.samplers.run`: after every chunk ending at or
    before iteration ``until``, stragglers (as :func:`straggler_mask` with these thresholds and the
    box ``lower``/``upper`` [D]) are moved next to good particles (:func:`reinit_stragglers`)
    and their sampler state is re-initialised; the others' state is untouched."""

    until: int
    lower: Any
    upper: Any
    z_max: float = Z_MAX
    min_gap: float | None = None
    max_box_excess: float = MAX_BOX_EXCESS
    jitter: float = 0.1
