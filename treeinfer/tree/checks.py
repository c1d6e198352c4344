"""Whole-tree checks used by :func:`treeinfer.tree.description.make_tree`: the branch list (names,
sizes, angles, gains, parent order, one root) and the stiffness tie's joint chain. Re-exported
by :mod:`treeinfer.tree.description`."""

from __future__ import annotations

from ..errors import TreeFileError
from .lump import check_lump
from .types import (
    _GENERATED_SUFFIXES,
    MAX_BRANCH_LENGTH,
    MAX_RADIUS,
    MIN_RADIUS,
    RESERVED_NAMES,
    Branch,
    Tree,
    _check_fraction,
    _density_in_range,
    _finite,
    _gain_in_range,
    _positive,
)


def check_tie(tree: Tree) -> None:
    """A taper tie needs two or more inferred joints along one stem (each joint an ancestor of
    the next): a stiffness profile along a taper means nothing across side branches.

    Raises:
        TreeFileError: naming ``inference.tie`` and what is wrong.
    """
    joints = list(tree.inferred)
    if len(joints) < 2:
        raise TreeFileError(
            f"inference.tie: '{tree.tie}' ties the stiffnesses of two or more joints along a stem; "
            f"this tree infers only {joints}; drop the tie or infer more joints (inference.levels)"
        )
    chain = sorted(joints, key=lambda n: len(tree.ancestors(n)))
    for lower, upper in zip(chain[:-1], chain[1:]):
        if lower not in tree.ancestors(upper):
            raise TreeFileError(
                f"inference.tie: '{tree.tie}' runs along one stem, but joints '{lower}' and "
                f"'{upper}' are on different branches (neither holds the other); infer one "
                "chain of joints (inference.joints) or drop the tie"
            )


def _validate_branches(branches: tuple[Branch, ...]) -> None:
    if not branches:
        raise TreeFileError("branches: the tree has no branches")
    from ..io.limits import check_tree_size, tree_depth

    check_tree_size(len(branches), 0)  # the count first: a huge tree is refused before its loop
    seen: set[str] = set()
    roots = 0
    for i, b in enumerate(branches):
        w = f"branches[{i}] ('{b.name}'): "
        if (
            not isinstance(b.name, str)
            or not b.name
            or not b.name.replace("_", "").replace("-", "").replace(".", "").isalnum()
        ):
            raise TreeFileError(
                f"branches[{i}].name: must be a non-empty name of letters, digits, '_', '-', "
                f"'.', got {b.name!r}"
            )
        if b.name in seen:
            raise TreeFileError(f"{w}duplicate branch name")
        if b.name.lower() in RESERVED_NAMES:
            raise TreeFileError(
                f"branches[{i}].name: '{b.name}' is reserved (MuJoCo's world body); rename the "
                "branch"
            )
        _positive(b.length, "length", w)
        _positive(b.radius, "radius", w)
        if b.length > MAX_BRANCH_LENGTH:
            raise TreeFileError(
                f"{w}length {b.length:g} m is longer than {MAX_BRANCH_LENGTH:g} m; "
                "looks like millimetres or centimetres, expected metres"
            )
        if not MIN_RADIUS <= b.radius <= MAX_RADIUS:
            raise TreeFileError(
                f"{w}radius {b.radius:g} m is outside [{MIN_RADIUS:g}, {MAX_RADIUS:g}] m; "
                + (
                    "looks like millimetres, expected metres"
                    if b.radius > MAX_RADIUS
                    else "too thin for a branch (check the unit)"
                )
            )
        if b.radius > b.length:
            raise TreeFileError(
                f"{w}radius {b.radius} m exceeds length {b.length} m (units mixed up?)"
            )
        _finite(b.angle_deg, "angle_deg", w)
        _finite(b.azimuth_deg, "azimuth_deg", w)
        _finite(b.twist_deg, "twist_deg", w)
        if b.lump is not None:
            check_lump(b.lump, w)
        _check_fraction(b.attach, "attach", w)
        if b.density is not None:
            _positive(b.density, "density", w)
            _density_in_range(b.density, "density", w)
        if b.kp is not None:
            _gain_in_range(_positive(b.kp, "kp", w), "kp", w)
        if b.kd is not None:
            _gain_in_range(_positive(b.kd, "kd", w), "kd", w)
        if b.parent is None:
            roots += 1
        elif b.parent not in seen:
            known = [x.name for x in branches]
            if b.parent in known:
                raise TreeFileError(f"{w}parent '{b.parent}' must be listed before its child")
            raise TreeFileError(f"{w}unknown parent '{b.parent}'; the tree has: {', '.join(known)}")
        seen.add(b.name)
    if roots != 1:
        raise TreeFileError(f"branches: exactly one root (parent: null) is required, found {roots}")
    # parents come before children (checked above): no cycle, the depth is well defined
    check_tree_size(len(branches), tree_depth({b.name: b.parent for b in branches}))
    names = {b.name for b in branches}
    for i, b in enumerate(branches):
        for suf in _GENERATED_SUFFIXES:
            if b.name.endswith(suf) and b.name[: -len(suf)] in names:
                raise TreeFileError(
                    f"branches[{i}].name: '{b.name}' clashes with the name generated for branch "
                    f"'{b.name[: -len(suf)]}' ({suf[1:]}); rename the branch"
                )
