"""SBC statistics (sampler-agnostic, numpy/scipy): ranks, fractional ranks, coverage of central
intervals, uniformity tests, the result record, and exact draws from the smoothed box prior.

Coverage from ranks: with the fractional rank ``u = (rank + V) / (L + 1)``, ``V ~ U(0, 1)``
(exactly uniform on (0, 1) under calibration, ties included), the truth lies inside the central
``a`` interval of the posterior draws iff ``|u - 1/2| <= a / 2``. So the expected coverage is
exactly ``a`` for a calibrated posterior with any L, without quantile interpolation.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.stats

from ..errors import ConfigError

COVERAGE_LEVELS = (0.5, 0.8, 0.9, 0.95)
ALPHA = 0.01  # family-wise level of the uniformity test (Bonferroni over parameters)


def sbc_ranks(truth, draws, rng: np.random.Generator | None = None) -> np.ndarray:
    """Rank of every true parameter among its posterior draws.

    Args:
      truth: ``[N, D]`` true parameters of N data sets (any units, same as ``draws``).
      draws: ``[N, L, D]`` L posterior draws per data set.
      rng: breaks ties (a draw equal to the truth) uniformly at random; None: seed 0.

    Returns ``[N, D]`` integers in ``0..L``: ``#{draws < truth} + Uniform{0..#{draws == truth}}``.
    """
    truth = np.asarray(truth, float)
    draws = np.asarray(draws, float)
    if (
        truth.ndim != 2
        or draws.ndim != 3
        or draws.shape[0] != truth.shape[0]
        or (draws.shape[2] != truth.shape[1])
    ):
        raise ConfigError(
            f"sbc_ranks: expected truth [N, D] and draws [N, L, D], got {truth.shape}, "
            f"{draws.shape}"
        )
    if not (np.all(np.isfinite(truth)) and np.all(np.isfinite(draws))):
        raise ConfigError("sbc_ranks: truth and draws must be finite")
    rng = np.random.default_rng(0) if rng is None else rng
    less = np.sum(draws < truth[:, None, :], axis=1)
    ties = np.sum(draws == truth[:, None, :], axis=1)
    return less + rng.integers(0, ties + 1)


def fractional_ranks(ranks, n_draws: int, rng: np.random.Generator | None = None) -> np.ndarray:
    """``u = (rank + V) / (L + 1)``, ``V ~ U(0, 1)``: exactly Uniform(0, 1) under calibration
    (a discrete uniform rank on 0..L spread over its cell). ``ranks [N, D]`` -> ``[N, D]``."""
    ranks = np.asarray(ranks)
    if np.any(ranks < 0) or np.any(ranks > n_draws):
        raise ConfigError(f"ranks: must lie in 0..{n_draws}")
    rng = np.random.default_rng(1) if rng is None else rng
    return (ranks + rng.uniform(size=ranks.shape)) / (n_draws + 1)


def rank_coverage(u, levels: Sequence[float] = COVERAGE_LEVELS) -> np.ndarray:
    """Observed coverage of central posterior intervals: ``[K, D]``, the share of data sets whose
    fractional rank ``u [N, D]`` lies within ``level / 2`` of 1/2 (truth inside the central
    ``level`` interval of the draws). Expected value: ``level`` exactly when calibrated."""
    u = np.asarray(u, float)
    return np.stack([np.mean(np.abs(u - 0.5) <= a / 2.0, axis=0) for a in levels])


def binomial_band(n: int, p: float, level: float = 0.99) -> tuple[float, float]:
    """Central ``level`` interval of a Binomial(n, p) count (scipy): the band a histogram bin
    with expected share ``p`` (or a coverage count) stays in with probability ~``level``."""
    lo = scipy.stats.binom.ppf((1 - level) / 2, n, p)
    hi = scipy.stats.binom.ppf(1 - (1 - level) / 2, n, p)
    return float(lo), float(hi)


def default_bins(n_datasets: int, n_draws: int) -> int:
    """Histogram bins: at least ~5 expected per bin (chi-square validity), at most 20 and at
    most L + 1."""
    return int(max(2, min(20, n_draws + 1, n_datasets // 5)))


def rank_uniformity(u, labels: Sequence[str], n_bins: int, alpha: float = ALPHA) -> dict:
    """Uniformity tests of the fractional ranks of each parameter.

    Tests (both exact under calibration, since ``u`` is continuous uniform): Pearson chi-square
    on ``n_bins`` equal bins (``scipy.stats.chisquare``, n_bins - 1 dof) and Kolmogorov-Smirnov
    against Uniform(0, 1) (``scipy.stats.kstest``). A parameter passes when both p-values exceed
    ``alpha / (2 D)`` (Bonferroni over D parameters and the two tests); the study passes at the
    family-wise level ``alpha`` when every parameter does.

    Returns ``{"alpha", "per_parameter_threshold", "n_bins", "parameters": {label: {...}},
    "pass"}``.
    """
    u = np.asarray(u, float)
    n, d = u.shape
    thr = alpha / (2 * d)
    out = {}
    for j, lab in enumerate(labels):
        counts = np.histogram(u[:, j], bins=n_bins, range=(0.0, 1.0))[0]
        chi = scipy.stats.chisquare(counts)
        ks = scipy.stats.kstest(u[:, j], "uniform")
        ok = bool(chi.pvalue > thr and ks.pvalue > thr)
        out[lab] = {
            "chi2": float(chi.statistic),
            "p_chi2": float(chi.pvalue),
            "ks": float(ks.statistic),
            "p_ks": float(ks.pvalue),
            "counts": counts.tolist(),
            "pass": ok,
        }
    return {
        "alpha": alpha,
        "per_parameter_threshold": thr,
        "correction": "Bonferroni over parameters and the two tests (chi-square, KS)",
        "n_bins": int(n_bins),
        "n_datasets": int(n),
        "parameters": out,
        "pass": all(v["pass"] for v in out.values()),
    }


@dataclass
class SBCResult:
    """Outcome of an SBC study.

    truth: ``[N, D]`` true parameters (theta units: log gains, log sigma_x).
    draws: ``[N, L, D]`` posterior draws (same units). ranks: ``[N, D]`` in 0..L.
    u: ``[N, D]`` fractional ranks. labels: D column names.
    coverage: ``[K, D]`` observed coverage at ``levels``. uniformity: :func:`rank_uniformity`.
    info: sampler diagnostics and timings (JSON-ready).
    """

    truth: np.ndarray
    draws: np.ndarray
    ranks: np.ndarray
    u: np.ndarray
    labels: tuple[str, ...]
    levels: tuple[float, ...]
    coverage: np.ndarray
    uniformity: dict
    info: dict = field(default_factory=dict)

    @property
    def n_draws(self) -> int:
        return int(self.draws.shape[1])


def summarize_sbc(
    truth,
    draws,
    labels: Sequence[str],
    levels: Sequence[float] = COVERAGE_LEVELS,
    n_bins: int | None = None,
    alpha: float = ALPHA,
    seed: int = 0,
    info: dict | None = None,
) -> SBCResult:
    """Ranks, fractional ranks, coverage and uniformity tests of ``draws [N, L, D]`` against
    ``truth [N, D]`` (ties and the fractional spread use ``seed``)."""
    labels = tuple(labels)
    truth = np.asarray(truth, float)
    draws = np.asarray(draws, float)
    if len(labels) != truth.shape[-1]:
        raise ConfigError(f"labels: expected {truth.shape[-1]} names, got {len(labels)}")
    for a in levels:
        if not 0.0 < a < 1.0:
            raise ConfigError(f"coverage levels: must lie in (0, 1), got {a}")
    rng = np.random.default_rng(seed)
    ranks = sbc_ranks(truth, draws, rng)
    u = fractional_ranks(ranks, draws.shape[1], rng)
    n_bins = default_bins(truth.shape[0], draws.shape[1]) if n_bins is None else int(n_bins)
    return SBCResult(
        truth,
        draws,
        ranks,
        u,
        labels,
        tuple(float(a) for a in levels),
        rank_coverage(u, levels),
        rank_uniformity(u, labels, n_bins, alpha),
        dict(info or {}),
    )


def coverage_table(result: SBCResult, band_level: float = 0.99) -> list[dict]:
    """One row per (level, parameter): expected, observed and the binomial band of the
    observed share for N data sets."""
    n = result.truth.shape[0]
    rows = []
    for k, a in enumerate(result.levels):
        lo, hi = binomial_band(n, a, band_level)
        for j, lab in enumerate(result.labels):
            rows.append(
                {
                    "level": a,
                    "parameter": lab,
                    "observed": float(result.coverage[k, j]),
                    "band_lower": lo / n,
                    "band_upper": hi / n,
                    "inside_band": bool(lo / n <= result.coverage[k, j] <= hi / n),
                }
            )
    return rows


def result_json(result: SBCResult, config: dict | None = None) -> dict:
    """JSON-ready summary: config, per-parameter p-values and pass, coverage table, info."""
    return {
        "method": "simulation-based calibration (Talts et al. 2018)",
        "config": config or {},
        "n_datasets": int(result.truth.shape[0]),
        "n_draws": result.n_draws,
        "labels": list(result.labels),
        "uniformity": result.uniformity,
        "coverage": coverage_table(result),
        "coverage_definition": "truth inside the central interval of the posterior draws, from "
        "fractional ranks u = (rank + V) / (L + 1): |u - 0.5| <= level / 2",
        "info": result.info,
    }


def sample_smoothed_box(rng: np.random.Generator, lower, upper, sigma, n: int) -> np.ndarray:
    """``[n, D]`` exact draws from :func:`treeinfer.model.priors.smoothed_box` (normalised).

    Per coordinate the density is flat on ``[lower, upper]`` with half-normal tails of std
    ``sigma`` outside, i.e. the mixture: box with probability ``w / (w + sqrt(2 pi) sigma)``
    (``w = upper - lower``), otherwise a half-normal beyond either edge with equal chance.
    (Written here because no library ships this mixture; the test checks it against the
    density by a KS test on its CDF.)"""
    lo, hi = np.asarray(lower, float), np.asarray(upper, float)
    s = np.broadcast_to(np.asarray(sigma, float), lo.shape)
    w = hi - lo
    p_box = w / (w + math.sqrt(2 * math.pi) * s)
    d = lo.size
    in_box = rng.uniform(size=(n, d)) < p_box
    upper_tail = rng.uniform(size=(n, d)) < 0.5
    h = np.abs(rng.normal(size=(n, d))) * s
    tail = np.where(upper_tail, hi + h, lo - h)
    return np.where(in_box, lo + rng.uniform(size=(n, d)) * w, tail)
