"""Figures of a posterior on plain arrays: the pair plot (KDE marginals, 68%/95% highest-density
contours), metric bars and the sampler trace; conventions as in :mod:`treeinfer.plots`, which
re-exports every name here."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from matplotlib.axes import Axes

from ._plot_common import (
    BAND_COLOR,
    GT_COLOR,
    MEAN_COLOR,
    SAMPLE_COLOR,
    SET_COLORS,
    _new_axes,
    _np,
)
from .errors import ConfigError

# --------------------------------------------------------------------------- pair plot


def _kde_curve(x: np.ndarray, grid: np.ndarray) -> np.ndarray | None:
    """1-D Scott's-rule Gaussian KDE on ``grid`` (same rule as treeinfer.metrics).

    None if degenerate."""
    n, sd = x.size, x.std(ddof=1) if x.size > 1 else 0.0
    if not sd > 0:
        return None
    h = sd * n ** (-0.2)
    z = (grid[:, None] - x[None, :]) / h
    return np.exp(-0.5 * z**2).sum(1) / (n * h * np.sqrt(2 * np.pi))


def _kde_2d(x: np.ndarray, y: np.ndarray, gx: np.ndarray, gy: np.ndarray) -> np.ndarray | None:
    """2-D Scott's-rule Gaussian KDE (full covariance) on the grid; None if singular."""
    data = np.vstack([x, y])
    n = data.shape[1]
    cov = np.cov(data) * n ** (-2.0 / 6.0)
    if n < 3 or not np.all(np.isfinite(cov)) or np.linalg.det(cov) <= 1e-12 * np.prod(np.diag(cov)):
        return None
    inv = np.linalg.inv(cov)
    X, Y = np.meshgrid(gx, gy)
    d = np.stack([X.ravel(), Y.ravel()])[:, :, None] - data[:, None, :]
    q = np.einsum("iam,ij,jam->am", d, inv, d)
    dens = np.exp(-0.5 * q).sum(1) / (n * 2 * np.pi * np.sqrt(np.linalg.det(cov)))
    return dens.reshape(X.shape)


def _hdr_levels(dens: np.ndarray, masses=(0.95, 0.68)) -> list[float]:
    """Density thresholds enclosing the given probability masses on a grid."""
    flat = np.sort(dens.ravel())[::-1]
    cum = np.cumsum(flat) / flat.sum()
    lv = sorted({float(flat[min(np.searchsorted(cum, m), flat.size - 1)]) for m in masses})
    return lv


def pair_plot(
    samples,
    labels: Sequence[str] | None = None,
    truth=None,
    *,
    kind: str = "scatter",
    bins: int = 30,
    max_points: int = 2000,
    figsize=None,
    title: str | None = None,
):
    """Corner plot of posterior samples, paper Fig. 4 style.

    Args:
      samples: ``[P, D]`` particles, or a mapping ``{name: [P_k, D]}`` to
        overlay several sets (e.g. ``{"NNSVGD": a, "SVGD": b}``) with a legend.
      labels: ``D`` parameter names, e.g. ``["Kp[b1]", "Kd[b1]", ...]``.
      truth: optional ``[D]`` true values: red lines on the diagonal, red dots below.
      kind: ``"scatter"`` or ``"kde"`` (68%/95% highest-density contours of a
        2-D Scott's-rule KDE; falls back to scatter for a collapsed set).
      bins: histogram bins on the diagonal (a 1-D KDE curve is drawn over them).
      max_points: at most this many points per set in each scatter.

    Returns:
      ``(fig, axes)``, ``axes`` is ``[D, D]``; panels above the diagonal are hidden.
    """
    if kind not in ("scatter", "kde"):
        raise ConfigError(f"kind: expected 'scatter' or 'kde', got {kind!r}")
    sets = dict(samples) if isinstance(samples, Mapping) else {"samples": samples}
    sets = {k: _np(v, f"samples[{k!r}]", 2) for k, v in sets.items()}
    D = next(iter(sets.values())).shape[1]
    for k, v in sets.items():
        if v.shape[1] != D:
            raise ConfigError(f"samples[{k!r}]: expected {D} columns, got {v.shape[1]}")
    labels = list(labels) if labels is not None else [f"theta[{i}]" for i in range(D)]
    if len(labels) != D:
        raise ConfigError(f"labels: expected {D} names, got {len(labels)}")
    tr = None if truth is None else _np(truth, "truth", 1)
    if tr is not None and tr.shape != (D,):
        raise ConfigError(f"truth: expected shape ({D},), got {tr.shape}")

    finite = {k: v[np.all(np.isfinite(v), axis=1)] for k, v in sets.items()}
    allv = np.concatenate(list(finite.values()))
    lo, hi = allv.min(0), allv.max(0)
    if tr is not None:  # NaN entries: no true value (e.g. a noise column), nothing marked
        lo, hi = np.fmin(lo, tr), np.fmax(hi, tr)
    pad = np.where(hi > lo, 0.05 * (hi - lo), np.maximum(np.abs(lo) * 0.05, 1e-3))
    lo, hi = lo - pad, hi + pad

    size = figsize or (max(4.0, 2.0 * D), max(4.0, 2.0 * D))
    fig, axes = _new_axes(D, D, figsize=size)
    multi = len(finite) > 1
    for s_idx, (name, v) in enumerate(finite.items()):
        color = SET_COLORS[s_idx % len(SET_COLORS)]
        pts = v[:: max(1, len(v) // max_points)]
        for i in range(D):
            ax = axes[i, i]
            ax.hist(
                v[:, i],
                bins=np.linspace(lo[i], hi[i], bins + 1),
                density=True,
                histtype="stepfilled",
                color=color,
                alpha=0.3,
                label=name if multi else None,
            )
            g = np.linspace(lo[i], hi[i], 200)
            curve = _kde_curve(v[:, i], g)
            if curve is not None:
                ax.plot(g, curve, color=color, lw=1.2)
            for j in range(i):
                ax2 = axes[i, j]
                dens = None
                if kind == "kde":
                    gx, gy = np.linspace(lo[j], hi[j], 60), np.linspace(lo[i], hi[i], 60)
                    dens = _kde_2d(v[:, j], v[:, i], gx, gy)
                if dens is not None:
                    ax2.contour(
                        gx, gy, dens, levels=_hdr_levels(dens), colors=color, linewidths=1.0
                    )
                else:
                    ax2.scatter(pts[:, j], pts[:, i], s=4, color=color, alpha=0.4, lw=0)
    for i in range(D):
        for j in range(D):
            ax = axes[i, j]
            if j > i:
                ax.set_visible(False)
                continue
            ax.set_xlim(lo[j], hi[j])
            if j < i:
                ax.set_ylim(lo[i], hi[i])
                if tr is not None and np.isfinite(tr[i]) and np.isfinite(tr[j]):
                    ax.plot(tr[j], tr[i], "o", color=GT_COLOR, ms=5, zorder=5)
            elif tr is not None and np.isfinite(tr[i]):
                ax.axvline(tr[i], color=GT_COLOR, lw=1.2, zorder=5)
            if i == D - 1:
                ax.set_xlabel(labels[j])
            else:
                ax.tick_params(labelbottom=False)
            if j == 0 and i > 0:
                ax.set_ylabel(labels[i])
            elif j > 0 or i == 0:
                ax.tick_params(labelleft=False)
            if i == j:
                ax.set_yticks([])
    if multi or tr is not None:
        handles, names = axes[0, 0].get_legend_handles_labels()
        if tr is not None:
            from matplotlib.lines import Line2D

            handles.append(Line2D([], [], color=GT_COLOR, marker="o", lw=1.2))
            names.append("ground truth")
        fig.legend(handles, names, loc="upper right", frameon=False)
    if title:
        fig.suptitle(title)
    return fig, axes


# --------------------------------------------------------------------------- bars, trace


def metric_bars(
    names: Sequence[str],
    values: Mapping[str, Sequence[float]],
    *,
    ax: Axes | None = None,
    separate: bool | None = None,
    ylabel: str | None = None,
    title: str | None = None,
    fmt: str = "{:.3g}",
):
    """Grouped bar chart of metrics per condition (paper Fig. 5 inset).

    Args:
      names: ``K`` condition names on the x axis (e.g. noise levels, samplers).
      values: ``{metric_name: K values}``, e.g. ``{"CI width [m]": [...], "% GT outside": [...]}``.
      separate: one panel per metric instead of one grouped panel. ``None``
        (default) decides: separate panels when the metrics' largest values
        differ more than 5-fold (CI width in metres next to % outside would
        otherwise flatten the widths to nothing), grouped otherwise.
      fmt: format of the value printed over each bar.

    Returns:
      ``(fig, ax)`` for one grouped panel, ``(fig, axes [M])`` for separate panels.
    """
    names = list(names)
    vals = {k: np.asarray(v, dtype=float) for k, v in values.items()}
    for k, v in vals.items():
        if v.shape != (len(names),):
            raise ConfigError(
                f"values[{k!r}]: expected {len(names)} values (one per condition), got {v.shape}"
            )
    x = np.arange(len(names))
    if separate is None:
        peaks = [np.nanmax(np.abs(v)) for v in vals.values() if np.any(np.isfinite(v))]
        separate = ax is None and len(peaks) > 1 and max(peaks) > 5 * max(min(peaks), 1e-300)
    if separate:
        if ax is not None:
            raise ConfigError("metric_bars: ax= cannot be combined with separate=True")
        fig, axs = _new_axes(1, len(vals), figsize=(3.2 * len(vals), 3.0))
        for c, (ax_, (k, v)) in enumerate(zip(axs[0], vals.items())):
            bars = ax_.bar(x, v, color=SET_COLORS[c % len(SET_COLORS)])
            ax_.bar_label(bars, labels=[fmt.format(b) for b in v], fontsize="small")
            ax_.set_xticks(x, names)
            ax_.set_title(k)
            ax_.margins(y=0.15)
        if title:
            fig.suptitle(title)
        return fig, axs[0]
    if ax is None:
        fig, axs = _new_axes(figsize=(max(4.0, 0.5 * len(names) * max(1, len(vals)) + 2.0), 3.0))
        ax = axs[0, 0]
    fig = ax.figure
    width = 0.8 / max(1, len(vals))
    for c, (k, v) in enumerate(vals.items()):
        bars = ax.bar(
            x + (c - (len(vals) - 1) / 2) * width,
            v,
            width,
            label=k,
            color=SET_COLORS[c % len(SET_COLORS)],
        )
        ax.bar_label(bars, labels=[fmt.format(b) for b in v], fontsize="small")
    ax.set_xticks(x, names)
    if ylabel:
        ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    ax.legend(frameon=False, fontsize="small")
    ax.margins(y=0.15)
    return fig, ax


def plot_trace(
    log_density_trace,
    bandwidth=None,
    *,
    iterations=None,
    quantiles=(0.05, 0.95),
    title: str | None = None,
):
    """Log-density over iterations: particle mean and a quantile band; optional bandwidth panel.

    Args:
      log_density_trace: ``[n, P]`` log posterior density of each particle at
        each recorded iteration. Non-finite values (unstable simulations) are
        left out of the statistics; the share of them is drawn if any occur.
      bandwidth: optional ``[n]`` SVGD kernel bandwidth, drawn in a second
        panel below (log scale).
      iterations: optional ``[n]`` iteration numbers (default ``0..n-1``).
      quantiles: lower/upper particle quantiles of the band.

    Returns:
      ``(fig, axes)`` with ``axes`` ``[1]`` or ``[2]`` (shared x).
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
    fig, axs = _new_axes(
        2 if bw is not None else 1, 1, figsize=(6.0, 4.5 if bw is not None else 3.0), sharex=True
    )
    axes = axs[:, 0]
    finite = np.where(np.isfinite(ld), ld, np.nan)
    ok = np.any(np.isfinite(finite), axis=1)
    mean = np.full(n, np.nan)
    qlo, qhi = np.full(n, np.nan), np.full(n, np.nan)
    mean[ok] = np.nanmean(finite[ok], axis=1)
    qlo[ok], qhi[ok] = np.nanquantile(finite[ok], quantiles, axis=1)
    ax = axes[0]
    ax.fill_between(
        it,
        qlo,
        qhi,
        color=BAND_COLOR,
        alpha=0.5,
        lw=0,
        label=f"{quantiles[0]:.0%}-{quantiles[1]:.0%} of particles",
    )
    ax.plot(it, mean, color=MEAN_COLOR, lw=1.2, label="particle mean")
    ax.set_ylabel("log density")
    bad = 1.0 - np.isfinite(ld).mean(axis=1)
    if np.any(bad > 0):
        ax_r = ax.twinx()
        ax_r.plot(it, 100 * bad, color=GT_COLOR, lw=0.8, ls=":", label="% non-finite")
        ax_r.set_ylabel("% non-finite", color=GT_COLOR)
    ax.legend(loc="lower right", frameon=False, fontsize="small")
    if bw is not None:
        axes[1].plot(it, bw, color=SAMPLE_COLOR, lw=1.2)
        axes[1].set_yscale("log")
        axes[1].set_ylabel("kernel bandwidth")
    axes[-1].set_xlabel("iteration")
    if title:
        axes[0].set_title(title)
    return fig, axes
