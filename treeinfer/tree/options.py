"""The tree description's options read from a tree file or the command line, parsed at the
lowest layer (no treeinfer imports but :mod:`treeinfer.errors`): the pull direction, the
inferred parameters (``kp``/``kd``) and the stiffness tie. Re-exported by
:mod:`treeinfer.tree.types`, :mod:`treeinfer.tree.description`, :mod:`treeinfer.data.pulls` and
:mod:`treeinfer.inference.static`."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from ..errors import ConfigError

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

    Hook for :func:`treeinfer.tree.description.tree_from_dict`: accept the top-level key ``pull``
    and store ``parse_tree_pull(d.get("pull"), source)`` on the tree (e.g. ``Tree.pull_direction``).
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


TIES = ("taper", "shape")


def parse_tie(
    tie, tie_scale=None, source: str = "inference", names=("tie", "tie_scale")
) -> tuple[str | None, float | None]:
    """Validate ``inference: {tie: taper|shape, tie_scale: TAU}`` (or ``--tie``/``--tie-scale``:
    ``source=""`` and ``names=("--tie", "--tie-scale")``). The shape of ``tie: shape`` is
    checked by :func:`parse_tie_shape` and :func:`resolve_tie_shape`.

    Returns:
        (tie, tie_scale): tie None (``none`` or absent: every joint's stiffness free),
        ``"taper"`` or ``"shape"``; tie_scale None (hard tie) or a finite TAU > 0 in
        natural-log units.
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


def _shape_number(v, where: str) -> float:
    if isinstance(v, bool):
        v = None
    try:
        x = float(v)
    except (TypeError, ValueError):
        x = float("nan")
    if not (math.isfinite(x) and x > 0):
        raise ConfigError(f"{where}: expected a positive finite number, got {v!r}")
    return x


def parse_tie_shape(value, tie, source: str = "inference", name: str = "tie_shape"):
    """Validate ``inference: {tie: shape, tie_shape: [s_1, ..., s_R]}`` (or the mapping
    ``{joint: s_j}``) without the tree: every entry a positive finite number (dimensionless,
    ``Kp_j = scale * s_j``), present exactly when ``tie`` is ``"shape"``.

    Returns:
        None (no shape), a tuple of floats (in the order of ``inference.joints``) or a dict
        ``{joint: float}``; :func:`resolve_tie_shape` aligns it with the inferred joints.
    Raises:
        ConfigError: naming ``{source}.{name}`` (and the entry) and what is wrong.
    """
    where = f"{source}.{name}" if source else name
    if value is None:
        if tie == "shape":
            raise ConfigError(
                f"{where}: 'tie: shape' needs the relative stiffness of every inferred joint, "
                "e.g. tie_shape: [1.0, 0.41, 0.12] (in the order of inference.joints) or "
                "{joint: value, ...}"
            )
        return None
    if tie != "shape":
        raise ConfigError(
            f"{where}: given with tie {tie!r}; an explicit stiffness shape needs 'tie: shape'"
        )
    if isinstance(value, Mapping):
        if not value:
            raise ConfigError(f"{where}: empty mapping; expected {{joint: value, ...}}")
        return {str(k): _shape_number(v, f"{where}.{k}") for k, v in value.items()}
    if isinstance(value, str):
        value = [v for v in value.replace(",", " ").split() if v]
    if not isinstance(value, (list, tuple, np.ndarray)) or len(value) == 0:
        raise ConfigError(
            f"{where}: expected a list of positive numbers, one per inferred joint, got {value!r}"
        )
    return tuple(_shape_number(v, f"{where}[{i}]") for i, v in enumerate(value))


def resolve_tie_shape(shape, joints, source: str = "inference", name: str = "tie_shape"):
    """:func:`parse_tie_shape`'s value aligned with the tree's inferred ``joints``.

    Returns:
        None or a tuple of R floats, one per joint of ``joints`` in that order.
    Raises:
        ConfigError: a list of the wrong length, or a mapping missing a joint or naming one
            that is not inferred.
    """
    where = f"{source}.{name}" if source else name
    if shape is None:
        return None
    joints = tuple(joints)
    if isinstance(shape, Mapping):
        unknown = sorted(set(shape) - set(joints))
        missing = [j for j in joints if j not in shape]
        if unknown or missing:
            raise ConfigError(
                f"{where}: needs one entry per inferred joint ({', '.join(joints)}); "
                + (f"not inferred: {unknown}" if unknown else f"missing: {missing}")
            )
        return tuple(float(shape[j]) for j in joints)
    vals = tuple(float(v) for v in shape)
    if len(vals) != len(joints):
        raise ConfigError(
            f"{where}: {len(vals)} value(s) for {len(joints)} inferred joint(s) "
            f"({', '.join(joints)}); give one per joint, in the order of inference.joints"
        )
    for i, v in enumerate(vals):
        _shape_number(v, f"{where}[{i}]")
    return vals
