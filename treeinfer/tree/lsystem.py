"""L-system trees (one of the :mod:`treeinfer.tree.generators`): rewrite an axiom with rules, walk
the result with a 3-D turtle (:func:`interpret`), size the branches by pipe-model radii
(:func:`pipe_radii`), and build the tree (:func:`lsystem`). Common keyword arguments as in
:mod:`treeinfer.tree.generators`, which re-exports every name here."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np

from ..errors import ConfigError
from ._generate import _build, _positive_float, _positive_int
from .description import Bounds, Branch, Tree, rot_x, rot_y, rot_z

# Longest L-system string we interpret; longer ones are almost always a runaway rule.
MAX_LSYSTEM_LENGTH = 1_000_000
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
