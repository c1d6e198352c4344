"""Figures of a posterior on plain arrays: the pair plot (KDE marginals, 68%/95% highest-density
contours, the prior box, the truth), metric bars and the sampler trace (:mod:`.plot_trace`);
conventions as in :mod:`treeinfer.evaluation.plots`, which re-exports every name here."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from matplotlib.axes import Axes

from ..errors import ConfigError
from ._plot_common import (
    GT_COLOR,
    LOG_MIN_DECADES,
    PRIOR_COLOR,
    SET_COLORS,
    _new_axes,
    _np,
    plain_log_ticks,
    with_unit,
    wrap_title,
)
from .trace_plot import plot_trace  # noqa: F401 -- re-exported: the old import path keeps working

# --------------------------------------------------------------------------- pair plot


def _kde_curve(x: np.ndarray, grid: np.ndarray) -> np.ndarray | None:
    """1-D Scott's-rule Gaussian KDE on ``grid`` (same rule as treeinfer.evaluation.metrics).

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
    units: Sequence[str] | None = None,
    log_axes: bool | Sequence[bool] = False,
    prior_box=None,
    view: str = "auto",
):
    """Corner plot of posterior samples, paper Fig. 4 style.

    Args:
      samples: ``[P, D]`` particles, or a mapping ``{name: [P_k, D]}`` to
        overlay several sets (e.g. ``{"NNSVGD": a, "SVGD": b}``) with a legend.
      labels: ``D`` parameter names, e.g. ``["Kp[b1]", "Kd[b1]", ...]``.
      truth: optional ``[D]`` true values (a simulation's; NaN: none): red lines on the
        diagonal, red dots below, "truth" in the legend.
      kind: ``"scatter"`` or ``"kde"`` (68%/95% highest-density contours of a
        2-D Scott's-rule KDE; falls back to scatter for a collapsed set).
      bins: histogram bins on the diagonal (a 1-D KDE curve is drawn over them: the marginal).
      max_points: at most this many points per set in each scatter.
      units: ``D`` units shown in the axis labels (``"Kp[b1] [N m/rad]"``).
      log_axes: log-scale axes (all, or per parameter); histograms and KDEs are then taken
        in log10 of the values (positive samples needed).
      prior_box: ``(lower [D], upper [D])`` drawn dashed (NaN: no box for that parameter).
      view: ``"prior"`` (axes span the prior box), ``"posterior"`` (the samples) or ``"auto"``:
        per parameter the box when the samples fill at least 5% of its width, else the samples.

    Returns:
      ``(fig, axes)``, ``axes`` is ``[D, D]``; panels above the diagonal are hidden.
    """
    if kind not in ("scatter", "kde"):
        raise ConfigError(f"kind: expected 'scatter' or 'kde', got {kind!r}")
    if view not in ("auto", "prior", "posterior"):
        raise ConfigError(f"view: expected 'auto', 'prior' or 'posterior', got {view!r}")
    sets = dict(samples) if isinstance(samples, Mapping) else {"samples": samples}
    sets = {k: _np(v, f"samples[{k!r}]", 2) for k, v in sets.items()}
    D = next(iter(sets.values())).shape[1]
    for k, v in sets.items():
        if v.shape[1] != D:
            raise ConfigError(f"samples[{k!r}]: expected {D} columns, got {v.shape[1]}")
    labels = list(labels) if labels is not None else [f"theta[{i}]" for i in range(D)]
    if len(labels) != D:
        raise ConfigError(f"labels: expected {D} names, got {len(labels)}")
    if units is not None and len(units) != D:
        raise ConfigError(f"units: expected {D} units, got {len(units)}")
    names = [with_unit(lab, None if units is None else units[i]) for i, lab in enumerate(labels)]
    logs = np.broadcast_to(np.asarray(log_axes, bool), (D,))
    tr = None if truth is None else _np(truth, "truth", 1)
    if tr is not None and tr.shape != (D,):
        raise ConfigError(f"truth: expected shape ({D},), got {tr.shape}")
    box = None
    if prior_box is not None:
        box = np.asarray(prior_box, float)
        if box.shape != (2, D):
            raise ConfigError(f"prior_box: expected (lower [{D}], upper [{D}]), got {box.shape}")

    # every computation in plot coordinates: log10 of the values on log axes
    def fwd(a, cols=slice(None)):
        a = np.asarray(a, float)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(logs[cols], np.log10(np.where(a > 0, a, np.nan)), a)

    def inv(a, i):
        return 10.0**a if logs[i] else a

    finite = {}
    for k, v in sets.items():
        if np.any(v[:, logs] <= 0):
            raise ConfigError(f"samples[{k!r}]: log axes need positive values")
        finite[k] = fwd(v[np.all(np.isfinite(v), axis=1)])
    allv = np.concatenate(list(finite.values()))
    lo, hi = allv.min(0), allv.max(0)
    if tr is not None:  # NaN entries: no true value (e.g. a noise column), nothing marked
        lo, hi = np.fmin(lo, fwd(tr)), np.fmax(hi, fwd(tr))
    bt = None if box is None else fwd(box)
    if bt is not None:
        width = bt[1] - bt[0]
        use = np.isfinite(width) & (width > 0)
        if view == "auto":
            use &= (hi - lo) >= 0.05 * np.where(use, width, np.inf)
        elif view == "posterior":
            use[:] = False
        lo, hi = np.where(use, np.fmin(lo, bt[0]), lo), np.where(use, np.fmax(hi, bt[1]), hi)
    pad = np.where(hi > lo, 0.05 * (hi - lo), np.maximum(np.abs(lo) * 0.05, 1e-3))
    lo, hi = lo - pad, hi + pad

    # a log scale only where the view spans a good part of a decade (ticks crowd otherwise);
    # the histograms and KDEs stay in log10 of the values either way
    log_scale = logs & (hi - lo >= LOG_MIN_DECADES)
    size = figsize or (max(4.5, 2.1 * D), max(4.5, 2.1 * D))
    fig, axes = _new_axes(D, D, figsize=size)
    multi = len(finite) > 1
    for s_idx, (name, v) in enumerate(finite.items()):
        color = SET_COLORS[s_idx % len(SET_COLORS)]
        pts = v[:: max(1, len(v) // max_points)]
        for i in range(D):
            ax = axes[i, i]
            # histogram and KDE both per unit of the plot coordinate (log10 on a log axis)
            edges = np.linspace(lo[i], hi[i], bins + 1)
            h, _ = np.histogram(v[:, i], bins=edges, density=True)
            ax.stairs(
                h, inv(edges, i), fill=True, color=color, alpha=0.3, label=name if multi else None
            )
            g = np.linspace(lo[i], hi[i], 200)
            curve = _kde_curve(v[:, i], g)
            if curve is not None:
                ax.plot(inv(g, i), curve, color=color, lw=1.2)
            for j in range(i):
                ax2 = axes[i, j]
                dens = None
                if kind == "kde":
                    gx, gy = np.linspace(lo[j], hi[j], 60), np.linspace(lo[i], hi[i], 60)
                    dens = _kde_2d(v[:, j], v[:, i], gx, gy)
                if dens is not None:
                    ax2.contour(
                        inv(gx, j),
                        inv(gy, i),
                        dens,
                        levels=_hdr_levels(dens),
                        colors=color,
                        linewidths=1.0,
                    )
                else:
                    ax2.scatter(
                        inv(pts[:, j], j), inv(pts[:, i], i), s=6, color=color, alpha=0.5, lw=0
                    )
    from matplotlib.patches import Rectangle

    def has_box(i):
        return bt is not None and np.all(np.isfinite(bt[:, i]))

    for i in range(D):
        for j in range(D):
            ax = axes[i, j]
            if j > i:
                ax.set_visible(False)
                continue
            if log_scale[j]:
                ax.set_xscale("log")
                plain_log_ticks(ax.xaxis)
            ax.set_xlim(inv(lo[j], j), inv(hi[j], j))
            if j < i:
                if log_scale[i]:
                    ax.set_yscale("log")
                    plain_log_ticks(ax.yaxis)
                ax.set_ylim(inv(lo[i], i), inv(hi[i], i))
                if has_box(i) and has_box(j):
                    ax.add_patch(
                        Rectangle(
                            (box[0, j], box[0, i]),
                            box[1, j] - box[0, j],
                            box[1, i] - box[0, i],
                            fill=False,
                            ls="--",
                            lw=1.0,
                            ec=PRIOR_COLOR,
                            zorder=1,
                            label="prior box",
                        )
                    )
                if tr is not None and np.isfinite(tr[i]) and np.isfinite(tr[j]):
                    ax.plot(tr[j], tr[i], "o", color=GT_COLOR, ms=5, zorder=5)
            else:
                if has_box(i):
                    ax.axvspan(
                        box[0, i], box[1, i], fill=False, ls="--", lw=1.0, ec=PRIOR_COLOR, zorder=1
                    )
                if tr is not None and np.isfinite(tr[i]):
                    ax.axvline(tr[i], color=GT_COLOR, lw=1.2, zorder=5)
            if i == D - 1:
                ax.set_xlabel(names[j])
            else:
                ax.tick_params(which="both", labelbottom=False)
            if j == 0 and i > 0:
                ax.set_ylabel(names[i])
            elif j > 0 or i == 0:
                ax.tick_params(which="both", labelleft=False)
            if i == j:
                ax.set_yticks([])
                ax.set_yticks([], minor=True)
                ax.set_title(f"{labels[i]}", fontsize="small")
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    handles, legend_names = axes[0, 0].get_legend_handles_labels()
    if tr is not None and np.any(np.isfinite(tr)):
        handles.append(Line2D([], [], color=GT_COLOR, marker="o", lw=1.2))
        legend_names.append("truth")
    if bt is not None and np.any(np.isfinite(bt)):
        handles.append(Patch(fill=False, ls="--", ec=PRIOR_COLOR))
        legend_names.append("prior box")
    if handles and D > 1:  # in the empty upper triangle
        fig.legend(handles, legend_names, loc="upper right", frameon=False)
    elif handles:
        axes[0, 0].legend(handles, legend_names, loc="upper right", frameon=False, fontsize="small")
    if title:
        fig.suptitle(wrap_title(title, size[0]))
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
