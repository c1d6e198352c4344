"""Tree descriptions: branches, the grasp point, which joints are inferred, and their prior boxes.

A tree is a set of cylindrical branches, each hinged to its parent by one revolute joint at
its base that acts as a torsional spring-damper ``T = Kp * psi + Kd * psi_dot`` about the
branch's geometric rest angle (the paper's PD controller with zero target).

Frames. Every branch has a frame whose origin is its joint, whose x-axis runs along the
branch and whose y-axis is the hinge axis. The root's frame is the base pose: ``base.position``
and a direction given by ``base.pitch_deg`` (elevation above horizontal; 90 = vertical trunk)
and ``base.yaw_deg`` (heading about the world z-axis). A child's frame sits ``attach`` (a
fraction of the parent's length, default 1 = the tip) along its parent, turned by ``azimuth_deg``
about the parent's x-axis (which plane it forks in; 0 keeps the parent's bending plane) and then
by ``angle_deg`` about the new y-axis (positive = upward when the bending plane is vertical),
and last by ``twist_deg`` (default 0) about its own x-axis, which turns its hinge across it. A
branch's ``lump`` is mass welded into its body (:mod:`treeinfer.tree.lump`).

The file format (YAML or JSON) is documented in the README; :func:`load_tree` reads it and
:func:`tree_to_dict` writes it back.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError, TreeFileError
from ..io.safe_load import load_file, string
from .checks import _validate_branches, check_tie  # noqa: F401 -- re-exported
from .lump import parse_lump
from .types import (  # noqa: F401 -- re-exported: the old import path keeps working
    _GENERATED_SUFFIXES,
    DEFAULT_DENSITY,
    DEFAULT_FIXED_KD,
    DEFAULT_FIXED_KP,
    DEFAULT_KD_BOUNDS,
    DEFAULT_KP_BOUNDS,
    DENSITY_RANGE,
    DIRECTION_WORDS,
    KD_RANGE,
    KP_RANGE,
    MAX_BRANCH_LENGTH,
    MAX_RADIUS,
    MIN_INERTIA,
    MIN_MASS,
    MIN_RADIUS,
    PARAMETERS,
    RESERVED_NAMES,
    WARN_BRANCH_LENGTH,
    Bounds,
    Branch,
    Tree,
    _bounds_pair,
    _check_fraction,
    _check_masses,
    _density_in_range,
    _finite,
    _gain_in_range,
    _positive,
    base_rotation,
    branch_density,
    cylinder_inertia,
    local_offset,
    local_rotation,
    parse_direction,
    parse_parameters,
    parse_tie,
    parse_tie_shape,
    parse_tree_pull,
    quat_from_matrix,
    resolve_tie_shape,
    rot_x,
    rot_y,
    rot_z,
    tree_scale_warnings,
    tree_to_dict,
    world_frames,
)


def default_inferred(branches: Iterable[Branch], grasp_branch: str, levels: int) -> tuple[str, ...]:
    """The chain from the grasped branch up ``levels`` jointed branches (fixed ones skipped)."""
    by = {b.name: b for b in branches}
    out, cur = [], by[grasp_branch]
    while cur is not None and len(out) < levels:
        if not cur.fixed:
            out.append(cur.name)
        cur = by[cur.parent] if cur.parent is not None else None
    return tuple(out)


def make_tree(
    branches: Iterable[Branch],
    grasp_branch: str,
    grasp_fraction: float = 1.0,
    inferred: Iterable[str] | None = None,
    levels: int = 1,
    bounds: dict[str, Bounds] | Bounds | None = None,
    name: str = "tree",
    **kwargs: Any,
) -> Tree:
    """Validate and build a :class:`Tree`. ``inferred`` defaults to the chain from the grasped
    branch up ``levels`` joints; ``bounds`` may be one :class:`Bounds` for every inferred joint."""
    branches = tuple(branches)
    _validate_branches(branches)
    names = [b.name for b in branches]
    if grasp_branch not in names:
        raise TreeFileError(
            f"grasp.branch: unknown branch '{grasp_branch}'; the tree has: {', '.join(names)}"
        )
    grasp_fraction = _check_fraction(grasp_fraction, "grasp.fraction")
    if inferred is None:
        if not isinstance(levels, int) or levels < 1:
            raise TreeFileError(f"inference.levels: must be a positive integer, got {levels!r}")
        inferred = default_inferred(branches, grasp_branch, levels)
    inferred = tuple(inferred)
    if not inferred:
        raise TreeFileError(
            "inference.joints: no joint to infer (every branch on the chain is fixed?)"
        )
    for n in inferred:
        if n not in names:
            raise TreeFileError(
                f"inference.joints: unknown branch '{n}'; the tree has: {', '.join(names)}"
            )
        if next(b for b in branches if b.name == n).fixed:
            raise TreeFileError(
                f"inference.joints: branch '{n}' is fixed (welded) and has no joint to infer"
            )
    if len(set(inferred)) != len(inferred):
        raise TreeFileError(f"inference.joints: duplicate names in {list(inferred)}")
    if bounds is None:
        bounds = Bounds()
    if isinstance(bounds, Bounds):
        bounds = {n: bounds for n in inferred}
    missing = [n for n in inferred if n not in bounds]
    if missing:
        raise TreeFileError(f"inference.prior: no bounds for joint(s) {missing}")
    for n, bd in bounds.items():
        _bounds_pair(bd.kp, f"inference.prior.{n}.kp")
        _bounds_pair(bd.kd, f"inference.prior.{n}.kd")
    try:  # the same checks as the file's pull: and inference.parameters
        if "pull_direction" in kwargs:
            kwargs["pull_direction"] = parse_direction(kwargs["pull_direction"], "pull.direction")
        if "parameters" in kwargs:
            kwargs["parameters"] = parse_parameters(kwargs["parameters"])
        if "tie" in kwargs or "tie_scale" in kwargs or "tie_shape" in kwargs:
            kwargs["tie"], kwargs["tie_scale"] = parse_tie(
                kwargs.get("tie"), kwargs.get("tie_scale")
            )
            kwargs["tie_shape"] = resolve_tie_shape(
                parse_tie_shape(kwargs.get("tie_shape"), kwargs["tie"]), inferred
            )
    except ConfigError as e:
        raise TreeFileError(str(e)) from None
    tree = Tree(
        name=name,
        branches=branches,
        grasp_branch=grasp_branch,
        grasp_fraction=grasp_fraction,
        inferred=inferred,
        bounds={n: bounds[n] for n in inferred},
        **kwargs,
    )
    _density_in_range(_positive(tree.density, "density"), "density")
    _gain_in_range(_positive(tree.fixed_kp, "fixed.kp"), "fixed.kp")
    _gain_in_range(_positive(tree.fixed_kd, "fixed.kd"), "fixed.kd")
    _check_masses(tree)
    if len(tree.base_position) != 3 or len(tree.gravity) != 3:
        raise TreeFileError("base.position and gravity must have 3 components")
    g = np.asarray(tree.gravity, float)
    if not np.all(np.isfinite(g)) or np.linalg.norm(g) == 0:
        raise TreeFileError(f"gravity: must be a finite non-zero vector, got {list(tree.gravity)}")
    if tree.tie is not None:
        check_tie(tree)
    return tree


# ---- file I/O --------------------------------------------------------------------------------
_BRANCH_KEYS = {
    "name",
    "parent",
    "length",
    "radius",
    "angle_deg",
    "azimuth_deg",
    "attach",
    "density",
    "kp",
    "kd",
    "fixed",
    "twist_deg",
    "lump",
}
_TOP_KEYS = {
    "name",
    "branches",
    "base",
    "gravity",
    "density",
    "grasp",
    "inference",
    "fixed",
    "generator",
    "pull",
    "model",
}


def _no_unknown(m: Any, allowed: set[str], fld: str, pre: str) -> None:
    if not isinstance(m, dict):
        raise TreeFileError(f"{pre}{fld}: expected a mapping with {sorted(allowed)}, got {m!r}")
    bad = set(m) - allowed
    if bad:
        raise TreeFileError(
            f"{pre}{fld}: unknown field(s) {sorted(bad)}; allowed: {sorted(allowed)}"
        )


def tree_from_dict(d: Any, source: str = "<dict>", base_dir: str | Path | None = None) -> Tree:
    """Build a tree from the parsed file content; errors name ``source`` and the field.
    ``base_dir``: where a relative ``model.file`` lies (the tree file's folder)."""
    pre = f"{source}: "
    if not isinstance(d, dict):
        raise TreeFileError(f"{pre}expected a mapping at the top level, got {type(d).__name__}")
    unknown = set(d) - _TOP_KEYS
    if unknown:
        raise TreeFileError(
            f"{pre}unknown top-level field(s) {sorted(unknown)}; allowed: {sorted(_TOP_KEYS)}"
        )
    raw = d.get("branches")
    if not isinstance(raw, list) or not raw:
        raise TreeFileError(f"{pre}branches: expected a non-empty list of branches")
    branches = []
    for i, rb in enumerate(raw):
        if not isinstance(rb, dict):
            raise TreeFileError(f"{pre}branches[{i}]: expected a mapping, got {rb!r}")
        unknown = set(rb) - _BRANCH_KEYS
        if unknown:
            raise TreeFileError(
                f"{pre}branches[{i}]: unknown field(s) {sorted(unknown)}; allowed: "
                f"{sorted(_BRANCH_KEYS)}"
            )
        for req in ("name", "length", "radius"):
            if req not in rb:
                raise TreeFileError(f"{pre}branches[{i}]: missing required field '{req}'")
        bname = string(rb["name"], f"branches[{i}].name", source, TreeFileError)
        parent = rb.get("parent")
        if parent is not None:
            parent = string(parent, f"branches[{i}].parent", source, TreeFileError)
        w = f"{pre}branches[{i}] ('{bname}'): "
        fixed = rb.get("fixed", False)
        if not isinstance(fixed, bool):
            raise TreeFileError(f"{w}fixed: expected true/false, got {fixed!r}")
        branches.append(
            Branch(
                name=bname,
                parent=parent,
                length=_positive(rb["length"], "length", w),
                radius=_positive(rb["radius"], "radius", w),
                angle_deg=_finite(rb.get("angle_deg", 0.0), "angle_deg", w),
                azimuth_deg=_finite(rb.get("azimuth_deg", 0.0), "azimuth_deg", w),
                attach=_check_fraction(rb.get("attach", 1.0), "attach", w),
                density=None
                if rb.get("density") is None
                else _positive(rb["density"], "density", w),
                kp=None if rb.get("kp") is None else _positive(rb["kp"], "kp", w),
                kd=None if rb.get("kd") is None else _positive(rb["kd"], "kd", w),
                fixed=fixed,
                twist_deg=_finite(rb.get("twist_deg", 0.0), "twist_deg", w),
                lump=parse_lump(rb.get("lump"), w),
            )
        )
    try:
        _validate_branches(tuple(branches))
    except TreeFileError as e:
        raise TreeFileError(f"{pre}{e}") from None

    grasp = d.get("grasp")
    if not isinstance(grasp, dict) or "branch" not in grasp:
        raise TreeFileError(f"{pre}grasp: expected a mapping with 'branch' and 'fraction'")
    _no_unknown(grasp, {"branch", "fraction"}, "grasp", pre)
    string(grasp["branch"], "grasp.branch", source, TreeFileError)
    if "name" in d:
        string(d["name"], "name", source, TreeFileError)
    base = d.get("base", {}) or {}
    if not isinstance(base, dict):
        raise TreeFileError(f"{pre}base: expected a mapping with position, pitch_deg, yaw_deg")
    bad = set(base) - {"position", "pitch_deg", "yaw_deg"}
    if bad:
        raise TreeFileError(f"{pre}base: unknown field(s) {sorted(bad)}")
    fixed = d.get("fixed", {}) or {}
    _no_unknown(fixed, {"kp", "kd"}, "fixed", pre)
    inf = d.get("inference", {}) or {}
    if not isinstance(inf, dict):
        raise TreeFileError(f"{pre}inference: expected a mapping")
    if "levels" in inf:
        lv = inf["levels"]
        if isinstance(lv, bool) or not isinstance(lv, int):
            raise TreeFileError(f"{pre}inference.levels: expected a positive integer, got {lv!r}")
    bad = set(inf) - {"joints", "levels", "prior", "parameters", "tie", "tie_scale", "tie_shape"}
    if bad:
        raise TreeFileError(
            f"{pre}inference: unknown field(s) {sorted(bad)}; allowed: joints, levels, prior, "
            "parameters, tie, tie_scale, tie_shape"
        )
    try:
        pull_direction = parse_tree_pull(d.get("pull"), source)
        parameters = parse_parameters(inf.get("parameters"), f"{source}: inference.parameters")
        tie, tie_scale = parse_tie(inf.get("tie"), inf.get("tie_scale"), f"{source}: inference")
        tie_shape = parse_tie_shape(inf.get("tie_shape"), tie, f"{source}: inference")
    except ConfigError as e:
        msg = str(e)
        raise TreeFileError(msg if msg.startswith(pre) else f"{pre}{msg}") from None
    levels = inf.get("levels", 1)
    joints = inf.get("joints")
    if joints is not None and (
        not isinstance(joints, list) or not all(isinstance(j, str) for j in joints)
    ):
        raise TreeFileError(
            f"{pre}inference.joints: expected a list of branch names, got {joints!r}"
        )
    prior = inf.get("prior", {}) or {}
    _no_unknown(prior, {"kp", "kd", "joints"}, "inference.prior", pre)
    per_joint_raw = prior.get("joints", {}) or {}
    if not isinstance(per_joint_raw, dict):
        raise TreeFileError(
            f"{pre}inference.prior.joints: expected a mapping {{joint: {{kp: [lo, hi], kd: [lo, "
            "hi]}}"
        )
    for n, pj in per_joint_raw.items():
        _no_unknown(pj, {"kp", "kd"}, f"inference.prior.joints.{n}", pre)
    try:
        default = Bounds(
            kp=_bounds_pair(prior.get("kp", DEFAULT_KP_BOUNDS), "inference.prior.kp"),
            kd=_bounds_pair(prior.get("kd", DEFAULT_KD_BOUNDS), "inference.prior.kd"),
        )
        per_joint = prior.get("joints", {}) or {}
        bounds_map: dict[str, Bounds] = {}
        tmp_inferred = (
            tuple(joints)
            if joints is not None
            else default_inferred(branches, str(grasp["branch"]), int(levels))
            if str(grasp["branch"]) in {b.name for b in branches}
            else ()
        )
        for n in tmp_inferred:
            pj = per_joint.get(n, {})
            bounds_map[n] = Bounds(
                kp=_bounds_pair(pj.get("kp", default.kp), f"inference.prior.joints.{n}.kp"),
                kd=_bounds_pair(pj.get("kd", default.kd), f"inference.prior.joints.{n}.kd"),
            )
        unknown_pj = set(per_joint) - set(tmp_inferred)
        if unknown_pj:
            raise TreeFileError(
                f"inference.prior.joints: bounds given for joint(s) {sorted(unknown_pj)} that "
                "are not inferred"
            )
        return make_tree(
            branches,
            grasp_branch=str(grasp["branch"]),
            grasp_fraction=grasp.get("fraction", 1.0),
            inferred=joints,
            levels=levels,
            bounds=bounds_map,
            name=str(d.get("name", "tree")),
            base_position=tuple(
                _finite(x, "base.position") for x in base.get("position", (0.0, 0.0, 0.0))
            ),
            base_pitch_deg=_finite(base.get("pitch_deg", 0.0), "base.pitch_deg"),
            base_yaw_deg=_finite(base.get("yaw_deg", 0.0), "base.yaw_deg"),
            gravity=tuple(_finite(x, "gravity") for x in d.get("gravity", (0.0, 0.0, -9.81))),
            density=_positive(d.get("density", DEFAULT_DENSITY), "density"),
            fixed_kp=_positive(fixed.get("kp", DEFAULT_FIXED_KP), "fixed.kp"),
            fixed_kd=_positive(fixed.get("kd", DEFAULT_FIXED_KD), "fixed.kd"),
            pull_direction=pull_direction,
            parameters=parameters,
            tie=tie,
            tie_scale=tie_scale,
            tie_shape=tie_shape,
            model=_model_section(d.get("model"), source, base_dir),
        )
    except TreeFileError as e:
        msg = str(e)
        raise TreeFileError(msg if msg.startswith(pre) else f"{pre}{msg}") from None
    except (TypeError, ValueError, AttributeError) as e:
        raise TreeFileError(f"{pre}malformed field: {e}") from None


def _model_section(raw: Any, source: str, base_dir) -> dict | None:
    if raw is None:
        return None
    from .model_section import parse_model_section

    return parse_model_section(raw, source, base_dir)


def read_tree_file(path: str | Path) -> Any:
    """The parsed content of a tree file (YAML, or JSON by suffix) through the safe loader:
    regular files only (no FIFO or device), size/depth/alias limits, no duplicate keys."""
    return load_file(path, "tree file", TreeFileError)


def load_tree(path: str | Path) -> Tree:
    """Read a tree description from YAML (``.yaml``/``.yml``) or JSON (``.json``)."""
    path = Path(path)
    if path.suffix.lower() in (".urdf", ".xml", ".mjcf") and path.is_file():
        raise TreeFileError(
            f"{path}: a URDF/MJCF model, not a tree description; describe it with "
            f"`treeinfer tree --model {path} --out tree.yaml` (or give it with --model)"
        )
    return tree_from_dict(read_tree_file(path), source=str(path), base_dir=path.parent)


def dump_tree(tree: Tree, path: str | Path) -> Path:
    """Write ``tree`` as YAML or JSON (by suffix), atomically."""
    from ..io.atomic import atomic_write_text

    path = Path(path)
    d = tree_to_dict(tree)
    if path.suffix.lower() == ".json":
        text = json.dumps(d, indent=2) + "\n"
    else:
        import yaml

        text = yaml.safe_dump(d, sort_keys=False)
    return atomic_write_text(path, text)
