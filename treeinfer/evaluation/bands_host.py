"""The central interval of :func:`treeinfer.evaluation.bands.predictive_interval` on the host
(NumPy, SciPy's ``ndtr``) for a few series: the same Scott's-rule KDE and the same bisection on
its CDF as the jitted :func:`treeinfer.evaluation.bands._interval`, in float64 (the degenerate
test at the input dtype's rounding, as there); the ends agree with the float32 program's to
its precision, a few 1e-5 of the series' scale in the tails (``tests/test_bands_host.py``).

Why a second implementation: each shape of the jitted one is an XLA program of its own (a
60-step loop of the KDE's CDF), 1-1.7 s to compile on a 2-core CPU, and a run asks for two
small ones once each (summary.json's parameter intervals ``[P, D]`` and the truth check's
``[P, R]``), microseconds of work on the host. The bands of whole recordings (``[P, B, T]``)
stay jitted: the program is worth its compile there and is kept by the persistent cache.
"""

from __future__ import annotations

import numpy as np
from scipy.special import ndtr

__all__ = ["interval_host"]

# the KDE's constants, shared with treeinfer.evaluation.bands (which imports them from here)
_DEGENERATE_EPS_FACTOR = 16.0
_BRACKET_BANDWIDTHS = 10.0  # F(min - 10 h) <= Phi(-10) ~ 8e-24: below any useful level


def interval_host(pred, eff, alpha: float, n_iter: int, dtype):
    """``(lower, upper, mean)`` ``[*S]`` (``dtype``) of ``pred [P, *S]`` over the particles
    ``eff [P]`` (bool, at least 2), as :func:`treeinfer.evaluation.bands._interval` computes
    them."""
    eps = np.finfo(dtype).eps
    out, dtype = dtype, np.float64
    x = np.asarray(pred, dtype)
    eff = np.asarray(eff, bool)
    n = int(eff.sum())
    w = eff.astype(dtype) / max(n, 1)
    x = np.moveaxis(np.where(eff.reshape((-1,) + (1,) * (x.ndim - 1)), x, 0.0), 0, -1)
    mean = np.sum(w * x, axis=-1)
    var = np.sum(w * (x - mean[..., None]) ** 2, axis=-1) / (1.0 - np.sum(w**2))
    std = np.sqrt(var).astype(dtype)
    scale = np.max(np.where(eff, np.abs(x), 0.0), axis=-1)
    degenerate = std <= _DEGENERATE_EPS_FACTOR * eps * scale
    h = np.where(degenerate, 1.0, std * np.asarray(n, dtype) ** (-1.0 / 5.0)).astype(dtype)
    lo = np.min(np.where(eff, x, np.inf), axis=-1) - _BRACKET_BANDWIDTHS * h
    hi = np.max(np.where(eff, x, -np.inf), axis=-1) + _BRACKET_BANDWIDTHS * h
    q = np.array([alpha, 1.0 - alpha], dtype).reshape((2,) + (1,) * mean.ndim)
    lo, hi = (
        np.broadcast_to(lo, q.shape[:1] + lo.shape),
        np.broadcast_to(hi, q.shape[:1] + hi.shape),
    )
    for _ in range(n_iter):
        mid = (0.5 * (lo + hi)).astype(dtype)
        cdf = np.sum(w * ndtr((mid[..., None] - x) / h[..., None]), axis=-1)
        below = cdf < q
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    ends = np.where(degenerate, mean, 0.5 * (lo + hi)).astype(out)
    return ends[0], ends[1], mean.astype(out)
