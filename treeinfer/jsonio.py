"""JSON in and out for everything treeinfer writes: strict JSON (NaN/inf become null), written
atomically; read back with errors naming the file and line."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import jax
import numpy as np

from ._io import atomic_write_json
from .errors import ConfigError

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


def read_json(path: Path, what: str) -> dict:
    """A JSON object through the safe loader (:mod:`treeinfer.safe_load`: regular files only,
    size and depth limits, no duplicate keys); ConfigError naming the file and line."""
    from .safe_load import load_file

    d = load_file(path, what, ConfigError, fmt="json")
    if not isinstance(d, dict):
        raise ConfigError(f"{path}: {what} must be a JSON object")
    return d
