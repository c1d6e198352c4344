"""Tree generators: explicit chains and branch lists, fractal trees and L-systems.

Every generator returns a validated :class:`~treeinfer.tree.Tree` (built with
:func:`~treeinfer.tree.make_tree`) and follows the frame convention of :mod:`treeinfer.tree`:
a branch frame has x along the branch and y along the hinge axis; a child's frame sits
``attach * L_parent`` along its parent's x-axis, turned by ``rot_x(azimuth) @ rot_y(-angle)``.

Common keyword arguments of all generators:
  grasp / grasp_fraction: the grasped branch (generator-specific default) and where along it (0, 1].
  levels: how many jointed branches, from the grasped one up towards the root, are inferred
    (None: every one on that path).
  bounds: one :class:`~treeinfer.tree.Bounds` (or ``{"kp": [lo, hi], "kd": [lo, hi]}``) used for
    every inferred joint (None: the default prior box).
  name: the tree's name.
  **tree_kwargs: ``base_position``, ``base_pitch_deg``, ``base_yaw_deg``, ``gravity``, ``density``,
    ``fixed_kp``, ``fixed_kd`` (see :class:`~treeinfer.tree.Tree`).

Settings are recorded with :func:`describe` (a plain, YAML/JSON-ready dict ``{"kind": ..., ...}``
with every default filled in) and replayed with :func:`generate`; :func:`dump_generated` writes a
tree file whose ``generator:`` section holds those settings (the tree loader ignores it).
"""

from __future__ import annotations

import inspect
import json
import math
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from .errors import ConfigError, TreeFileError
from .tree import Bounds, Branch, Tree, make_tree, rot_x, rot_y, rot_z, tree_from_dict, tree_to_dict

_TREE_KWARGS = (
    "base_position",
    "base_pitch_deg",
    "base_yaw_deg",
    "gravity",
    "density",
    "fixed_kp",
    "fixed_kd",
)
# Longest L-system string we interpret; longer ones are almost always a runaway rule.
MAX_LSYSTEM_LENGTH = 1_000_000


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
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: {fld} must be a positive number, got {v!r}") from None
    if not (math.isfinite(f) and f > 0):
        raise ConfigError(f"{where}: {fld} must be a finite positive number, got {v!r}")
    return f


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


# ---- (a) explicit chains and branch lists -------------------------------------------------------
def chain(
    n: int,
    lengths: float | Sequence[float],
    radii: float | Sequence[float],
    angles_deg: float | Sequence[float] = 0.0,
    azimuths_deg: float | Sequence[float] = 0.0,
    *,
    names: Sequence[str] | None = None,
    grasp_fraction: float = 1.0,
    levels: int | None = None,
    bounds: Bounds | Mapping[str, Any] | None = None,
    name: str = "chain",
    **tree_kwargs: Any,
) -> Tree:
    """A chain ``branch0 -> branch1 -> ... -> branch{n-1}``, grasped on the last branch.

    Args:
      n: number of branches.
      lengths, radii: m, one number for all or one per branch (root first).
      angles_deg, azimuths_deg: deg, each branch's fork angle / bending-plane rotation relative to
        its parent (the root's: relative to the base direction); one number or one per branch.
      names: branch names (default ``branch0``, ``branch1``, ...).
      levels: inferred joints from the tip up (None: all n).
    """
    where = "chain()"
    n = _positive_int(n, "n", where)
    ls = _per_branch(lengths, n, "lengths", where)
    rs = _per_branch(radii, n, "radii", where)
    an = _per_branch(angles_deg, n, "angles_deg", where)
    az = _per_branch(azimuths_deg, n, "azimuths_deg", where)
    names = [f"branch{i}" for i in range(n)] if names is None else [str(s) for s in names]
    if len(names) != n:
        raise ConfigError(f"{where}: names has {len(names)} entries, expected {n}")
    branches = [
        Branch(
            name=names[i],
            parent=None if i == 0 else names[i - 1],
            length=ls[i],
            radius=rs[i],
            angle_deg=an[i],
            azimuth_deg=az[i],
        )
        for i in range(n)
    ]
    return _build("chain", branches, names[-1], grasp_fraction, levels, bounds, name, tree_kwargs)


def explicit(
    branches: Sequence[Mapping[str, Any]],
    *,
    grasp: str | None = None,
    grasp_fraction: float = 1.0,
    levels: int | None = None,
    inferred: Sequence[str] | None = None,
    bounds: Bounds | Mapping[str, Any] | None = None,
    name: str = "tree",
    **tree_kwargs: Any,
) -> Tree:
    """A tree from branch dicts with the tree file's branch fields (``name``, ``parent``,
    ``length``, ``radius``, ``angle_deg``, ``azimuth_deg``, ``attach``, ``density``, ``kp``, ``kd``,
    ``fixed``), validated exactly like a tree file (:func:`~treeinfer.tree.tree_from_dict`).

    Args:
      grasp: the grasped branch (default: the last one listed).
      inferred: explicit list of inferred joints (overrides ``levels``).
    Raises:
      TreeFileError: a branch dict is malformed, naming ``explicit()`` and the field.
    """
    where = "explicit()"
    if not isinstance(branches, Sequence) or not branches:
        raise TreeFileError(f"{where}: branches: expected a non-empty list of branch dicts")
    branches = [dict(b) if isinstance(b, Mapping) else b for b in branches]
    bounds = _as_bounds(bounds, where)
    tkw = _check_tree_kwargs(tree_kwargs, where)
    if grasp is None:
        grasp = branches[-1].get("name") if isinstance(branches[-1], dict) else None
    d: dict[str, Any] = {
        "name": name,
        "branches": branches,
        "grasp": {"branch": grasp, "fraction": grasp_fraction},
    }
    inf: dict[str, Any] = {}
    if inferred is not None:
        inf["joints"] = list(inferred)
    elif levels is not None:
        inf["levels"] = levels
    else:
        inf["levels"] = len(branches)  # default_inferred stops at the root: the whole path
    if bounds is not None:
        inf["prior"] = {"kp": list(bounds.kp), "kd": list(bounds.kd)}
    d["inference"] = inf
    base = {k[5:]: tkw[k] for k in ("base_position", "base_pitch_deg", "base_yaw_deg") if k in tkw}
    if base:
        d["base"] = {k: (list(v) if k == "position" else v) for k, v in base.items()}
    if "gravity" in tkw:
        d["gravity"] = list(tkw["gravity"])
    if "density" in tkw:
        d["density"] = tkw["density"]
    fixed = {k[6:]: tkw[k] for k in ("fixed_kp", "fixed_kd") if k in tkw}
    if fixed:
        d["fixed"] = fixed
    return tree_from_dict(d, source=where)


# ---- (b) fractal trees --------------------------------------------------------------------------
def fractal_name(path: Sequence[int], branching: int) -> str:
    """Name of the branch reached from the root by the child indices ``path``.

    ``b`` is the root, ``b0``/``b1`` its children, ``b01`` the second child of the first child,
    and so on; with more than 10 children per fork the indices are separated: ``b_0_12``.
    """
    if branching <= 10:
        return "b" + "".join(str(i) for i in path)
    return "b" + "".join(f"_{i}" for i in path)


def fractal(
    depth: int = 2,
    branching: int = 2,
    length_ratio: float = 0.7,
    fork_angles_deg: Sequence[float] | None = None,
    azimuths_deg: Sequence[float] | None = None,
    base_length: float = 1.0,
    base_radius: float = 0.04,
    da_vinci_exponent: float = 2.0,
    area_fractions: Sequence[float] | None = None,
    *,
    grasp: str | None = None,
    grasp_fraction: float = 1.0,
    levels: int | None = None,
    bounds: Bounds | Mapping[str, Any] | None = None,
    name: str = "fractal",
    **tree_kwargs: Any,
) -> Tree:
    """A self-similar tree: every branch above level ``depth`` forks into ``branching`` children.

    The root is level 0; a tree of depth ``d`` has ``sum(branching**k for k in 0..d)`` branches,
    listed depth-first (parents before children) and named by :func:`fractal_name`.

    Geometry (level k): length ``base_length * length_ratio**k``. Child ``i`` of every fork turns by
    ``fork_angles_deg[i]`` in a bending plane rotated by ``azimuths_deg[i]`` about the parent.
    Radii follow Leonardo da Vinci's rule: ``r_parent**e == sum(r_child**e)`` with
    ``e = da_vinci_exponent`` (2: the parent's cross-section area equals the children's total),
    child ``i`` taking the fraction ``area_fractions[i]`` of it, so
    ``r_i = r_parent * area_fractions[i]**(1/e)``.

    Args:
      depth: number of fork levels (0: a single branch).
      branching: children per fork.
      length_ratio: child length / parent length.
      fork_angles_deg: deg, one per child (default: (30, -30) for two children; otherwise evenly
        spread from +30 to -30; 0 for one child).
      azimuths_deg: deg, one per child (default: all 0, a planar tree).
      base_length, base_radius: m, the root branch.
      da_vinci_exponent: the exponent e above (> 0).
      area_fractions: positive, one per child, summing to 1 (default: equal, 1/branching).
      grasp: grasped branch (default: the leftmost leaf ``b00...0``, reached through child 0).
      levels: inferred joints from the grasped leaf up (default: all ``depth + 1`` on the path).
    """
    where = "fractal()"
    depth = _positive_int(depth, "depth", where, minimum=0)
    branching = _positive_int(branching, "branching", where)
    length_ratio = _positive_float(length_ratio, "length_ratio", where)
    base_length = _positive_float(base_length, "base_length", where)
    base_radius = _positive_float(base_radius, "base_radius", where)
    expo = _positive_float(da_vinci_exponent, "da_vinci_exponent", where)
    if fork_angles_deg is None:
        fork_angles_deg = [0.0] if branching == 1 else list(np.linspace(30.0, -30.0, branching))
    angles = _per_branch(fork_angles_deg, branching, "fork_angles_deg", where)
    azims = _per_branch(
        0.0 if azimuths_deg is None else azimuths_deg, branching, "azimuths_deg", where
    )
    if area_fractions is None:
        fracs = [1.0 / branching] * branching
    else:
        fracs = _per_branch(area_fractions, branching, "area_fractions", where)
        if min(fracs) <= 0 or abs(sum(fracs) - 1.0) > 1e-9:
            raise ConfigError(
                f"{where}: area_fractions must be positive and sum to 1, got {list(area_fractions)}"
            )
    scale = [f ** (1.0 / expo) for f in fracs]

    branches: list[Branch] = []

    def grow(path: tuple[int, ...], parent: str | None, length: float, radius: float) -> None:
        i = path[-1] if path else None
        nm = fractal_name(path, branching)
        branches.append(
            Branch(
                name=nm,
                parent=parent,
                length=length,
                radius=radius,
                angle_deg=0.0 if i is None else angles[i],
                azimuth_deg=0.0 if i is None else azims[i],
            )
        )
        if len(path) < depth:
            for c in range(branching):
                grow(path + (c,), nm, length * length_ratio, radius * scale[c])

    grow((), None, base_length, base_radius)
    if grasp is None:
        grasp = fractal_name((0,) * depth, branching)
    return _build("fractal", branches, grasp, grasp_fraction, levels, bounds, name, tree_kwargs)


# ---- (c) L-systems ------------------------------------------------------------------------------
Rules = Mapping[str, "str | Sequence[tuple[float, str]]"]


def _normalise_rules(rules: Rules) -> dict[str, tuple[np.ndarray, list[str]]]:
    """{symbol: (cumulative probabilities, successors)}; deterministic rules have one successor."""
    if not isinstance(rules, Mapping):
        raise ConfigError(f"lsystem: rules must be a mapping {{symbol: successor}}, got {rules!r}")
    out = {}
    for sym, succ in rules.items():
        if not isinstance(sym, str) or len(sym) != 1:
            raise ConfigError(f"lsystem: rules: each key must be one symbol, got {sym!r}")
        if isinstance(succ, str):
            out[sym] = (np.array([1.0]), [succ])
            continue
        try:
            probs = [float(p) for p, _ in succ]
            words = [str(s) if isinstance(s, str) else None for _, s in succ]
        except (TypeError, ValueError):
            raise ConfigError(
                f"lsystem: rules['{sym}']: expected a string or a list of (probability, string), "
                f"got {succ!r}"
            ) from None
        if not probs or None in words:
            raise ConfigError(
                f"lsystem: rules['{sym}']: expected a list of (probability, string), got {succ!r}"
            )
        if min(probs) < 0 or abs(sum(probs) - 1.0) > 1e-9:
            raise ConfigError(
                f"lsystem: rules['{sym}']: probabilities must be >= 0 and sum to 1, got {probs}"
            )
        cum = np.cumsum(probs)
        cum[-1] = 1.0
        out[sym] = (cum, words)
    return out


def rewrite(
    axiom: str, rules: Rules, iterations: int, rng: np.random.Generator | int | None = None
) -> str:
    """Apply the L-system ``rules`` to ``axiom`` ``iterations`` times, all symbols in parallel.

    Args:
      rules: ``{symbol: successor}`` (deterministic) or ``{symbol: [(p, successor), ...]}``
        (stochastic: each occurrence independently picks a successor with probability p; the p's
        sum to 1). Symbols without a rule are copied unchanged.
      rng: a numpy Generator or seed; one uniform draw per occurrence of a stochastic symbol, in
        reading order, so a seed reproduces the string exactly. Required only for stochastic rules.
    """
    if not isinstance(axiom, str):
        raise ConfigError(f"lsystem: axiom must be a string, got {axiom!r}")
    iterations = _positive_int(iterations, "iterations", "lsystem", minimum=0)
    table = _normalise_rules(rules)
    if any(len(w) > 1 for _, w in table.values()):
        if rng is None:
            raise ConfigError("lsystem: stochastic rules need a seed (rng)")
        rng = np.random.default_rng(rng)
    s = axiom
    for _ in range(iterations):
        parts = []
        for ch in s:
            rule = table.get(ch)
            if rule is None:
                parts.append(ch)
            elif len(rule[1]) == 1:
                parts.append(rule[1][0])
            else:
                parts.append(rule[1][int(np.searchsorted(rule[0], rng.random(), side="right"))])
        s = "".join(parts)
        if len(s) > MAX_LSYSTEM_LENGTH:
            raise ConfigError(
                f"lsystem: the string grew beyond {MAX_LSYSTEM_LENGTH} symbols; use fewer "
                "iterations"
            )
    return s


class TurtleSegment(NamedTuple):
    """One branch drawn by the turtle (radius comes later, from :func:`pipe_radii`).

    ``start`` [3] (m) and ``rotation`` [3,3] are the branch frame in the base frame."""

    name: str
    parent: str | None
    length: float
    angle_deg: float
    azimuth_deg: float
    attach: float
    start: np.ndarray
    rotation: np.ndarray


def _fork_angles(r_rel: np.ndarray) -> tuple[float, float]:
    """(azimuth, angle) in rad with ``rot_x(az) @ rot_y(-angle)`` pointing the x-axis like
    ``r_rel``; |azimuth| <= pi/2 where the direction allows, pure rolls go into the azimuth.

    The turtle's remaining roll about the new branch axis cannot be stored in the tree model (one
    hinge per branch): it only decides this branch's hinge axis, and the children's azimuths,
    computed against the stored frame, absorb it, so every branch still points where the turtle
    drew.
    """
    h = r_rel[:, 0]
    sin_b = math.hypot(h[1], h[2])
    if sin_b < 1e-12:  # straight on (or straight back): no bending plane; keep the turtle's roll
        az = math.atan2(r_rel[2, 1], r_rel[1, 1]) if h[0] > 0 else 0.0
        return az, (0.0 if h[0] > 0 else math.pi)
    # heading of rot_x(a) @ rot_y(-b) @ e_x is (cos b, -sin a sin b, cos a sin b)
    az, ang = math.atan2(-h[1], h[2]), math.atan2(sin_b, h[0])
    if abs(az) > math.pi / 2 + 1e-12:
        az, ang = az - math.copysign(math.pi, az), -ang
    return az, ang


def interpret(
    commands: str,
    angle_deg: float,
    step_length: float,
    length_ratio: float = 1.0,
    merge_segments: bool = True,
    draw_symbols: str = "F",
    prefix: str = "s",
) -> list[TurtleSegment]:
    """Turtle interpretation of an L-system string into branches (parents before children).

    The turtle starts at the base with the base frame's orientation (x = heading, y = the hinge
    axis, z completes it) and reads:

    - a symbol in ``draw_symbols`` (``F``): draw forward by ``step_length * length_ratio**d``, where
      d is the current bracket depth;
    - ``+`` / ``-``: turn up / down in the bending plane by ``angle_deg`` (about the turtle's
      y-axis; ``+`` matches a positive ``angle_deg`` of the tree model);
    - ``&`` / ``^``: turn out of the bending plane, towards +y / -y (about the turtle's z-axis);
    - ``/`` / ``\\``: roll about the heading by +/- ``angle_deg`` (this rotates the bending plane of
      the branches drawn next: their azimuth); ``|``: turn around (180 deg about y);
    - ``[`` / ``]``: push / pop the turtle (position on its branch, orientation, depth);
    - any other symbol: ignored.

    A new branch starts wherever the turtle draws and cannot extend the branch it is on: after a
    turn, after a ``]`` that returns it part-way along a branch, and, with
    ``merge_segments=False``, at every drawn segment. With ``merge_segments=True`` straight runs
    are one branch even when side branches fork off in between; those attach part-way along
    (``attach = fork distance / branch length`` in (0, 1]).

    Raises:
      ConfigError: unbalanced brackets, nothing drawn, or a second root (drawing again from the
        base after a ``]`` returned the turtle there).
    """
    delta = math.radians(float(angle_deg))
    step_length = _positive_float(step_length, "step_length", "lsystem")
    length_ratio = _positive_float(length_ratio, "length_ratio", "lsystem")
    turns = {
        "+": rot_y(-delta),
        "-": rot_y(delta),
        "&": rot_z(delta),
        "^": rot_z(-delta),
        "/": rot_x(delta),
        "\\": rot_x(-delta),
        "|": rot_y(math.pi),
    }
    # nodes: name, parent index, length, start, branch frame, (az, angle), fork distance on parent
    nodes: list[dict[str, Any]] = []
    cur, dist, heading, stack = None, 0.0, np.eye(3), []
    for pos, ch in enumerate(commands):
        if ch in draw_symbols:
            step = step_length * length_ratio ** len(stack)
            node = nodes[cur] if cur is not None else None
            if (
                merge_segments
                and node is not None
                and dist == node["length"]
                and np.linalg.norm(heading[:, 0] - node["rotation"][:, 0]) < 1e-9
            ):
                node["length"] += step
                dist = node["length"]
                continue
            if node is None and nodes:
                raise ConfigError(
                    f"lsystem: symbol {pos} ('{ch}') draws a second root from the base"
                )
            if node is None:
                start, parent_rot = np.zeros(3), np.eye(3)
            else:
                start, parent_rot = node["start"] + node["rotation"][:, 0] * dist, node["rotation"]
            az, ang = _fork_angles(parent_rot.T @ heading)
            nodes.append(
                {
                    "parent": cur,
                    "length": step,
                    "start": start,
                    "fork": dist,
                    "az": az,
                    "ang": ang,
                    "rotation": parent_rot @ rot_x(az) @ rot_y(-ang),
                }
            )
            cur, dist = len(nodes) - 1, step
        elif ch in turns:
            heading = heading @ turns[ch]
        elif ch == "[":
            stack.append((cur, dist, heading))
        elif ch == "]":
            if not stack:
                raise ConfigError(f"lsystem: symbol {pos}: ']' without a matching '['")
            cur, dist, heading = stack.pop()
    if stack:
        raise ConfigError(f"lsystem: {len(stack)} '[' without a matching ']'")
    if not nodes:
        raise ConfigError(
            f"lsystem: the string draws nothing (no symbol from '{draw_symbols}'): "
            f"{commands[:80]!r}"
        )
    names = [f"{prefix}{i}" for i in range(len(nodes))]
    out = []
    for i, nd in enumerate(nodes):
        p = nd["parent"]
        if p is None:
            attach = 1.0
        else:
            # float sums: a fork at the parent's tip is exactly 1, never slightly above
            attach = nd["fork"] / nodes[p]["length"]
            attach = 1.0 if math.isclose(attach, 1.0, rel_tol=1e-12) else min(attach, 1.0)
        out.append(
            TurtleSegment(
                name=names[i],
                parent=None if p is None else names[p],
                length=nd["length"],
                angle_deg=math.degrees(nd["ang"]) + 0.0,
                azimuth_deg=math.degrees(nd["az"]) + 0.0,  # no -0.0
                attach=attach,
                start=nd["start"],
                rotation=nd["rotation"],
            )
        )
    return out


def pipe_radii(
    segments: Sequence[TurtleSegment],
    leaf_radius: float | None = None,
    base_radius: float | None = None,
    exponent: float = 2.0,
) -> list[float]:
    """Branch radii from Leonardo da Vinci's rule (the pipe model), bottom-up.

    Every free tip (a branch with no child at its tip, ``attach == 1``) carries ``leaf_radius``;
    a branch's radius is its base cross-section, ``r**e = sum(r_child**e) + (leaf_radius**e if
    its tip is free)``, with ``e = exponent`` (2: areas add up). Give ``base_radius`` instead to
    scale all radii so that the root has it (top-down: equivalent to a leaf radius of
    ``base_radius / n_tips**(1/e)``).
    """
    if (leaf_radius is None) == (base_radius is None):
        raise ConfigError("lsystem: give exactly one of leaf_radius and base_radius")
    e = _positive_float(exponent, "da_vinci_exponent", "lsystem")
    idx = {s.name: i for i, s in enumerate(segments)}
    pipes = np.zeros(len(segments))  # r**e in units of leaf_radius**e (= number of free tips)
    tip_taken = [False] * len(segments)
    for s in segments:
        if s.parent is not None and s.attach == 1.0:
            tip_taken[idx[s.parent]] = True
    for i in range(len(segments) - 1, -1, -1):  # children come after their parents
        pipes[i] += 0.0 if tip_taken[i] else 1.0
        if segments[i].parent is not None:
            pipes[idx[segments[i].parent]] += pipes[i]
    if leaf_radius is None:
        leaf_radius = _positive_float(base_radius, "base_radius", "lsystem") / pipes[0] ** (1.0 / e)
    leaf_radius = _positive_float(leaf_radius, "leaf_radius", "lsystem")
    return [float(leaf_radius * p ** (1.0 / e)) for p in pipes]


def lsystem(
    axiom: str,
    rules: Rules,
    iterations: int,
    angle_deg: float = 25.0,
    step_length: float = 0.3,
    length_ratio: float = 1.0,
    base_radius: float | None = 0.04,
    leaf_radius: float | None = None,
    da_vinci_exponent: float = 2.0,
    seed: int | None = 0,
    merge_segments: bool = True,
    draw_symbols: str = "F",
    *,
    grasp: str | None = None,
    grasp_fraction: float = 1.0,
    levels: int | None = None,
    bounds: Bounds | Mapping[str, Any] | None = None,
    name: str = "lsystem",
    **tree_kwargs: Any,
) -> Tree:
    """A tree grown by an L-system: :func:`rewrite`, :func:`interpret`, then :func:`pipe_radii`.

    Branches are named ``s0`` (the root), ``s1``, ... in drawing order.

    Args:
      axiom, rules, iterations: the L-system (see :func:`rewrite`).
      angle_deg: deg, the turtle's turn per ``+ - & ^ / \\``.
      step_length: m, one ``F`` at bracket depth 0; ``length_ratio`` scales it per bracket depth.
      base_radius / leaf_radius: m, give one (``leaf_radius`` wins when both are set): the root's
        radius (top-down) or every free tip's (bottom-up), see :func:`pipe_radii`.
      seed: seed of the numpy Generator for stochastic rules (default 0: reproducible).
      merge_segments: merge straight runs of ``F`` into one branch (see :func:`interpret`).
      grasp: grasped branch (default: the leaf whose tip is farthest from the base).
      levels: inferred joints from the grasped branch up (default: every one on the path).
    """
    s = rewrite(axiom, rules, iterations, seed)
    segs = interpret(s, angle_deg, step_length, length_ratio, bool(merge_segments), draw_symbols)
    if leaf_radius is not None:
        radii = pipe_radii(segs, leaf_radius=leaf_radius, exponent=da_vinci_exponent)
    else:
        radii = pipe_radii(segs, base_radius=base_radius, exponent=da_vinci_exponent)
    branches = [
        Branch(
            name=g.name,
            parent=g.parent,
            length=g.length,
            radius=r,
            angle_deg=g.angle_deg,
            azimuth_deg=g.azimuth_deg,
            attach=g.attach,
        )
        for g, r in zip(segs, radii)
    ]
    if grasp is None:
        parents = {g.parent for g in segs}
        leaves = [g for g in segs if g.name not in parents]
        tips = [np.linalg.norm(g.start + g.rotation[:, 0] * g.length) for g in leaves]
        grasp = leaves[int(np.argmax(tips))].name
    try:
        return _build("lsystem", branches, grasp, grasp_fraction, levels, bounds, name, tree_kwargs)
    except ConfigError as e:
        if "radius" in str(e):
            raise ConfigError(
                f"{e} (hint: lsystem radii follow the pipe model; use a smaller "
                "base_radius/leaf_radius, a longer step_length or merge_segments=True)"
            ) from None
        raise


# ---- recorded settings --------------------------------------------------------------------------
GENERATORS: dict[str, Callable[..., Tree]] = {
    "chain": chain,
    "explicit": explicit,
    "fractal": fractal,
    "lsystem": lsystem,
}


def _plain(v: Any) -> Any:
    """YAML/JSON-ready copy: tuples -> lists, numpy -> Python, Bounds -> dict."""
    if isinstance(v, Bounds):
        return {"kp": [float(x) for x in v.kp], "kd": [float(x) for x in v.kd]}
    if isinstance(v, Mapping):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple, np.ndarray)):
        return [_plain(x) for x in v]
    if isinstance(v, np.generic):
        return v.item()
    return v


def describe(kind: str, **settings: Any) -> dict[str, Any]:
    """The full settings of generator ``kind`` called with ``settings``, defaults filled in, as a
    plain dict ``{"kind": kind, ...}`` that :func:`generate` turns back into the same tree."""
    if kind not in GENERATORS:
        raise ConfigError(f"generator: unknown kind '{kind}'; choose one of {sorted(GENERATORS)}")
    sig = inspect.signature(GENERATORS[kind])
    try:
        bound = sig.bind(**settings)
    except TypeError as e:
        raise ConfigError(f"generator '{kind}': {e}") from None
    bound.apply_defaults()
    cfg: dict[str, Any] = {"kind": kind}
    for k, v in bound.arguments.items():
        if sig.parameters[k].kind is inspect.Parameter.VAR_KEYWORD:
            cfg.update(v)
        else:
            cfg[k] = v
    return _plain(cfg)


def generate(config: Mapping[str, Any]) -> Tree:
    """Build the tree that ``config`` (from :func:`describe` or a file's ``generator:`` section)
    describes."""
    if not isinstance(config, Mapping) or "kind" not in config:
        raise ConfigError(
            f"generator: expected a mapping with a 'kind' ({sorted(GENERATORS)}), got {config!r}"
        )
    settings = dict(config)
    kind = settings.pop("kind")
    if kind not in GENERATORS:
        raise ConfigError(f"generator: unknown kind '{kind}'; choose one of {sorted(GENERATORS)}")
    try:
        inspect.signature(GENERATORS[kind]).bind(**settings)
    except TypeError as e:
        raise ConfigError(f"generator '{kind}': {e}") from None
    return GENERATORS[kind](**settings)


def dump_generated(config: Mapping[str, Any], path: str | Path, comment: str | None = None) -> Tree:
    """Generate the tree of ``config`` and write it (YAML, or JSON by suffix) atomically, with the
    settings under ``generator:``; returns the tree. ``load_tree`` reads the file back as usual.
    ``comment``: text for a ``#`` header (YAML only)."""
    from ._io import atomic_write_text

    config = _plain(dict(config))
    tree = generate(config)
    d = {**tree_to_dict(tree), "generator": config}
    path = Path(path)
    if path.suffix.lower() == ".json":
        text = json.dumps(d, indent=2) + "\n"
    else:
        import yaml

        text = yaml.safe_dump(d, sort_keys=False)
        if comment:
            text = "".join(f"# {line}\n" for line in comment.splitlines()) + text
    atomic_write_text(path, text)
    return tree
