"""Helpers shared by the tree generators (:mod:`treeinfer.tree.generators`,
:mod:`treeinfer.tree.lsystem`): argument checks naming the generator, and the final
:func:`~treeinfer.tree.description.make_tree` call."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ..errors import ConfigError, TreeFileError, check_positive
from .description import Bounds, Branch, Tree, make_tree

_TREE_KWARGS = (
    "base_position",
    "base_pitch_deg",
    "base_yaw_deg",
    "gravity",
    "density",
    "fixed_kp",
    "fixed_kd",
)


# ---- shared helpers -----------------------------------------------------------------------------
def _as_bounds(bounds: Bounds | Mapping[str, Any] | None, where: str) -> Bounds | None:
    if bounds is None or isinstance(bounds, Bounds):
        return bounds
    if isinstance(bounds, Mapping) and set(bounds) <= {"kp", "kd"}:
        try:
            return Bounds(
                kp=tuple(float(x) for x in bounds.get("kp", Bounds().kp)),
                kd=tuple(float(x) for x in bounds.get("kd", Bounds().kd)),
            )
        except (TypeError, ValueError):
            pass
    raise ConfigError(
        f"{where}: bounds must be a Bounds or {{'kp': [lo, hi], 'kd': [lo, hi]}}, got {bounds!r}"
    )


def _check_tree_kwargs(tree_kwargs: Mapping[str, Any], where: str) -> dict[str, Any]:
    bad = sorted(set(tree_kwargs) - set(_TREE_KWARGS))
    if bad:
        raise ConfigError(
            f"{where}: unknown setting(s) {bad}; allowed tree settings: {list(_TREE_KWARGS)}"
        )
    out = dict(tree_kwargs)
    for k in ("base_position", "gravity"):
        if k in out:
            out[k] = tuple(float(x) for x in out[k])
    return out


def _per_branch(value: Any, n: int, fld: str, where: str) -> list[float]:
    """A scalar repeated ``n`` times, or a sequence of exactly ``n`` numbers."""
    try:
        vals = [float(value)] * n if np.ndim(value) == 0 else [float(v) for v in value]
    except (TypeError, ValueError):
        raise ConfigError(
            f"{where}: {fld} must be a number or a list of numbers, got {value!r}"
        ) from None
    if len(vals) != n:
        raise ConfigError(f"{where}: {fld} has {len(vals)} values, expected {n} (or one number)")
    if not all(math.isfinite(v) for v in vals):
        raise ConfigError(f"{where}: {fld} must be finite, got {value!r}")
    return vals


def _positive_int(v: Any, fld: str, where: str, minimum: int = 1) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < minimum:
        raise ConfigError(f"{where}: {fld} must be an integer >= {minimum}, got {v!r}")
    return int(v)


def _positive_float(v: Any, fld: str, where: str) -> float:
    return check_positive(v, f"{where}: {fld}")


def _path_levels(branches: Sequence[Branch], grasp: str) -> int:
    """Number of branches from ``grasp`` up to the root (enough to infer the whole path)."""
    by = {b.name: b for b in branches}
    n, cur = 0, by[grasp]
    while cur is not None:
        n += 1
        cur = by[cur.parent] if cur.parent is not None else None
    return n


def _build(
    kind: str,
    branches: list[Branch],
    grasp: str,
    grasp_fraction: float,
    levels: int | None,
    bounds: Bounds | Mapping[str, Any] | None,
    name: str,
    tree_kwargs: Mapping[str, Any],
) -> Tree:
    """make_tree with the generator's name in every error.

    (A bad generated tree is a bad setting.)"""
    where = f"{kind}()"
    bounds = _as_bounds(bounds, where)
    tree_kwargs = _check_tree_kwargs(tree_kwargs, where)
    names = {b.name for b in branches}
    if grasp not in names:
        raise ConfigError(
            f"{where}: grasp: unknown branch '{grasp}'; generated branches: "
            f"{', '.join(sorted(names))}"
        )
    if levels is None:
        levels = _path_levels(branches, grasp)
    try:
        return make_tree(
            branches,
            grasp_branch=grasp,
            grasp_fraction=grasp_fraction,
            levels=levels,
            bounds=bounds,
            name=str(name),
            **tree_kwargs,
        )
    except TreeFileError as e:
        raise ConfigError(f"{where}: the generated tree is invalid: {e}") from None
