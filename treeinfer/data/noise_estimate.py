"""White-noise estimation from recordings that real sensors and loggers produce: quantised
values (a stepper's 0.5 mm steps, a CSV written with few decimals) and upsampled streams (a
50 Hz stream written at 100 Hz by repeating or linearly interpolating samples).

The estimator (:func:`estimate_white_noise`) is the robust scale of second differences:
white noise of std sigma gives ``d2 = x[t+1] - 2 x[t] + x[t-1]`` of std ``sqrt(6) sigma``, a
smooth pull's second differences are tiny, and ``1.4826 MAD(d2) / sqrt(6)`` ignores the few
samples at force kinks. Two recordings break it, and each is recognised first:

* **Upsampled streams.** Linear interpolation by a factor k makes ``d2`` exactly zero (up to
  rounding) at k - 1 of every k samples, holding (repeating) samples makes the first
  difference zero there; the MAD then sees mostly zeros and returns ~0 (issue 27: 1e-5 mm for a
  50 Hz stream written at 100 Hz). :func:`detect_upsampling` finds the factor k and the phase of
  the native samples from where the differences' size concentrates (one phase of k carries them
  all) and the noise is estimated on the native samples (every k-th, at ``k dt``).
* **Quantised values.** Values on a grid of step q (:func:`quantisation_step`: every first
  difference an integer multiple of q) carry a rounding error of std ``q / sqrt(12)`` (uniform
  on a step) whatever the sensor's own noise; a stepper at rest gives zero second differences,
  and the MAD returns 0. The estimate is floored at ``q / sqrt(12)`` and says so.

A hand-written detector, not a library's: no installed package detects quantisation grids or
upsampling factors; both tests are a few lines of numpy, checked in ``tests/test_noise_estimate.py``
against series built with known steps and factors.

``coarse``: the pull's own curvature, not noise, dominates the second differences when the
recording is sampled coarsely or is noise-free. White noise gives ``d2`` a lag-1 correlation of
``-2/3``; a smooth signal gives ``+1``. Above :data:`COARSE_CORRELATION` the estimate is flagged
as an upper bound and its description names the flag that gives the noise explicitly.
"""

from __future__ import annotations

import math
import statistics
from typing import NamedTuple

import numpy as np

from ..errors import ConfigError

MIN_NOISE_SAMPLES = 20  # second differences needed for a noise estimate worth the name
MAX_FACTOR = 10  # largest upsampling factor looked for
PHASE_RATIO = 10.0  # one phase's median |difference| this many times every other phase's
QUANT_TOL = 1e-3  # |d / q - round(d / q)| below this share of a step counts as on the grid
QUANT_SHARE = 0.99  # ... for this share of the non-zero differences
ROUNDING_SHARE = 0.1  # moving second differences of one or two steps: at least this for a grid
COARSE_CORRELATION = 0.0  # lag-1 correlation of d2 above this: the signal dominates
_MAD_TO_STD = 1.0 / statistics.NormalDist().inv_cdf(0.75)  # 1.4826
_SQRT12 = math.sqrt(12.0)


class NoiseEstimate(NamedTuple):
    """A data-based white-noise estimate.

    sigma: the estimated white-noise standard deviation (m for displacement, N for force).
    n_used: number of second differences it was computed from.
    method: a one-line description of the estimator.
    step: the quantisation step detected (same unit), or None.
    factor: the upsampling factor detected (1: the stream is at its native rate).
    notes: sentences for the user (quantisation floor, upsampling, coarse sampling).
    coarse: the second differences are dominated by the signal: sigma is an upper bound.
    unit: ``"m"`` or ``"N"`` (for :meth:`describe`).
    """

    sigma: float
    n_used: int
    method: str
    step: float | None = None
    factor: int = 1
    notes: tuple = ()
    coarse: bool = False
    unit: str = "m"

    def describe(self) -> str:
        what = (
            f"displacement noise sigma_x ~ {self.sigma * 1e3:.3g} mm"
            if self.unit == "m"
            else f"force noise sigma_F ~ {self.sigma:.3g} N"
        )
        tail = "".join(f"; {n}" for n in self.notes)
        return f"{what} ({self.method}, n = {self.n_used}){tail}"


def _runs(values: np.ndarray, mask: np.ndarray) -> list[np.ndarray]:
    """The contiguous real (masked-in) stretches of every row, as 1-D float arrays."""
    out = []
    for x, m in zip(np.atleast_2d(values), np.atleast_2d(mask)):
        idx = np.flatnonzero(np.diff(np.concatenate([[0], m.astype(np.int8), [0]])))
        for a, b in zip(idx[::2], idx[1::2]):
            out.append(np.asarray(x[a:b], float))
    return out


def _scale(rows) -> float:
    """Largest |value| over the rows (float rounding tolerances are relative to it)."""
    return max((float(np.max(np.abs(r))) for r in rows if r.size), default=0.0)


def quantisation_step(rows, min_differences: int = 10) -> float | None:
    """The grid step q on which the values lie, or None.

    q is the smallest non-zero first difference, or an integer fraction of it (up to 1/10),
    such that at least :data:`QUANT_SHARE` of the non-zero first differences are integer
    multiples of q (to :data:`QUANT_TOL` of a step): then every row's values lie on a grid of
    step q. Unquantised data (float noise) have no such q: their smallest difference is tiny and
    the others are not multiples of it.

    An exactly piecewise-linear series (a simulated ramp-hold-release force, ``linspace``) also
    lies on a grid, of its slope per sample, but carries no rounding: where it moves, its second
    differences are zero except at a few kinks. Rounding error (within half a step) moves a
    second difference by one or two steps, and does so all along a moving signal (the first
    difference alternates between neighbouring multiples of q). So a grid counts only when at
    least :data:`ROUNDING_SHARE` of the second differences where the series moves are one or
    two steps (:func:`_moves_without_rounding`); a noise-free ramp gives None, and its estimate
    is then refused or switched off as noise-free rather than floored at ``slope / sqrt(12)``.
    (A quantised signal moving by exactly the same multiple of q every sample cannot be told
    from a noise-free ramp; it is read as one.)"""
    d = np.concatenate([np.abs(np.diff(r)) for r in rows if r.size > 1] or [np.zeros(0)])
    tiny = 1e-12 * max(_scale(rows), 1e-300)
    nz = d[d > tiny]
    if nz.size < min_differences:
        return None
    q0 = float(np.min(nz))
    for div in range(1, MAX_FACTOR + 1):
        q = q0 / div
        k = nz / q
        if np.max(k) > 1e7:  # a grid this fine relative to the steps is float noise, not a sensor
            return None
        if np.mean(np.abs(k - np.round(k)) <= QUANT_TOL) >= QUANT_SHARE:
            return None if _moves_without_rounding(rows, q, tiny) else q
    return None


def _moves_without_rounding(rows, q: float, tiny: float) -> bool:
    """True when, at the samples where the rows move (a non-zero first difference on either
    side), fewer than :data:`ROUNDING_SHARE` of the second differences are one or two steps
    ``q`` (rounding's jitter; a kink of a ramp is usually larger, and there are few of them):
    straight segments between kinks, not values rounded onto a grid."""
    jitter = moving = 0
    for r in rows:
        if r.size < 3:
            continue
        d1 = np.diff(r)
        at = (np.abs(d1[:-1]) > tiny) | (np.abs(d1[1:]) > tiny)
        d2 = np.abs(np.diff(d1)[at])
        moving += int(d2.size)
        jitter += int(np.sum((d2 > QUANT_TOL * q) & (d2 <= (2 + QUANT_TOL) * q)))
    return moving > 0 and jitter < ROUNDING_SHARE * moving


class Upsampling(NamedTuple):
    """factor: k (1: native); kind: ``"hold"`` (repeated samples) or ``"linear"``
    (interpolated), None at k = 1; starts: per row, the index of its first native sample."""

    factor: int
    kind: str | None
    starts: tuple


def _dominant_phase(a: np.ndarray, k: int) -> int | None:
    """The phase p (0..k-1) of ``a[p::k]`` whose median |a| exceeds every other phase's by
    :data:`PHASE_RATIO`, or None."""
    if a.size < 5 * k:
        return None
    med = np.array([np.median(np.abs(a[p::k])) for p in range(k)])
    p = int(np.argmax(med))
    rest = np.delete(med, p)
    if med[p] > 0 and np.all(rest * PHASE_RATIO <= med[p]):
        return p
    return None


def detect_upsampling(rows) -> Upsampling:
    """Upsampling factor of the rows (module docstring): the largest k in 2..:data:`MAX_FACTOR`
    for which every row long enough to tell has one phase of k carrying the first differences
    (``hold``) or the second differences (``linear``); else factor 1."""
    best = Upsampling(1, None, tuple(0 for _ in rows))
    for kind, order in (("hold", 1), ("linear", 2)):
        for k in range(2, MAX_FACTOR + 1):
            starts, judged = [], 0
            for r in rows:
                if r.size < 5 * k + order:
                    starts.append(0)
                    continue
                judged += 1
                p = _dominant_phase(np.diff(r, n=order), k)
                if p is None:
                    break
                # d1[i] = x[i+1] - x[i]: a new held value starts at i + 1; d2[i] is centred on
                # x[i + 1], which is then a knot of the interpolation
                starts.append((p + 1) % k)
            else:
                if judged and k > best.factor:
                    best = Upsampling(k, kind, tuple(starts))
    return best


def _second_differences(rows) -> np.ndarray:
    return np.concatenate([np.diff(r, n=2) for r in rows if r.size > 2] or [np.zeros(0)])


def _lag1(rows) -> float:
    """Pooled lag-1 correlation of the rows' second differences (NaN if too few)."""
    num = den = 0.0
    for r in rows:
        d2 = np.diff(r, n=2) if r.size > 3 else np.zeros(0)
        if d2.size < 3:
            continue
        d2 = d2 - np.median(d2)
        num += float(d2[1:] @ d2[:-1])
        den += float(d2 @ d2)
    return num / den if den > 0 else float("nan")


def estimate_white_noise(
    values,
    mask=None,
    *,
    what: str = "displacement",
    flag: str = "--noise-displacement",
    unit: str = "m",
    min_samples: int = MIN_NOISE_SAMPLES,
) -> NoiseEstimate:
    """White-noise std of ``values [B, T]`` at real samples ``mask [B, T]`` (module docstring).

    Raises :class:`ConfigError` naming ``flag`` when fewer than ``min_samples`` second
    differences remain at the native rate ("too short"), or when more than half of them are
    zero with no quantisation grid to floor the estimate (constant or piecewise-linear data)."""
    x = np.atleast_2d(np.asarray(values, float))
    m = np.ones(x.shape, bool) if mask is None else np.atleast_2d(np.asarray(mask, bool))
    rows = _runs(x, m)
    notes: list[str] = []
    up = detect_upsampling(rows)
    if up.factor > 1:
        rows = [r[s :: up.factor] for r, s in zip(rows, up.starts)]
        how = "repeated" if up.kind == "hold" else "linearly interpolated"
        notes.append(
            f"the {what} is upsampled {up.factor}x ({how} samples): noise estimated at the "
            f"native rate (every {up.factor}th sample); the likelihood counts each native "
            f"sample {up.factor} times, so resample the recording to its native rate for a "
            "calibrated posterior"
        )
    d2 = _second_differences(rows)
    if d2.size < min_samples:
        native = " at the native rate" if up.factor > 1 else ""
        raise ConfigError(
            f"trajectories: too short to estimate the {what} noise ({d2.size} second "
            f"differences{native}, need at least {min_samples}); give it explicitly ({flag}, "
            f"{'metres' if unit == 'm' else 'newtons'})"
        )
    sigma = _MAD_TO_STD * float(np.median(np.abs(d2 - np.median(d2)))) / math.sqrt(6.0)
    method = "robust MAD of second differences / sqrt(6)"
    q = quantisation_step(rows)
    if q is not None:
        floor = q / _SQRT12
        if not sigma > floor:
            sigma = floor
            method = f"quantisation floor step / sqrt(12), step {q:.4g} {unit}"
        notes.append(
            f"the {what} is quantised on a grid of {q:.4g} {unit}: noise floored at step / "
            f"sqrt(12) = {floor:.3g} {unit}"
        )
    if not sigma > 0.0:
        raise ConfigError(
            f"trajectories: cannot estimate the {what} noise: more than half of its second "
            "differences are zero and its values lie on no grid (constant or piecewise-linear "
            f"data); give it explicitly ({flag}, {'metres' if unit == 'm' else 'newtons'})"
        )
    rho = _lag1(rows)
    coarse = bool(math.isfinite(rho) and rho > COARSE_CORRELATION and q is None)
    if coarse:
        notes.append(
            f"the {what}'s second differences follow the pull itself (lag-1 correlation "
            f"{rho:.2f}, white noise gives -0.67): sampled too coarsely or noise-free, so this "
            f"is an upper bound; give the noise explicitly ({flag}) if you know it"
        )
    return NoiseEstimate(sigma, int(d2.size), method, q, up.factor, tuple(notes), coarse, unit)
