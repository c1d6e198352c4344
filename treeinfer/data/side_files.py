"""Files written beside recordings and predictions: the per-recording band CSV (``time, force,
recorded, mean, lower, upper``) of ``predict``/``evaluate`` and the importers' provenance
(``import.json``). Re-exported by :mod:`treeinfer.data.trajectories`."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..io.atomic import atomic_write_text

BAND_COLUMNS = ("time", "force", "recorded", "mean", "lower", "upper")


def band_csv_text(
    time,
    force,
    recorded,
    mean,
    lower,
    upper,
    predictive_lower=None,
    predictive_upper=None,
) -> str:
    """One recording's prediction as CSV text, header first, for users' own plots and scores.

    Columns ``time,force,recorded,mean,lower,upper`` (s, N, m, m, m, m): ``lower``/``upper``
    bound the 95% band over the parameters; with ``predictive_lower``/``predictive_upper``
    (the band including observation noise) two more columns of those names follow.
    ``recorded`` may be ``None`` (a force profile without displacement): an empty column;
    NaN (padding) is written as an empty cell too.
    """
    cols = [time, force, recorded, mean, lower, upper]
    names = list(BAND_COLUMNS)
    if predictive_lower is not None or predictive_upper is not None:
        if predictive_lower is None or predictive_upper is None:
            raise ConfigError("band CSV: give both predictive_lower and predictive_upper")
        cols += [predictive_lower, predictive_upper]
        names += ["predictive_lower", "predictive_upper"]
    n = len(np.asarray(time))
    arrs = []
    for name, c in zip(names, cols):
        if c is None:
            arrs.append(np.full(n, np.nan))
            continue
        a = np.asarray(c, dtype=float).reshape(-1)
        if a.shape[0] != n:
            raise ConfigError(f"band CSV: column '{name}' has {a.shape[0]} values, time {n}")
        arrs.append(a)
    out = [",".join(names)]
    out.extend(
        ",".join(repr(float(v)) if math.isfinite(v) else "" for v in row) for row in zip(*arrs)
    )
    return "\n".join(out) + "\n"


def write_band_csv(path: str | os.PathLike, *columns, **kwargs) -> Path:
    """Write :func:`band_csv_text` atomically to ``path`` (same arguments)."""
    return atomic_write_text(path, band_csv_text(*columns, **kwargs))


PROVENANCE_FILE = "import.json"


def write_provenance(directory: str | os.PathLike, entries: dict) -> Path:
    """Write ``<directory>/import.json``: how the folder's CSVs were made (JSON object; keys are
    free-form, e.g. ``{"source": ..., "options": {...}, "files": {"a.csv": [steps...]}}``)."""
    from ..io.atomic import atomic_write_json

    return atomic_write_json(Path(directory) / PROVENANCE_FILE, entries)
