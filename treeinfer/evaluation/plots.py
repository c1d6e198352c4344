"""Figures on plain arrays: predictive bands, pair plots, metric bars, traces.

Every function takes numpy/JAX arrays and returns ``(fig, axes)``; nothing
calls ``plt.show``. Figures are built with :class:`matplotlib.figure.Figure`
directly, not through ``pyplot``, so they work under any backend (Agg on a
headless machine, inline in notebooks, where a returned figure displays
itself) and leave no global pyplot state behind. Pass ``ax=`` to draw into an
existing axes instead. Save with :func:`save_figure`.

Colours follow the paper's figures: the 95% band in grey, the reference in red: a real pull's
measured displacement is labelled "recording", a simulation's noise-free response "truth"
(``reference_label``); "ground truth" is never used for a recording.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from ..errors import ConfigError
from ..io.atomic import atomic_save
from ._plot_common import (  # noqa: F401 -- re-exported: the old import path keeps working
    BAND_COLOR,
    GT_COLOR,
    MEAN_COLOR,
    SAMPLE_COLOR,
    SET_COLORS,
    _new_axes,
    _np,
    wrap_title,
)
from .posterior_plots import (  # noqa: F401 -- re-exported: the old import path keeps working
    metric_bars,
    pair_plot,
    plot_trace,
)

__all__ = [
    "metric_bars",
    "pair_plot",
    "plot_band_grid",
    "plot_trace",
    "plot_trajectory_bands",
    "save_figure",
]

# --------------------------------------------------------------------------- bands


def plot_trajectory_bands(
    time,
    lower,
    upper,
    mean=None,
    gt=None,
    samples=None,
    *,
    ax: Axes | None = None,
    title: str | None = None,
    xlabel: str = "time [s]",
    ylabel: str = "displacement [m]",
    band_label: str = "95% CI",
    max_samples: int = 20,
    legend: bool = True,
    reference_label: str = "recording",
):
    """Predictive band of one trajectory, paper Fig. 3/5/6/7 style.

    Args:
      time: ``[T]`` seconds (or step index).
      lower, upper: ``[T]`` band limits, e.g. from
      :func:`treeinfer.evaluation.metrics.predictive_interval`. mean: optional ``[T]`` predictive
      mean (dark dashed line). gt: optional ``[T]`` reference displacement (red), named
      ``reference_label``:
        ``"recording"`` (a measured pull, the default) or ``"truth"`` (a simulation's
        noise-free response). NaN points are not drawn.
      samples: optional ``[S, T]`` predicted trajectories (thin lines, first ``max_samples``).
      ax: draw into this axes instead of a new figure.

    Returns:
      ``(fig, ax)``.
    """
    t = _np(time, "time", 1)
    lo, hi = _np(lower, "lower", 1), _np(upper, "upper", 1)
    if lo.shape != t.shape or hi.shape != t.shape:
        raise ConfigError(
            f"lower/upper: expected shape {t.shape} to match time, got {lo.shape}/{hi.shape}"
        )
    if ax is None:
        fig, axs = _new_axes(figsize=(6.0, 3.5))
        ax = axs[0, 0]
    fig = ax.figure
    if samples is not None:
        s = _np(samples, "samples", 2)[:max_samples]
        for i, row in enumerate(s):
            ax.plot(
                t, row, color=SAMPLE_COLOR, lw=0.5, alpha=0.35, label="samples" if i == 0 else None
            )
    ax.fill_between(t, lo, hi, color=BAND_COLOR, alpha=0.5, lw=0, label=band_label)
    if mean is not None:
        ax.plot(t, _np(mean, "mean", 1), color=MEAN_COLOR, lw=1.0, ls="--", label="predictive mean")
    if gt is not None:
        ax.plot(t, _np(gt, "gt", 1), color=GT_COLOR, lw=1.5, label=reference_label)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(wrap_title(title, ax.get_position().width * fig.get_figwidth()))
    if legend:
        ax.legend(loc="best", fontsize="small", frameon=False)
    return fig, ax


def plot_band_grid(
    time,
    lower,
    upper,
    mean=None,
    gt=None,
    samples=None,
    *,
    titles: Sequence[str] | None = None,
    row_labels: Sequence[str] | None = None,
    col_labels: Sequence[str] | None = None,
    ncols: int = 3,
    sharey: bool = True,
    suptitle: str | None = None,
    xlabel: str = "time [s]",
    ylabel: str = "displacement [m]",
    panel_size=(3.2, 2.4),
    max_samples: int = 10,
    reference_label: str = "recording",
):
    """Several predictive bands in a grid with shared axes (noise sweep, grasp study, samplers).

    Args:
      time: ``[T]`` shared, or one per panel with the panel shape (``[K, T]`` / ``[R, C, T]``).
      lower, upper (and optional mean, gt): ``[K, T]`` laid out in ``ncols``
        columns, or ``[R, C, T]`` for an explicit rows x columns grid (e.g. rows =
        samplers, columns = test trajectories).
      samples: optional ``[K, S, T]`` / ``[R, C, S, T]``.
      titles: ``K`` (or ``R*C``) panel titles; ``row_labels`` / ``col_labels``
        label the grid's rows (y label) and columns (titles) instead.
      reference_label: the name of ``gt`` in the legend (``"recording"`` or ``"truth"``, as
        in :func:`plot_trajectory_bands`).

    Returns:
      ``(fig, axes)`` with ``axes`` the full ``[rows, cols]`` array; unused
      panels are hidden. Only the first panel carries a legend.
    """
    lo = _np(lower, "lower", (2, 3))
    hi = _np(upper, "upper", lo.ndim)
    if hi.shape != lo.shape:
        raise ConfigError(f"upper: expected shape {lo.shape} to match lower, got {hi.shape}")
    T = lo.shape[-1]
    if lo.ndim == 3:
        nrows, ncols = lo.shape[:2]
    else:
        ncols = max(1, min(ncols, lo.shape[0]))
        nrows = -(-lo.shape[0] // ncols)
    grid = lo.shape[:-1]
    K = int(np.prod(grid))

    def panels(a, name, extra=0):
        if a is None:
            return [None] * K
        a = _np(a, name)
        if a.shape[: len(grid)] != grid:
            raise ConfigError(
                f"{name}: expected leading shape {grid} to match lower, got {a.shape}"
            )
        return list(a.reshape((K,) + a.shape[len(grid) :]))

    t = _np(time, "time")
    times = [t] * K if t.ndim == 1 else panels(t, "time")
    if times[0].shape != (T,):
        raise ConfigError(f"time: expected {T} steps, got shape {times[0].shape}")
    lows, highs = list(lo.reshape(K, T)), list(hi.reshape(K, T))
    means, gts, samps = panels(mean, "mean"), panels(gt, "gt"), panels(samples, "samples")
    if titles is not None and len(titles) != K:
        raise ConfigError(f"titles: expected {K} titles, got {len(titles)}")

    fig, axes = _new_axes(
        nrows,
        ncols,
        figsize=(panel_size[0] * ncols, panel_size[1] * nrows),
        sharex=True,
        sharey=sharey,
    )
    flat = axes.ravel()
    for k in range(K):
        ax = flat[k]
        plot_trajectory_bands(
            times[k],
            lows[k],
            highs[k],
            means[k],
            gts[k],
            samps[k],
            ax=ax,
            title=titles[k] if titles is not None else None,
            xlabel="",
            ylabel="",
            max_samples=max_samples,
            legend=(k == 0),
            reference_label=reference_label,
        )
    for ax in flat[K:]:
        ax.set_visible(False)
    if col_labels is not None:
        for c, lab in enumerate(col_labels):
            axes[0, c].set_title(lab)
    if row_labels is not None:
        for r, lab in enumerate(row_labels):
            axes[r, 0].set_ylabel(lab)
    fig.supxlabel(xlabel)
    fig.supylabel(ylabel)
    if suptitle:
        fig.suptitle(wrap_title(suptitle, panel_size[0] * ncols))
    return fig, axes


# --------------------------------------------------------------------------- saving


FIGURE_FORMATS = ("png", "pdf", "svg")


def save_figure(fig: Figure, path, dpi: int = 120, formats=None) -> list:
    """Save ``fig`` atomically and close it; returns the paths written.

    ``path``'s suffix gives the format (usually ``.png``); ``formats`` (e.g. ``("png", "pdf")``,
    any of :data:`FIGURE_FORMATS`) writes ``path`` with each of those suffixes instead.
    Closing releases the figure from ``pyplot`` if it was made there; figures
    from this module are not registered with ``pyplot`` and need no closing.
    """
    from pathlib import Path

    path = Path(path)
    if formats is None:
        targets = [path]
    else:
        fmts = [formats] if isinstance(formats, str) else list(formats)
        bad = [f for f in fmts if str(f).lower().lstrip(".") not in FIGURE_FORMATS]
        if bad or not fmts:
            raise ConfigError(
                f"formats: expected some of {', '.join(FIGURE_FORMATS)}, got {list(fmts)!r}"
            )
        targets = [path.with_suffix("." + str(f).lower().lstrip(".")) for f in dict.fromkeys(fmts)]
    for target in targets:
        with atomic_save(target) as tmp:
            fig.savefig(tmp, dpi=dpi, format=tmp.suffix.lstrip(".") or "png")
    plt = sys.modules.get("matplotlib.pyplot")  # only if the caller already uses pyplot
    if plt is not None:
        plt.close(fig)
    return targets
