"""SVGD convergence (kernelized Stein discrepancy, moment change, early stopping), MCMC
summaries from the post-warm-up trace, and prior-edge mass (split from
:mod:`treeinfer.inference.diagnostics`, which re-exports every name)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from ...errors import ConfigError
from .core import _labels, mcmc_diagnostics

# --------------------------------------------------------------------------- Stein discrepancy
#
# Kernelized Stein discrepancy (Liu, Lee & Jordan 2016; Gorham & Mackey 2017) with the inverse
# multiquadric kernel k(x, y) = (c^2 + |x - y|^2)^beta, beta = -1/2, which (unlike the RBF)
# detects non-convergence in the tails (Gorham & Mackey, Theorem 8). Written here because no
# maintained JAX implementation exists (BlackJAX has none; its users ask for one); the closed
# form of the Stein kernel below is checked against autodiff of k in tests/test_convergence.py.
# Particles are standardised per coordinate first (x' = (x - m) / s, grad' = s * grad, the same
# log density in the new coordinates), so the kernel's unit length means "one posterior sd" in
# every coordinate whatever the parameter units.


def kernel_stein_discrepancy(
    theta, grad, *, c: float = 1.0, beta: float = -0.5, standardise: bool = True
):
    """IMQ kernelized Stein discrepancy of particles against the target whose score they carry.

    Args:
      theta: [P, D] particles. grad: [P, D] gradient of the target log density at them
        (uphill; exactly what SVGD states hold). Rows with a non-finite value are left out.
      c, beta: IMQ kernel ``(c^2 + r^2)^beta`` with ``c > 0`` and ``-1 < beta < 0``.
      standardise: measure in per-coordinate standardised units (default).
    Returns:
      scalar KSD = sqrt of the V-statistic ``mean_ij u_p(x_i, x_j)`` (>= 0, jax array, same
      units as a score times a standard deviation: dimensionless after standardising). For
      particles drawn from the target it is ``O(P^-1/2)``; it does not go to 0 for a fixed
      number of SVGD particles, so read its plateau, not its value.
    """
    x = jnp.asarray(theta)
    g = jnp.asarray(grad, x.dtype)
    ok = jnp.all(jnp.isfinite(x), -1) & jnp.all(jnp.isfinite(g), -1)
    w = ok.astype(x.dtype)
    n = jnp.maximum(jnp.sum(w), 1.0)
    x = jnp.where(ok[:, None], x, 0.0)
    g = jnp.where(ok[:, None], g, 0.0)
    if standardise:
        m = jnp.sum(x * w[:, None], 0) / n
        s = jnp.sqrt(jnp.sum(jnp.square(x - m) * w[:, None], 0) / jnp.maximum(n - 1, 1.0))
        s = jnp.where(s > 0, s, 1.0)
        x = (x - m) / s
        g = g * s
    d = x.shape[-1]
    r = x[:, None, :] - x[None, :, :]  # [P, P, D], r_ij = x_i - x_j
    r2 = jnp.sum(r * r, -1)
    q = c * c + r2
    gg = g @ g.T
    # u(x, y) = s_x.s_y k + s_x.grad_y k + s_y.grad_x k + tr(grad_x grad_y k)
    r_dot = jnp.einsum("ijd,jd->ij", r, g) - jnp.einsum("ijd,id->ij", r, g)  # r.(s_y - s_x)
    u = (
        gg * q**beta
        + 2 * beta * q ** (beta - 1) * r_dot
        - 2 * beta * d * q ** (beta - 1)
        - 4 * beta * (beta - 1) * r2 * q ** (beta - 2)
    )
    v = jnp.sum(u * w[:, None] * w[None, :]) / (n * n)
    return jnp.sqrt(jnp.maximum(v, 0.0))


def moment_change(previous, current) -> float:
    """Largest change of the particles' per-coordinate mean and spread between two snapshots.

    ``max_d max(|m1 - m0| / s1, |log(s1 / s0)|)`` over finite rows of ``previous`` and
    ``current`` ([P, D] each; the particles need not correspond): the mean shift in units
    of the current standard deviation, and the relative change of the spread. 0 = no change.
    """
    a, b = np.asarray(previous, float), np.asarray(current, float)
    a = a[np.all(np.isfinite(a), 1)]
    b = b[np.all(np.isfinite(b), 1)]
    if len(a) < 2 or len(b) < 2:
        return float("inf")
    m0, m1 = a.mean(0), b.mean(0)
    s0, s1 = a.std(0, ddof=1), b.std(0, ddof=1)
    tiny = 1e-12
    with np.errstate(divide="ignore", invalid="ignore"):
        shift = np.abs(m1 - m0) / np.maximum(s1, tiny)
        spread = np.abs(np.log(np.maximum(s1, tiny) / np.maximum(s0, tiny)))
    return float(np.max(np.maximum(shift, spread)))


class ConvergenceCriterion(NamedTuple):
    """Stop rule for :func:`treeinfer.inference.samplers.run` (``stop_when=``), checked between
    chunks.

    Converged when, at a chunk end at or after ``min_iterations``: the particles' moments
    changed by less than ``moment_tol`` (:func:`moment_change`, in posterior sds) since the
    previous check, and, when the sampler records ``ksd`` (SVGD/NNSVGD), the mean KSD of the
    last ``window`` iterations differs from that of the ``window`` before by less than
    ``ksd_rtol`` (relative). Checks run at chunk ends, so ``chunk_size`` (default 100) sets how
    often; pick a smaller chunk (e.g. 25) for finer stopping.
    """

    min_iterations: int = 50
    moment_tol: float = 0.05
    ksd_rtol: float = 0.05
    window: int = 20

    def __call__(self, iteration: int, positions, previous_positions, diagnostics: dict):
        """``'converged: ...'`` (a reason) or None. positions, previous_positions: [P, D]."""
        if iteration < self.min_iterations or previous_positions is None:
            return None
        dm = moment_change(previous_positions, positions)
        if not dm < self.moment_tol:
            return None
        reason = f"converged at iteration {iteration}: moments changed by {dm:.3g} sd"
        ksd = diagnostics.get("ksd")
        if ksd is not None:
            k = np.asarray(ksd, float)
            w = self.window
            if k.size < 2 * w:
                return None
            k0, k1 = np.nanmean(k[-2 * w : -w]), np.nanmean(k[-w:])
            rel = abs(k1 - k0) / max(abs(k0), 1e-12)
            if not rel < self.ksd_rtol:
                return None
            reason += f", KSD {k1:.3g} changed by {100 * rel:.1f}% over {w} iterations"
        return reason


# --------------------------------------------------------------------------- MCMC draws


def mcmc_draws(trace_positions, warmup, thin: int = 1, log_density=None):
    """Posterior draws of an MCMC trace: all chains, warm-up discarded, thinned.

    Args:
      trace_positions: [S, C, D] recorded positions (S trace entries of C chains; treeinfer's
        ``RunResult.trace_positions``, entry 0 being the initial state on fresh runs).
      warmup: trace entries discarded at the start: an int (count) or a float in [0, 1)
        (share of S, e.g. 0.5 = the first half, as :func:`mcmc_diagnostics` ``burn_in``).
      thin: keep every ``thin``-th entry after the warm-up (>= 1).

      log_density: optional [S, C] log density of the trace entries.

    Returns:
      [N, D] draws, N = C x ceil((S - warmup) / thin) minus rows with a non-finite
      coordinate (chains stuck in an unstable region); ordered entry by entry, chains within.
      With ``log_density``: ``(draws [N, D], log_density [N])``.
    """
    x = np.asarray(trace_positions, dtype=float)
    if x.ndim != 3:
        raise ConfigError(f"trace_positions: expected shape [S, C, D], got {x.shape}")
    k = _warmup_count(warmup, x.shape[0])
    if isinstance(thin, bool) or not isinstance(thin, (int, np.integer)) or thin < 1:
        raise ConfigError(f"thin: expected a positive integer, got {thin!r}")
    kept = x[k::thin]
    if kept.shape[0] == 0:
        raise ConfigError(
            f"mcmc_draws: nothing left after a warm-up of {k} of {x.shape[0]} trace entries"
        )
    draws = kept.reshape(-1, x.shape[2])
    ok = np.all(np.isfinite(draws), axis=1)
    if log_density is None:
        return draws[ok]
    ld = np.asarray(log_density, dtype=float)
    if ld.shape != x.shape[:2]:
        raise ConfigError(f"log_density: expected shape {x.shape[:2]}, got {ld.shape}")
    return draws[ok], ld[k::thin].reshape(-1)[ok]


def _warmup_count(warmup, n: int) -> int:
    if isinstance(warmup, bool):
        raise ConfigError(f"warmup: expected a count or a fraction, got {warmup!r}")
    if isinstance(warmup, (int, np.integer)):
        if not 0 <= warmup < n:
            raise ConfigError(f"warmup: expected 0 <= warmup < {n} trace entries, got {warmup}")
        return int(warmup)
    w = float(warmup)
    if not 0.0 <= w < 1.0:
        raise ConfigError(f"warmup: a fraction must lie in [0, 1), got {warmup!r}")
    return math.floor(w * n)


def mcmc_summary(
    trace_positions,
    labels: Sequence[str] | None = None,
    *,
    warmup=0.5,
    thin: int = 1,
    log_density=None,
) -> dict:
    """Post-warm-up draws and their R-hat / ESS, for summary.json / particles.csv / evaluate.

    Returns ``{"draws": [N, D] (mcmc_draws), "diagnostics": mcmc_diagnostics(...) on the
    post-warm-up trace (unthinned: thinning only discards information for R-hat/ESS),
    "warmup": entries discarded, "thin": thin, "n_draws": N}``.
    """
    x = np.asarray(trace_positions, dtype=float)
    draws = mcmc_draws(x, warmup, thin)
    k = _warmup_count(warmup, x.shape[0]) if x.ndim == 3 else 0
    diag = mcmc_diagnostics(x, labels, burn_in=k / x.shape[0], log_density=log_density)
    return {
        "draws": draws,
        "diagnostics": diag,
        "warmup": k,
        "thin": int(thin),
        "n_draws": int(draws.shape[0]),
    }


# --------------------------------------------------------------------------- prior edge

MAX_EDGE_SHARE = 0.1  # warn when more than 10% of the particles sit beyond one edge of the box


def prior_edge_mass(
    theta, lower, upper, *, labels: Sequence[str] | None = None, max_share: float = MAX_EDGE_SHARE
) -> dict:
    """Posterior mass piling up at (or beyond) a prior-box edge.

    The smoothed box prior is flat inside ``[lower, upper]`` and has Gaussian tails outside;
    mass beyond an edge means the data push against the box: the interval is then set by the
    tail width (``--prior-tail``), not by the data.

    Args:
      theta: [P, D] particles or draws (theta units). lower, upper: [D] box.
      max_share: warn when the share beyond one edge of a parameter exceeds this.
    Returns:
      ``{"parameters": {label: {"below": share below lower, "above": share above upper}},
      "warnings": [...]}`` (shares over finite rows).
    """
    x = np.asarray(theta, dtype=float)
    if x.ndim != 2:
        raise ConfigError(f"prior_edge_mass: theta must be [P, D], got {x.shape}")
    x = x[np.all(np.isfinite(x), 1)]
    lo = np.broadcast_to(np.asarray(lower, float), x.shape[1:])
    hi = np.broadcast_to(np.asarray(upper, float), x.shape[1:])
    names = _labels(labels, x.shape[1])
    params, msgs = {}, []
    n = max(len(x), 1)
    for i, name in enumerate(names):
        below = float(np.sum(x[:, i] < lo[i]) / n)
        above = float(np.sum(x[:, i] > hi[i]) / n)
        params[name] = {"below": below, "above": above}
        for side, share, edge in (("lower", below, lo[i]), ("upper", above, hi[i])):
            if share > max_share:
                msgs.append(
                    f"{name}: {100 * share:.0f}% of the posterior lies beyond the {side} edge of "
                    f"the prior box ({math.exp(edge):.4g} in natural units): the data push "
                    "against the box, so this interval reflects the prior's tail width "
                    "(--prior-tail); widen the box if the value is physically possible"
                )
    return {"parameters": params, "warnings": msgs}
