"""The Levenberg–Marquardt iteration behind :func:`treeinfer.inference.mapfit.fit_map` and
:func:`treeinfer.inference.batch.map_fits`: damped Gauss–Newton steps on N points at once, on
the host in NumPy (D is small), with one batched evaluation of value, gradient and curvature
per iteration (the caller's jitted ``jax.vmap``, over points and, for ``map_fits``, data sets).

Why our own: neither ``scipy.optimize.least_squares`` nor ``jaxopt.LevenbergMarquardt`` takes
the Boltzmann loss (a sum of norms, not of squares) or a prior curvature, and scipy would
evaluate one point at a time.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from ..errors import ConfigError

__all__ = ["LMResult", "levenberg_marquardt"]


class LMResult(NamedTuple):
    """Result of :func:`levenberg_marquardt` (NumPy arrays, N points of D coordinates).

    theta: [N, D] final points; values: [N] objective there (+inf: no valid start);
    curvature: [N, D, D] the evaluated curvature there; extras: the evaluator's extra per-point
    arrays there; converged: [N] whether each point met the tolerance; iterations: run."""

    theta: np.ndarray
    values: np.ndarray
    curvature: np.ndarray
    extras: tuple
    converged: np.ndarray
    iterations: int


def levenberg_marquardt(
    evaluate: Callable,
    starts,
    max_iterations: int,
    tolerance: float,
    max_step: float,
    agree: int | None = None,
    n_extras: int = 0,
) -> LMResult:
    """The Levenberg–Marquardt iteration of :func:`fit_map` (and of
    :func:`treeinfer.inference.batch.map_fits`, whose points are several data sets' starts),
    run on the host on N points at once.

    ``evaluate(theta [N, D]) -> (objective [N], gradient [N, D], curvature [N, D, D], *extras)``
    with ``n_extras`` further per-point arrays ([N, ...], kept at the accepted points): one
    batched call per iteration, e.g. a jitted ``jax.vmap`` over points (and data sets). Each
    point takes Marquardt-scaled damped Gauss–Newton steps (at most ``max_step`` in any
    coordinate), accepted when the objective falls; a point stops when an accepted step lowers
    it by less than ``tolerance * (1 + |f|)``, its step is below ``tolerance`` everywhere, or its
    damping exceeds 1e10. ``agree``: see :func:`fit_map` (all N points are one fit's starts).
    """
    theta = np.array(starts, float)  # a writable copy
    f, g, h, *extras = (np.array(x, float) for x in evaluate(theta))
    if len(extras) != n_extras:
        raise ConfigError(f"evaluate returned {len(extras)} extra arrays, expected {n_extras}")
    n = theta.shape[0]
    scale0 = np.array([np.mean(np.abs(np.diag(hi))) + 1e-12 for hi in h])
    lam = 1e-3 * np.ones(n)
    done = ~np.isfinite(f)
    converged = np.zeros(n, bool)
    iterations = 0
    for iterations in range(1, max_iterations + 1):
        steps = np.zeros_like(theta)
        for i in np.flatnonzero(~done):
            # Marquardt's scaling, floored so unidentified directions still get damped
            damp = lam[i] * (np.diag(h[i]) + 1e-6 * scale0[i])
            try:
                step = np.linalg.solve(h[i] + np.diag(damp), -g[i])
            except np.linalg.LinAlgError:
                step = -g[i] / (np.diag(h[i]) + damp + 1e-12)
            big = np.max(np.abs(step))
            steps[i] = step if big <= max_step else step * (max_step / big)
        trial = theta + steps
        ft, gt, ht, *extras_t = (np.array(x, float) for x in evaluate(trial))
        accept = ~done & np.isfinite(ft) & (ft < f)
        small = np.max(np.abs(steps), axis=1) < tolerance
        flat = accept & ((f - ft) < tolerance * (1.0 + np.abs(f)))
        theta[accept], f[accept], g[accept], h[accept] = (
            trial[accept],
            ft[accept],
            gt[accept],
            ht[accept],
        )
        for x, xt in zip(extras, extras_t):
            x[accept] = xt[accept]
        lam = np.where(accept, np.maximum(lam / 3.0, 1e-9), lam * 4.0)
        newly = ~done & (flat | small)
        converged |= newly
        done |= newly | (lam > 1e10)
        if done.all():
            break
        if agree is not None and np.isfinite(f).any():
            low = np.min(np.where(np.isfinite(f), f, np.inf))
            at_low = converged & (f - low <= math.sqrt(tolerance) * (1.0 + abs(low)))
            if at_low.sum() >= agree:
                break
    return LMResult(theta, f, h, tuple(extras), converged, iterations)
