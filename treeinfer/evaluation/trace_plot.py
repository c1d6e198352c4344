"""The sampler trace: log density and every parameter over iterations, drawn so that a plateau
(convergence) or a drift shows; conventions as in :mod:`treeinfer.evaluation.plots`."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..errors import ConfigError
from ._plot_common import (
    BAND_COLOR,
    GT_COLOR,
    LOG_MIN_DECADES,
    MEAN_COLOR,
    SAMPLE_COLOR,
    _new_axes,
    _np,
    plain_log_ticks,
    with_unit,
    wrap_title,
)

ZOOM_RATIO = 5.0  # zoom the log density on its last half when the whole range is this much wider


def _band(x: np.ndarray, quantiles) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-row median and quantiles of ``x [n, P]`` over its finite entries (NaN rows: none)."""
    n = x.shape[0]
    med, qlo, qhi = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
    ok = np.any(np.isfinite(x), axis=1)
    if ok.any():
        med[ok] = np.nanmedian(x[ok], axis=1)
        qlo[ok], qhi[ok] = np.nanquantile(x[ok], quantiles, axis=1)
    return med, qlo, qhi


def _plateau_limits(qlo: np.ndarray, qhi: np.ndarray) -> tuple[float, float] | None:
    """y limits around the last half of the band when the early iterations (often orders of
    magnitude below) would flatten it to a line; None to keep the full range."""
    n = len(qlo)
    late = slice(n // 2, n)
    if n < 4 or not np.any(np.isfinite(qlo[late])):
        return None
    a, b = np.nanmin(qlo[late]), np.nanmax(qhi[late])
    full = np.nanmax(qhi) - np.nanmin(qlo)
    span = max(b - a, 1e-12 * max(abs(a), abs(b), 1.0))
    if not full > ZOOM_RATIO * span:
        return None
    return a - 0.5 * span, b + 0.5 * span


def plot_trace(
    log_density_trace,
    bandwidth=None,
    *,
    iterations=None,
    quantiles=(0.05, 0.95),
    title: str | None = None,
    params=None,
    labels: Sequence[str] | None = None,
    units: Sequence[str] | None = None,
    log_params: bool | Sequence[bool] | None = None,
    warmup: float | None = None,
    max_lines: int = 8,
):
    """Log density over iterations and, with ``params``, each parameter: the particles' (or
    chains') median and a quantile band, with a few single particles drawn thin.

    Args:
      log_density_trace: ``[n, P]`` log posterior density of each particle at each recorded
        iteration. Non-finite values (unstable simulations) are left out of the statistics;
        the share of them is drawn if any occur. When the first iterations lie far below the
        rest, the panel zooms on the last half (the plateau) and says so.
      bandwidth: optional ``[n]`` SVGD kernel bandwidth, drawn in a panel of its own (log).
      iterations: optional ``[n]`` iteration numbers (default ``0..n-1``).
      quantiles: lower/upper particle quantiles of the bands.
      params: optional ``[n, P, D]`` parameter values (natural units) at the same iterations,
        one panel each. labels, units: ``D`` names and units for their y labels.
      log_params: log y axis per parameter (default: where every value is positive).
      warmup: iteration where MCMC warm-up ends (shaded before it).
      max_lines: single particles / chains drawn per parameter panel.

    Returns:
      ``(fig, axes)`` with ``axes`` ``[1 + D (+1)]`` (shared x): log density, parameters,
      bandwidth.
    """
    ld = _np(log_density_trace, "log_density_trace", 2)
    n = ld.shape[0]
    it = np.arange(n) if iterations is None else _np(iterations, "iterations", 1)
    if it.shape != (n,):
        raise ConfigError(f"iterations: expected {n} values, got shape {it.shape}")
    bw = None if bandwidth is None else _np(bandwidth, "bandwidth", 1)
    if bw is not None and bw.shape != (n,):
        raise ConfigError(
            f"bandwidth: expected {n} values to match the trace, got shape {bw.shape}"
        )
    pr = None if params is None else _np(params, "params", 3)
    D = 0 if pr is None else pr.shape[2]
    if pr is not None and pr.shape[:2] != ld.shape:
        raise ConfigError(f"params: expected [{n}, {ld.shape[1]}, D], got shape {pr.shape}")
    labels = [f"theta[{j}]" for j in range(D)] if labels is None else list(labels)
    if len(labels) != D:
        raise ConfigError(f"labels: expected {D} names, got {len(labels)}")
    if units is not None and len(units) != D:
        raise ConfigError(f"units: expected {D} units, got {len(units)}")
    if log_params is None:
        logs = [
            pr is not None and bool(np.all(pr[:, :, j][np.isfinite(pr[:, :, j])] > 0))
            for j in range(D)
        ]
    else:
        logs = list(np.broadcast_to(np.asarray(log_params, bool), (D,)))

    rows = 1 + D + (bw is not None)
    fig, axs = _new_axes(rows, 1, figsize=(6.4, 2.9 + 1.7 * (rows - 1)), sharex=True)
    axes = axs[:, 0]
    finite = np.where(np.isfinite(ld), ld, np.nan)
    ok = np.any(np.isfinite(finite), axis=1)
    mean = np.full(n, np.nan)
    mean[ok] = np.nanmean(finite[ok], axis=1)
    _, qlo, qhi = _band(finite, quantiles)
    ax = axes[0]
    band_label = f"{quantiles[0]:.0%}-{quantiles[1]:.0%} of particles"
    ax.fill_between(it, qlo, qhi, color=BAND_COLOR, alpha=0.5, lw=0, label=band_label)
    ax.plot(it, mean, color=MEAN_COLOR, lw=1.2, label="particle mean")
    ax.set_ylabel("log density")
    zoom = _plateau_limits(qlo, qhi)
    if zoom is not None:
        ax.set_ylim(*zoom)
        ax.text(
            0.01,
            0.03,
            f"y zoomed on the last half; earlier values down to {np.nanmin(qlo):.3g}",
            transform=ax.transAxes,
            fontsize="x-small",
            color="0.3",
        )
    bad = 1.0 - np.isfinite(ld).mean(axis=1)
    if np.any(bad > 0):
        ax_r = ax.twinx()
        ax_r.plot(it, 100 * bad, color=GT_COLOR, lw=0.8, ls=":", label="% non-finite")
        ax_r.set_ylabel("% non-finite", color=GT_COLOR)
    ax.legend(loc="lower right", frameon=False, fontsize="small")
    for j in range(D):
        a = axes[1 + j]
        x = np.where(np.isfinite(pr[:, :, j]), pr[:, :, j], np.nan)
        med, lo, hi = _band(x, quantiles)
        a.fill_between(it, lo, hi, color=BAND_COLOR, alpha=0.5, lw=0)
        step = max(1, x.shape[1] // max_lines)
        for p in range(0, x.shape[1], step)[:max_lines]:
            a.plot(it, x[:, p], color=SAMPLE_COLOR, lw=0.5, alpha=0.4)
        a.plot(it, med, color=MEAN_COLOR, lw=1.2)
        span = np.log10(np.nanmax(hi) / np.nanmin(lo)) if logs[j] and np.any(lo > 0) else 0.0
        if logs[j] and span >= LOG_MIN_DECADES:  # narrower: linear ticks read better
            a.set_yscale("log")
            plain_log_ticks(a.yaxis)
        a.set_ylabel(with_unit(labels[j], None if units is None else units[j]), fontsize="small")
    if D:
        axes[1].plot([], [], color=SAMPLE_COLOR, lw=0.5, label="single particles")
        axes[1].plot([], [], color=MEAN_COLOR, lw=1.2, label="median")
        axes[1].legend(loc="best", frameon=False, fontsize="x-small")
    if warmup is not None:
        for a in axes[: 1 + D]:
            a.axvspan(it[0], warmup, color="0.9", zorder=0, lw=0)
        axes[0].text(0.01, 0.9, "warm-up (shaded)", transform=axes[0].transAxes, fontsize="x-small")
    if bw is not None:
        axes[-1].plot(it, bw, color=SAMPLE_COLOR, lw=1.2)
        axes[-1].set_yscale("log")
        plain_log_ticks(axes[-1].yaxis)
        axes[-1].set_ylabel("kernel bandwidth", fontsize="small")
    axes[-1].set_xlabel("iteration")
    if title:
        axes[0].set_title(wrap_title(title, 6.4))
    return fig, axes
