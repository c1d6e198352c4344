"""JSON in and out for everything treeinfer writes: strict JSON (NaN/inf become null), written
atomically; read back with errors naming the file and line."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import jax
import numpy as np

from ..errors import ConfigError
from .atomic import atomic_write_json

__all__ = ["jsonable", "read_json", "write_json"]


def jsonable(o: Any) -> Any:
    """Plain JSON values; NaN/inf become None (strict JSON has no NaN)."""
    if isinstance(o, dict):
        return {str(k): jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [jsonable(v) for v in o]
    if isinstance(o, Path):
        return str(o)
    if isinstance(o, (np.ndarray, jax.Array)):
        return jsonable(np.asarray(o).tolist())
    if isinstance(o, np.generic):
        o = o.item()
    if isinstance(o, float) and not math.isfinite(o):
        return None
    return o


def write_json(path, obj) -> Path:
    return atomic_write_json(path, jsonable(obj))


def read_json(path: Path, what: str, where: str | None = None, kinds: tuple = (dict,)) -> Any:
    """A JSON object through the safe loader (:mod:`treeinfer.io.safe_load`: regular files only,
    size and depth limits, no duplicate keys); ConfigError naming the file and line.

    ``where``: how errors name the file (default: its path, e.g. ``"--params-json FILE"``);
    ``kinds``: the JSON types accepted at the top (default: an object only). The one JSON
    reader of treeinfer's files (run configs, summaries, ``true_params.json``)."""
    from .safe_load import load_file

    try:
        d = load_file(path, what, ConfigError, fmt="json")
    except ConfigError as e:
        if where is None or where == str(path):
            raise
        raise ConfigError(str(e).replace(str(path), where, 1)) from None
    if not isinstance(d, kinds):
        raise ConfigError(f"{where or path}: {what} must be a JSON object")
    return d
