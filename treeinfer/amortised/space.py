"""The coordinates the flow works in: each parameter column mapped through the prior's own
marginal (the smoothed box: a uniform on [lower, upper] with Gaussian tails of std ``tail``,
:func:`treeinfer.amortised.simulations.draw_prior`) and the standard normal's quantile,
``u = Phi^-1(F(theta))``, so that the prior is a standard normal in each column.

Why (session 13): the flow in the box's linear coordinates (``z = (theta - centre) /
half-width``) must itself learn the prior's shape, a flat box with Gaussian shoulders, which
an affine autoregressive flow (a Gaussian base moved and stretched column by column) draws as
a rounded hump; where the data say little (the damping of a short pull) the posterior is that
shape. In ``u`` the prior is the base Gaussian itself. Measured at the CPU size
(experiments/results/amortised_cpu_two_branch_s13/README.md, two training seeds): the largest
coverage gap 3.4-3.6 points against 3.8-7.3 in the box's coordinates (Kd[child], the damping
the data say least about, under-covered at 50% in the box: 43-46%), the sharpness alike.

Computed in float64 with SciPy's log-space normal functions (``log_ndtr``, ``ndtri_exp``), on
the half of each column nearer its lower edge (the other half by reflection), so that a draw
far in a tail keeps its digits."""

from __future__ import annotations

import math

import numpy as np
from scipy.special import log_ndtr, ndtri_exp

# the map's tail for a column whose prior has none (log sigma_x: log-uniform in its range), as
# a share of the width: a bijection of the whole line, whatever a proposal draws
MIN_TAIL_SHARE = 0.1
_HALF_LOG_2PI = 0.5 * math.log(2 * math.pi)


class ProbitSpace:
    """``u = Phi^-1(F(theta))`` per column, ``F`` the smoothed box's CDF."""

    def __init__(self, lower, upper, tail):
        self.lo = np.asarray(lower, float)
        self.hi = np.asarray(upper, float)
        width = self.hi - self.lo
        self.s = np.maximum(np.asarray(tail, float), MIN_TAIL_SHARE * width)
        self.c = self.s * math.sqrt(2 * math.pi)  # the two tails' mass, unnormalised
        self.log_z = np.log(width + self.c)
        self.log_edge = np.log(self.c / 2) - self.log_z  # log F at the lower edge

    def _reflect(self, theta):
        """``(theta on the lower half, +1 / -1)``."""
        upper_half = theta > (self.lo + self.hi) / 2
        return np.where(upper_half, self.lo + self.hi - theta, theta), np.where(upper_half, -1, 1)

    def _log_cdf_lower(self, t):
        below = t < self.lo
        with np.errstate(divide="ignore", invalid="ignore"):
            tail = np.log(self.c) - self.log_z + log_ndtr((t - self.lo) / self.s)
            inside = np.log(np.maximum(self.c / 2 + t - self.lo, 1e-300)) - self.log_z
        return np.where(below, tail, inside)

    def to_u(self, theta) -> np.ndarray:
        t, sign = self._reflect(np.asarray(theta, float))
        return sign * ndtri_exp(self._log_cdf_lower(t))

    def from_u(self, u) -> np.ndarray:
        u = np.asarray(u, float)
        log_p = log_ndtr(-np.abs(u))  # the lower half's probability
        with np.errstate(over="ignore"):
            tail = self.lo + self.s * ndtri_exp(np.minimum(log_p - self.log_edge + np.log(0.5), 0))
            inside = self.lo + np.exp(log_p + self.log_z) - self.c / 2
        t = np.where(log_p < self.log_edge, tail, inside)
        return np.where(u > 0, self.lo + self.hi - t, t)

    def log_abs_det(self, theta) -> np.ndarray:
        """[n] ``sum_j log |du_j / dtheta_j|`` = log prior density - log standard normal at u."""
        theta = np.asarray(theta, float)
        u = self.to_u(theta)
        below = np.minimum(theta - self.lo, 0) / self.s
        above = np.maximum(theta - self.hi, 0) / self.s
        log_f = -0.5 * (below**2 + above**2) - self.log_z
        return np.sum(log_f + 0.5 * u**2 + _HALF_LOG_2PI, axis=-1)
