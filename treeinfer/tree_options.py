"""The tree description's options read from a tree file or the command line, parsed at the
lowest layer (no treeinfer imports but :mod:`treeinfer.errors`): the pull direction, the
inferred parameters (``kp``/``kd``) and the stiffness tie. Re-exported by
:mod:`treeinfer.tree_types`, :mod:`treeinfer.tree`, :mod:`treeinfer.pulls` and
:mod:`treeinfer.static`."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from .errors import ConfigError

DIRECTION_WORDS = ("down", "horizontal")
PARAMETERS = ("kp", "kd")


def parse_direction(value: Any, where: str = "direction") -> str | tuple[float, float, float]:
    """Validate a direction: ``down``, ``horizontal``, ``[x, y, z]`` or the text ``"x,y,z"``.

    Returns the word (lower case) or the 3-tuple as given (not normalised).

    Raises:
        ConfigError: naming ``where``: unknown word, wrong length, non-finite or zero vector.
    """
    if isinstance(value, str):
        word = value.strip().lower()
        if word in DIRECTION_WORDS:
            return word
        parts = [p for p in word.replace(",", " ").split() if p]
        if len(parts) == 3:
            value = parts
        else:
            raise ConfigError(
                f"{where}: expected 'down', 'horizontal' or a vector [x, y, z], got {value!r}"
            )
    if not isinstance(value, (list, tuple, np.ndarray)) or len(value) != 3:
        raise ConfigError(
            f"{where}: expected 'down', 'horizontal' or a vector [x, y, z], got {value!r}"
        )
    try:
        vec = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: vector components must be numbers, got {value!r}") from None
    if not all(math.isfinite(v) for v in vec):
        raise ConfigError(f"{where}: vector components must be finite, got {list(vec)}")
    if math.hypot(*vec) == 0.0:
        raise ConfigError(f"{where}: the zero vector has no direction")
    return vec  # type: ignore[return-value]


def parse_tree_pull(value: Any, source: str = "<tree>") -> str | tuple[float, float, float]:
    """Parse a tree file's ``pull:`` mapping; returns its default direction (``"down"`` if absent).

    Hook for :func:`treeinfer.tree.tree_from_dict`: accept the top-level key ``pull`` and store
    ``parse_tree_pull(d.get("pull"), source)`` on the tree (e.g. ``Tree.pull_direction``).
    """
    if value is None:
        return "down"
    if not isinstance(value, Mapping):
        raise ConfigError(
            f"{source}: pull: expected a mapping like {{direction: down}}, got {value!r}"
        )
    bad = set(value) - {"direction"}
    if bad:
        raise ConfigError(
            f"{source}: pull: unknown field(s) {sorted(map(str, bad))}; allowed: direction"
        )
    if value.get("direction") is None:
        return "down"
    return parse_direction(value["direction"], f"{source}: pull: field 'direction'")


def parse_parameters(value, source: str = "inference.parameters") -> tuple[str, ...]:
    """Validate ``inference: {parameters: [...]}``: a list of ``kp``/``kd`` containing ``kp``."""
    if value is None:
        return PARAMETERS
    if isinstance(value, str):
        value = [v for v in value.replace(",", " ").split() if v]
    if not isinstance(value, (list, tuple)) or not value:
        raise ConfigError(f"{source}: expected a list like [kp] or [kp, kd], got {value!r}")
    names = [str(v).strip().lower() for v in value]
    bad = [n for n in names if n not in PARAMETERS]
    if bad:
        raise ConfigError(f"{source}: unknown parameter(s) {bad}; allowed: kp, kd")
    if "kp" not in names:
        raise ConfigError(
            f"{source}: stiffness (kp) must be inferred; damping alone is not supported"
        )
    if len(set(names)) != len(names):
        raise ConfigError(f"{source}: duplicate entries in {names}")
    return tuple(p for p in PARAMETERS if p in names)


TIES = ("taper",)


def parse_tie(
    tie, tie_scale=None, source: str = "inference", names=("tie", "tie_scale")
) -> tuple[str | None, float | None]:
    """Validate ``inference: {tie: taper, tie_scale: TAU}`` (or ``--tie``/``--tie-scale``:
    ``source=""`` and ``names=("--tie", "--tie-scale")``).

    Returns:
        (tie, tie_scale): tie None (``none`` or absent: every joint's stiffness free) or
        ``"taper"``; tie_scale None (hard tie) or a finite TAU > 0 in natural-log units.
    Raises:
        ConfigError: an unknown tie, a bad scale, or a scale without a tie.
    """
    where = f"{source}." if source else ""
    name = None if tie is None else str(tie).strip().lower()
    if name in ("none", ""):
        name = None
    if name is not None and name not in TIES:
        raise ConfigError(
            f"{where}{names[0]}: unknown tie {tie!r}; expected one of: {', '.join(TIES)} (or none)"
        )
    if tie_scale is None:
        return name, None
    if isinstance(tie_scale, bool):
        tau = float("nan")
    else:
        try:
            tau = float(tie_scale)
        except (TypeError, ValueError):
            tau = float("nan")
    if not (math.isfinite(tau) and tau > 0):
        raise ConfigError(
            f"{where}{names[1]}: expected a positive number (std of each joint's log-stiffness "
            f"about the taper), got {tie_scale!r}"
        )
    if name is None:
        raise ConfigError(f"{where}{names[1]}: given without a tie; add {names[0]} taper")
    return name, tau
