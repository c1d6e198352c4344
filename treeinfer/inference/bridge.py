"""A tempered bridge from a broad Student-t to the posterior: sequential Monte Carlo with adaptive
tempering, run where the start pipeline's importance weights fail (Pareto k_hat above the limit),
before resample-move settles the cloud at the posterior (:mod:`treeinfer.inference.resample_move`).

Why: SBC of the default command on 192 data sets (``experiments/results/sbc_default_s14/``) held
the true gains in 68-77% of the 95% intervals where the weights had failed and resample-move had
started from them. On one such data set (index 90) the importance draws sat on a side lobe of a
curved ridge; the Metropolis chains started there drifted towards the posterior's bulk (the
parent's stiffness in the prior's tail beyond the box) by a few hundredths of a standard deviation
per sweep, slowly enough to pass the "cloud stopped changing" rule after 40 sweeps with the truth
5-8 sd out, and had not arrived after 200. Chains that start in every part of the posterior need no
such travel: tempering moves the particles' *weights* between the parts of the posterior as the
likelihood is switched on, where Metropolis alone has to move the particles themselves.

The bridge (Neal 2001; Del Moral, Doucet & Jasra 2006; Chopin 2002), on the geometric path

    log pi_beta(x) = (1 - beta) log q(x) + beta log p(x),   beta: 0 -> 1,

from ``q``, a Student-t (df :data:`REFERENCE_DF`) at the importance draws' weighted mean with
their weighted covariance inflated :data:`REFERENCE_INFLATE` times in std (broad enough to cover
the lobes the draws missed), to ``p``, the posterior. Each stage picks the next ``beta`` by
bisection so that the incremental weights keep an effective sample size of :data:`STAGE_ESS` of
the chains (adaptive tempering, Jasra et al. 2011), resamples systematically, then runs
:data:`STAGE_SWEEPS` random-walk Metropolis sweeps at ``pi_beta`` with the cloud's covariance
(scale adapted towards 30% acceptance, as resample-move's). Exact for any ``q``: a draw of ``q``
is a draw of ``pi_0``.

Written on the host, not with ``blackjax.adaptive_tempered_smc``: the log density is the start
pipeline's NumPy-batched rollout program (:class:`treeinfer.inference.fast_evaluator.BatchEvaluator`),
one call per sweep for every chain, which BlackJAX's jitted kernels cannot call without a host
callback per particle.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ..errors import ConfigError

__all__ = ["BridgeResult", "tempered_bridge"]

# the reference: a Student-t at the importance draws' weighted moments, std inflated 2x (on the
# data set 90 above the posterior's bulk sat 1-2.4 weighted sd from the draws' weighted mean)
REFERENCE_DF = 5.0
REFERENCE_INFLATE = 2.0
# adaptive tempering: each stage keeps half the chains' effective sample size
STAGE_ESS = 0.5
# random-walk sweeps per stage (each is one batched evaluation of every chain)
STAGE_SWEEPS = 3
MAX_STAGES = 40
TARGET_ACCEPT = 0.3


class BridgeResult(NamedTuple):
    """Result of :func:`tempered_bridge`.

    chains: [N, D] the cloud at the last stage; log_density: [N] log p there (the posterior's, not
    pi_beta's); log_weights: [N] the weights that carry the cloud from ``pi_beta`` to the
    posterior (zeros when ``beta`` reached 1); beta: the last stage's temperature; stages:
    stages run; sweeps: Metropolis sweeps run; evaluations: log-density calls (sweeps plus the
    reference draws'); acceptance: mean random-walk acceptance; log_evidence: log of the
    posterior's normalising constant relative to ``q``'s (the product of the stages' mean
    incremental weights).
    """

    chains: np.ndarray
    log_density: np.ndarray
    log_weights: np.ndarray
    beta: float
    stages: int
    sweeps: int
    acceptance: float
    log_evidence: float

    def describe(self) -> str:
        """One line for the log."""
        return (
            f"tempered bridge: {len(self.chains)} chains, {self.stages} stages "
            f"({self.sweeps} Metropolis sweeps, acceptance {100 * self.acceptance:.0f}%)"
            + ("" if self.beta >= 1.0 else f", stopped at beta {self.beta:.3f}")
        )

    def settings(self) -> dict:
        """JSON-ready record."""
        return {
            "method": "tempered_bridge",
            "chains": int(len(self.chains)),
            "stages": int(self.stages),
            "sweeps": int(self.sweeps),
            "beta": float(self.beta),
            "acceptance": float(self.acceptance),
            "log_evidence": float(self.log_evidence),
        }


def _ess(log_w: np.ndarray) -> float:
    """Effective sample size ``(sum w)^2 / sum w^2`` of unnormalised ``log_w`` (-inf: weight 0)."""
    if not np.isfinite(log_w).any():
        return 0.0
    w = np.exp(log_w - np.max(log_w))
    return float(w.sum() ** 2 / np.sum(w**2))


def _next_beta(beta: float, delta_log: np.ndarray, target: float) -> float:
    """The largest ``beta' <= 1`` whose incremental weights ``(beta' - beta) * delta_log`` keep an
    effective sample size of ``target`` (bisection; ``delta_log = log p - log q``, -inf where the
    simulation failed)."""
    if _ess((1.0 - beta) * delta_log) >= target:
        return 1.0
    lo, hi = 0.0, 1.0 - beta
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        if _ess(mid * delta_log) >= target:
            lo = mid
        else:
            hi = mid
    return beta + max(lo, 1e-6)


def tempered_bridge(
    log_density,
    draws,
    log_weights,
    n_chains: int,
    seed: int = 0,
    inflate: float = REFERENCE_INFLATE,
    df: float = REFERENCE_DF,
    stage_ess: float = STAGE_ESS,
    stage_sweeps: int = STAGE_SWEEPS,
    max_stages: int = MAX_STAGES,
) -> BridgeResult:
    """Tempered SMC from a Student-t at the importance draws' weighted moments to the posterior
    (module docstring).

    Args:
      log_density: ``[M, D] -> [M]`` NumPy log posterior density (``-inf``/NaN where the
        simulation is unstable), called once per sweep with every chain.
      draws, log_weights: ``[M, D]`` importance draws and their log weights (the reference's
        centre and shape; not used as particles).
      n_chains: N particles of the bridge. seed: of the reference draws, the resampling and the
        moves. inflate, df: the reference's std inflation and degrees of freedom.
      stage_ess: the share of N each stage's incremental weights keep. stage_sweeps: Metropolis
        sweeps per stage. max_stages: stop there (``beta < 1``; the returned ``log_weights``
        carry the cloud the rest of the way).
    """
    from .importance import _draw_log_density, systematic_resample, weighted_moments

    draws = np.atleast_2d(np.asarray(draws, float))
    lw = np.asarray(log_weights, float)
    ok = np.isfinite(lw) & np.isfinite(draws).all(axis=1)
    if not ok.any():
        raise ConfigError("tempered_bridge: no importance draw with a finite weight")
    if not (isinstance(n_chains, (int, np.integer)) and n_chains >= 2):
        raise ConfigError(f"n_chains: must be an integer >= 2, got {n_chains!r}")
    if not (0.0 < stage_ess < 1.0) or stage_sweeps < 1 or max_stages < 1:
        raise ConfigError(
            f"tempered_bridge: need 0 < stage_ess < 1, stage_sweeps >= 1 and max_stages >= 1, "
            f"got {stage_ess}, {stage_sweeps}, {max_stages}"
        )
    mean, cov = weighted_moments(draws[ok], lw[ok] - np.max(lw[ok]))
    cov = float(inflate) ** 2 * cov
    rng = np.random.default_rng([int(seed), 7919])
    n, d = int(n_chains), draws.shape[1]
    x, lq = _draw_log_density(rng, mean, cov, n, df)
    lp = np.asarray(log_density(x), float)
    lp = np.where(np.isnan(lp), -np.inf, lp)
    beta, stages, sweeps, log_z = 0.0, 0, 0, 0.0
    log_s = math.log(2.38 / math.sqrt(d))
    rates: list[float] = []
    while beta < 1.0 and stages < max_stages:
        delta = np.where(np.isfinite(lp), lp - lq, -np.inf)
        new = _next_beta(beta, delta, stage_ess * n)
        inc = np.where(np.isfinite(delta), (new - beta) * delta, -np.inf)
        m = np.max(inc)
        log_z += float(m + np.log(np.mean(np.exp(inc - m))))
        beta, stages = new, stages + 1
        idx = systematic_resample(rng, inc, n)
        x, lp, lq = x[idx], lp[idx], lq[idx]
        for _ in range(stage_sweeps):
            c = np.atleast_2d(np.cov(x.T))
            c = c + np.diag(1e-6 * np.maximum(np.diag(c), 1e-12))
            try:
                chol = np.linalg.cholesky(c)
            except np.linalg.LinAlgError:
                chol = np.diag(np.sqrt(np.maximum(np.diag(c), 1e-12)))
            xp = x + math.exp(log_s) * rng.standard_normal((n, d)) @ chol.T
            lpp = np.asarray(log_density(xp), float)
            lpp = np.where(np.isnan(lpp), -np.inf, lpp)
            lqp = _draw_log_density(None, mean, cov, 0, df, xp)[1]
            with np.errstate(invalid="ignore"):
                ratio = (1.0 - beta) * (lqp - lq) + beta * (lpp - lp)
            ratio = np.where(np.isfinite(lpp), ratio, -np.inf)
            acc = np.log(rng.random(n)) < ratio
            x[acc], lp[acc], lq[acc] = xp[acc], lpp[acc], lqp[acc]
            rate = float(acc.mean())
            rates.append(rate)
            log_s += 1.5 * (rate - TARGET_ACCEPT)
            sweeps += 1
    rest = np.where(np.isfinite(lp), (1.0 - beta) * (lp - lq), -np.inf)
    return BridgeResult(
        x, lp, rest, float(beta), stages, sweeps,
        float(np.mean(rates)) if rates else math.nan, log_z,
    )  # fmt: skip
