"""User-facing errors.

Every mistake a user can make in a file or an option raises a subclass of
:class:`TreeinferError` whose message names the file, line or field and the
problem. The command line prints these without a traceback (``--debug`` shows
one); anything else escaping is a bug in treeinfer.
"""

from __future__ import annotations

import math


class TreeinferError(Exception):
    """Base class for errors caused by user input, not by a bug."""


class TreeFileError(TreeinferError):
    """A tree description (YAML/JSON/MJCF/URDF) is malformed or inconsistent."""


class TrajectoryFileError(TreeinferError):
    """A trajectory CSV (or ROS bag) is malformed, inconsistent or implausible."""


class ConfigError(TreeinferError):
    """An option, config value or parameter is out of range or inconsistent."""


class SimulationError(TreeinferError):
    """The simulator could not produce a usable result (e.g. too many unstable particles)."""


class OutputExistsError(TreeinferError):
    """An output folder already holds results and ``--force`` was not given."""


class PosteriorError(ConfigError):
    """A posterior cannot answer what was asked: samples of a run that failed (poor fit,
    interrupted), or a prediction for a grasp point or force outside what the run supports."""


def where(path=None, line=None, field=None) -> str:
    """Format a location prefix such as ``data/pull1.csv, line 12, column 'force'``."""
    parts = []
    if path is not None:
        parts.append(str(path))
    if line is not None:
        parts.append(f"line {line}")
    if field is not None:
        parts.append(f"field '{field}'")
    return ", ".join(parts)


def check_positive(
    v, subject: str, what: str = "a finite positive number", error: type = None
) -> float:
    """``v`` as a float if it is a finite number > 0; else ``error`` (ConfigError by default)
    saying ``"{subject} must be {what}, got {v!r}"``. The one "positive finite number" check of
    the options, tree fields, generator settings and parameter files."""
    error = ConfigError if error is None else error
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise error(f"{subject} must be {what}, got {v!r}") from None
    if not (math.isfinite(f) and f > 0):
        raise error(f"{subject} must be {what}, got {v!r}")
    return f
