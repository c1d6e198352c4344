"""Colours and array/axes helpers shared by :mod:`treeinfer.evaluation.plots` and
:mod:`treeinfer.evaluation.posterior_plots`."""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from ..errors import ConfigError

BAND_COLOR = "0.6"
GT_COLOR = "tab:red"
MEAN_COLOR = "0.15"
SAMPLE_COLOR = "tab:blue"
PRIOR_COLOR = "0.35"  # the prior box, dashed
SET_COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:brown")


def _np(x, name: str, ndim: int | tuple[int, ...] | None = None) -> np.ndarray:
    a = np.asarray(x, dtype=float)
    if ndim is not None and a.ndim not in np.atleast_1d(ndim):
        raise ConfigError(f"{name}: expected {ndim}-D array, got shape {a.shape}")
    return a


def _new_axes(nrows: int = 1, ncols: int = 1, figsize=None, **kw) -> tuple[Figure, np.ndarray]:
    fig = Figure(figsize=figsize, layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False, **kw)
    return fig, axes


def wrap_title(text: str | None, width_in: float, fontsize: float = 12.0) -> str | None:
    """``text`` broken into lines that fit ``width_in`` inches at ``fontsize`` points (an
    average glyph is about 0.55 em wide): constrained layout makes room for a title's height but
    never shortens a line, so a long title would run off the figure."""
    if not text:
        return text
    import textwrap

    chars = max(20, int(width_in * 72.0 / (0.55 * fontsize)))
    return "\n".join(textwrap.fill(line, chars) for line in str(text).split("\n"))


def with_unit(label: str, unit: str | None) -> str:
    """``"Kp[child] [N m/rad]"``; the label alone for a unitless quantity."""
    return f"{label} [{unit}]" if unit and unit != "1" else label


def plain_log_ticks(axis) -> None:
    """Plain numbers (``300``, ``0.1``; not ``3 x 10^2``, ``1e-01``) on a log ``axis``
    (``ax.xaxis``/``ax.yaxis``); minor ticks labelled only where a decade holds few of them
    (matplotlib's thresholds)."""
    from matplotlib.ticker import LogFormatter

    class Plain(LogFormatter):
        def _num_to_string(self, x, vmin, vmax):  # where LogFormatter formats one number
            return f"{x:g}"

    axis.set_major_formatter(Plain(labelOnlyBase=False))
    axis.set_minor_formatter(Plain(labelOnlyBase=False, minor_thresholds=(1.5, 0.5)))


LOG_MIN_DECADES = 0.5  # a log axis narrower than this reads better (and ticks better) linear
