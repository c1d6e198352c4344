"""Calibration of an amortised posterior on held-out simulated data sets: expected coverage of
its central intervals and simulation-based calibration (SBC) ranks, per parameter.

Held-out data sets are drawn exactly as the training sets (the prior, the noise model, the
layout's pulls) with another seed; for each, ``n_draws`` draws of the flow give the rank of the
truth among them (SBC: uniform on ``0..n_draws`` for a calibrated posterior) and whether the
truth lies in the central ``level`` interval (expected coverage: the share of data sets should
be ``level``). No simulator is run at the posterior: this measures the flow alone, the answer
``infer --amortised`` gives before its check."""

from __future__ import annotations

import numpy as np

DEFAULT_LEVELS = (0.5, 0.8, 0.9, 0.95)


def null_max_gap(n_sets: int, n_columns: int, levels=DEFAULT_LEVELS, reps: int = 2000) -> dict:
    """The largest |coverage - nominal| over the columns and levels that a perfectly calibrated
    posterior shows on ``n_sets`` data sets (independent uniform ranks per column: the columns'
    correlation only lowers it): its median and 95th percentile over ``reps`` repetitions. A
    measured gap below the 95th percentile is not evidence of miscalibration."""
    rng = np.random.default_rng(0)
    gaps = np.zeros(reps)
    for r in range(reps):
        u = rng.uniform(size=(n_sets, n_columns))
        gaps[r] = max(
            float(np.abs((np.abs(u - 0.5) <= lv / 2).mean(axis=0) - lv).max()) for lv in levels
        )
    return {"median": float(np.median(gaps)), "p95": float(np.quantile(gaps, 0.95))}


def expected_coverage(
    am,
    tree,
    n_sets: int = 200,
    n_draws: int = 256,
    seed: int = 1,
    levels=DEFAULT_LEVELS,
    log=lambda m: None,
) -> dict:
    """``{"coverage": {label: {level: share}}, "ranks": {label: [n_sets]}, "chi2_p": {label:
    p}, "mean_log_q_truth", "null_max_gap": {"median", "p95"}, "n_sets", "n_draws",
    "latency_ms"}`` of ``am`` on ``n_sets`` held-out data sets of
    ``tree`` (simulated with ``seed``: use one the model was not trained with). ``chi2_p``: the
    p-value of a chi-square test of the ranks' uniformity over 10 bins (scipy)."""
    import time

    import jax
    from scipy import stats

    from . import network
    from .simulations import simulate_training_set

    cfg = am.config
    held, _ = simulate_training_set(
        tree, cfg.layout, cfg.train, n=n_sets, seed=seed, scales=tuple(am.meta["scales"]), log=log
    )
    draw = network.sampler(am.network_model(), int(n_draws))
    labels = am.labels
    ranks = np.zeros((len(held.theta), len(labels)), int)
    log_q_truth = np.zeros(len(held.theta))
    inside = {lv: np.zeros((len(held.theta), len(labels)), bool) for lv in levels}
    times = []
    for i, (truth, feats) in enumerate(zip(held.theta, held.feats)):
        t0 = time.perf_counter()
        z, _ = draw(jax.random.key(seed * 100003 + i), feats)
        z = np.asarray(z)
        times.append(time.perf_counter() - t0)
        theta = am.from_z(z)
        ranks[i] = (theta < truth[None]).sum(axis=0)
        log_q_truth[i] = am.log_q(np.asarray(truth, float)[None], feats)[0]
        for lv in levels:
            lo, hi = np.quantile(theta, [(1 - lv) / 2, (1 + lv) / 2], axis=0)
            inside[lv][i] = (truth >= lo) & (truth <= hi)
    coverage = {
        lab: {str(lv): float(inside[lv][:, j].mean()) for lv in levels}
        for j, lab in enumerate(labels)
    }
    chi2 = {}
    for j, lab in enumerate(labels):
        counts = np.histogram(ranks[:, j], bins=10, range=(0, n_draws + 1))[0]
        chi2[lab] = float(stats.chisquare(counts).pvalue)
    return {
        "coverage": coverage,
        "ranks": {lab: ranks[:, j].tolist() for j, lab in enumerate(labels)},
        "chi2_p": chi2,
        # the held-out sets' mean log q(truth | data) in theta units: a proper score, higher for
        # a sharper calibrated posterior; compare models on the same held-out sets only
        "mean_log_q_truth": float(np.mean(log_q_truth)),
        "null_max_gap": null_max_gap(len(held.theta), len(labels), levels),
        "n_sets": int(len(held.theta)),
        "n_unstable": int(held.n_unstable),
        "n_draws": int(n_draws),
        # the first call compiles; the rest is the posterior's latency on this machine
        "latency_ms": float(1e3 * np.median(times[1:] if len(times) > 1 else times)),
    }
