"""Tree generators: explicit chains and branch lists, fractal trees and L-systems (the last in
:mod:`treeinfer.tree.lsystem`, re-exported here; shared argument checks in ``_generate``).

Every generator returns a validated :class:`~treeinfer.tree.description.Tree` (built with
:func:`~treeinfer.tree.description.make_tree`) and follows the frame convention of
:mod:`treeinfer.tree.description`: a branch frame has x along the branch and y along the hinge axis;
a child's frame sits ``attach * L_parent`` along its parent's x-axis, turned by ``rot_x(azimuth) @
rot_y(-angle)``.

Common keyword arguments of all generators:
  grasp / grasp_fraction: the grasped branch (generator-specific default) and where along it (0, 1].
  levels: how many jointed branches, from the grasped one up towards the root, are inferred
    (None: every one on that path).
  bounds: one :class:`~treeinfer.tree.description.Bounds` (or ``{"kp": [lo, hi], "kd": [lo, hi]}``)
  used for
    every inferred joint (None: the default prior box).
  name: the tree's name.
  **tree_kwargs: ``base_position``, ``base_pitch_deg``, ``base_yaw_deg``, ``gravity``, ``density``,
    ``fixed_kp``, ``fixed_kd`` (see :class:`~treeinfer.tree.description.Tree`).

Settings are recorded with :func:`describe` (a plain, YAML/JSON-ready dict ``{"kind": ..., ...}``
with every default filled in) and replayed with :func:`generate`; :func:`dump_generated` writes a
tree file whose ``generator:`` section holds those settings (the tree loader ignores it).
"""

from __future__ import annotations

import inspect
import json
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError, TreeFileError
from ._generate import (  # noqa: F401 -- re-exported: the old import path keeps working
    _as_bounds,
    _build,
    _check_tree_kwargs,
    _per_branch,
    _positive_float,
    _positive_int,
)
from .description import Bounds, Branch, Tree, tree_from_dict, tree_to_dict
from .lsystem import (  # noqa: F401 -- re-exported: the old import path keeps working
    MAX_LSYSTEM_LENGTH,
    Rules,
    TurtleSegment,
    interpret,
    lsystem,
    pipe_radii,
    rewrite,
)


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
    ``fixed``), validated exactly like a tree file
    (:func:`~treeinfer.tree.description.tree_from_dict`).

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

    from ..io.limits import check_tree_size

    # before growing: depth 25 of a binary fork is 2^26 - 1 branches, which would never finish
    check_tree_size(sum(branching**k for k in range(depth + 1)), depth + 1, where)
    branches: list[Branch] = []
    # depth-first, children in order (the names and order of the recursive walk this replaced),
    # with an explicit stack: a deep tree cannot reach Python's recursion limit
    stack: list[tuple[tuple[int, ...], str | None, float, float]] = [
        ((), None, base_length, base_radius)
    ]
    while stack:
        path, parent, length, radius = stack.pop()
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
            for c in reversed(range(branching)):
                stack.append((path + (c,), nm, length * length_ratio, radius * scale[c]))
    if grasp is None:
        grasp = fractal_name((0,) * depth, branching)
    return _build("fractal", branches, grasp, grasp_fraction, levels, bounds, name, tree_kwargs)


# ---- recorded settings --------------------------------------------------------------------------
# ---- (d) a plant stem pushed at a few heights ---------------------------------------------------
STEM_KP_BOUNDS = (0.05, 50.0)  # N m/rad: stems of a few mm to 2 cm, E of 0.1 to 20 GPa


def _stem_of(height, push_heights, base_diameter, tip_diameter, diameters, where):
    """The stem :func:`~treeinfer.tree.stem.matched_hinges` reads: a linear taper from
    base to tip, or a piecewise-linear profile through one diameter per push height (plus the
    base and tip diameters where given)."""
    from .stem import Stem, StemProfile

    h = _positive_float(height, "height", where)
    pushes = _per_branch(push_heights, len(np.atleast_1d(push_heights)), "push_heights", where)
    if not pushes or any(b <= a for a, b in zip(pushes[:-1], pushes[1:])):
        raise ConfigError(f"{where}: push_heights must increase, got {pushes}")
    if pushes[0] <= 0 or pushes[-1] > h:
        raise ConfigError(f"{where}: push_heights must lie in (0, height = {h:g}] m, got {pushes}")
    base = None if base_diameter is None else _positive_float(base_diameter, "base_diameter", where)
    tip = None if tip_diameter is None else _positive_float(tip_diameter, "tip_diameter", where)
    if diameters is None:
        if base is None or tip is None:
            raise ConfigError(
                f"{where}: give base_diameter and tip_diameter (a linear taper), or diameters "
                "(one per push height)"
            )
        return pushes, Stem(height=h, base_diameter=base, tip_diameter=tip)
    ds = _per_branch(diameters, len(pushes), "diameters (one per push height)", where)
    for d in ds:
        _positive_float(d, "diameters", where)
    zs, dd = list(pushes), list(ds)
    if base is not None:
        zs, dd = [0.0, *zs], [base, *dd]
    if tip is not None and h > zs[-1]:
        zs, dd = [*zs, h], [*dd, tip]
    return pushes, StemProfile(height=h, heights=tuple(zs), diameters=tuple(dd))


def stem(
    height: float,
    push_heights: Sequence[float],
    base_diameter: float | None = None,
    tip_diameter: float | None = None,
    diameters: Sequence[float] | None = None,
    *,
    gamma: float = 0.85,
    tie_scale: float | None = 0.1,
    bounds: Bounds | Mapping[str, Any] | None = None,
    name: str = "stem",
    direction: str | Sequence[float] = "horizontal",
    density: float = 900.0,
    base_position: Sequence[float] = (0.0, 0.0, 0.0),
    base_yaw_deg: float = 0.0,
) -> Tree:
    """A vertical hinge chain for a stem pushed at ``push_heights``: one hinge per push height
    at the pseudo-rigid-body pivot, stiffnesses tied to the shape that makes the chain's
    compliance the tapered beam's at every push height (one free scale;
    :func:`treeinfer.tree.stem.matched_hinges`), written as ``inference: {tie: shape,
    tie_shape: ..., tie_scale: ...}`` with stiffness only inferred (``parameters: [kp]``).

    Branches: a welded ``stub`` from the ground to the first pivot, then ``link0``...
    ``link{n-1}`` from pivot to pivot, the last up to ``height``; radii follow the diameter at
    each piece's middle. Grasped at the top push height. Push height ``h`` lies on the link
    :func:`stem_push_points` names, at its distance from that link's joint.

    Args:
      height: m, the stem from the ground (the clamp) to its tip.
      push_heights: m above the ground, increasing, in (0, height].
      base_diameter, tip_diameter: m, a linear taper; or ``diameters``: m, one per push height
        (piecewise linear between them, through the base/tip diameters where given).
      gamma: pseudo-rigid-body characteristic radius (Howell's 0.85).
      tie_scale: std of each hinge's log-stiffness about the shape (soft tie; 0.1: about 10%),
        or None for a hard tie.
      bounds: prior box of every hinge (default Kp in ``STEM_KP_BOUNDS`` N m/rad).
      direction: the data set's default pull direction (``pull: {direction: ...}``): pushes are
        sideways, ``horizontal`` by default.
      density: kg/m^3 of the stem.
    """
    from .stem import matched_hinges

    where = "stem()"
    pushes, beam = _stem_of(height, push_heights, base_diameter, tip_diameter, diameters, where)
    if not 0.0 < float(gamma) < 1.0:
        raise ConfigError(f"{where}: gamma must lie in (0, 1), got {gamma!r}")
    if tie_scale is not None:
        tie_scale = _positive_float(tie_scale, "tie_scale", where)
    z, shape = matched_hinges(beam, pushes, float(gamma))
    cuts = [0.0, *z.tolist(), float(beam.height)]
    branches, parent = [], None
    for k, (a, b) in enumerate(zip(cuts[:-1], cuts[1:])):
        bname = "stub" if k == 0 else f"link{k - 1}"
        r = float(beam.diameter((a + b) / 2)) / 2
        branches.append(Branch(bname, parent, b - a, r, fixed=k == 0))
        parent = bname
    top = f"link{len(z) - 1}"
    grasp_fraction = (pushes[-1] - float(z[-1])) / (cuts[-1] - cuts[-2])
    bounds = _as_bounds(bounds, where) or Bounds(kp=STEM_KP_BOUNDS)
    names = [f"link{k}" for k in range(len(z))]
    try:
        from .description import make_tree

        tree = make_tree(
            branches,
            grasp_branch=top,
            grasp_fraction=grasp_fraction,
            levels=len(z),
            bounds=bounds,
            name=str(name),
            base_position=tuple(float(v) for v in base_position),
            base_pitch_deg=90.0,
            base_yaw_deg=float(base_yaw_deg),
            density=float(density),
            pull_direction=direction,
            parameters=("kp",),
            tie="shape" if len(z) > 1 else None,
            tie_scale=tie_scale if len(z) > 1 else None,
            tie_shape=dict(zip(names, shape.tolist())) if len(z) > 1 else None,
        )
    except TreeFileError as e:
        raise ConfigError(f"{where}: the generated tree is invalid: {e}") from None
    return tree


def stem_push_points(tree: Tree, push_heights: Sequence[float]) -> list[tuple[float, str, float]]:
    """(height m, branch, distance m from its joint) of each push height on a vertical chain
    such as :func:`stem` builds: the ``--grasp-branch``/``--grasp-distance`` of ``import-csv``
    for the push at that height."""
    from .stem import branch_at_height

    return [(float(h), *branch_at_height(tree, float(h))) for h in push_heights]


GENERATORS: dict[str, Callable[..., Tree]] = {
    "chain": chain,
    "explicit": explicit,
    "fractal": fractal,
    "lsystem": lsystem,
    "stem": stem,
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
    from ..io.atomic import atomic_write_text

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
