"""Colours and array/axes helpers shared by :mod:`treeinfer.plots` and
:mod:`treeinfer.plot_posterior`."""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from .errors import ConfigError

BAND_COLOR = "0.6"
GT_COLOR = "tab:red"
MEAN_COLOR = "0.15"
SAMPLE_COLOR = "tab:blue"
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
