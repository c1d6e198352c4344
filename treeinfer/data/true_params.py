"""``true_params.json``: the one reader and writer of the true parameters of a synthetic data set
(natural units, checked positive and finite; errors name the file and field). Re-exported by
:mod:`treeinfer.data.trajectories`."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..errors import ConfigError, check_positive
from ..io.jsonio import read_json, write_json

# ==== true_params.json: the one reader and writer ================================================
TRUE_PARAMS_FILE = "true_params.json"
GAIN_UNITS = {"kp": "N m/rad", "kd": "N m s/rad"}


def check_positive_params(values: Sequence[float], labels: Sequence[str], where: str) -> np.ndarray:
    """``values`` as a float array [len(labels)], each a positive finite number (ConfigError
    naming ``where`` and the label otherwise)."""
    if len(values) != len(labels):
        raise ConfigError(
            f"{where}: expected {len(labels)} numbers, in the order {', '.join(labels)}; "
            f"got {len(values)}"
        )
    out = np.empty(len(labels))
    for i, (v, lab) in enumerate(zip(values, labels)):
        out[i] = check_positive(v, f"{where}: {lab}")
    return out


def read_true_params(tree, path: str | os.PathLike, where: str | None = None) -> np.ndarray:
    """True parameters [2R] (Kp of each inferred joint of ``tree``, then Kd; natural units) from
    a JSON file: a ``true_params.json`` (``{"kp": {joint: value}, "kd": {joint: value}}``),
    ``{"theta_log": [2R natural logs]}`` or a plain list of 2R numbers. ``where`` names the file
    in error messages (default: its path)."""

    labels = tree.parameter_labels()
    where = str(path) if where is None else where
    d = read_json(
        Path(path), "parameter file", where=where, kinds=(dict, list, str, int, float, type(None))
    )
    if isinstance(d, list):
        return check_positive_params(d, labels, where)
    if not isinstance(d, dict):
        raise ConfigError(
            f"{where}: expected an object with 'kp' and 'kd' (or 'theta_log'), or a list"
        )
    if "kp" in d or "kd" in d:
        vals = []
        for key in ("kp", "kd"):
            m = d.get(key)
            if not isinstance(m, dict):
                raise ConfigError(
                    f"{where}: field '{key}' must map joint names to values, got {m!r}"
                )
            missing = [n for n in tree.inferred if n not in m]
            extra = sorted(set(m) - set(tree.inferred))
            if missing or extra:
                raise ConfigError(
                    f"{where}: field '{key}' must give exactly the inferred joints "
                    f"{list(tree.inferred)}"
                    + (f"; missing {missing}" if missing else "")
                    + (f"; not inferred: {extra}" if extra else "")
                )
            vals += [m[n] for n in tree.inferred]
        return check_positive_params(vals, labels, where)
    if "theta_log" in d:
        t = d["theta_log"]
        if not isinstance(t, list) or len(t) != len(labels):
            raise ConfigError(
                f"{where}: field 'theta_log' must be a list of {len(labels)} numbers "
                f"({', '.join(labels)})"
            )
        try:
            vals = [math.exp(float(x)) for x in t]
        except (TypeError, ValueError, OverflowError):
            raise ConfigError(f"{where}: field 'theta_log' must hold numbers, got {t!r}") from None
        return check_positive_params(vals, labels, where)
    raise ConfigError(f"{where}: expected fields 'kp' and 'kd' (or 'theta_log'), found {sorted(d)}")


def true_params_record(tree, kp, kd, source: str, log_units: bool = True) -> dict:
    """The ``true_params.json`` object of gains ``kp``, ``kd`` [R] (natural units)."""
    units = dict(GAIN_UNITS)
    if log_units:
        units["theta_log"] = "natural log of kp, kd"
    return {
        "labels": tree.parameter_labels(),
        "kp": {n: float(v) for n, v in zip(tree.inferred, kp)},
        "kd": {n: float(v) for n, v in zip(tree.inferred, kd)},
        "theta_log": [float(math.log(v)) for v in np.concatenate([kp, kd])],
        "units": units,
        "source": source,
    }


def write_true_params(path: str | os.PathLike, record: dict) -> Path:
    """Write a :func:`true_params_record` atomically (strict JSON)."""
    return write_json(Path(path), record)
