"""The tree description's types: branches, prior boxes and the :class:`Tree` itself, the limits
every field is checked against, the frame geometry, and the field-level checks (grasp
fraction, gains) shared by :mod:`treeinfer.tree.description` (construction and files) and the
importers. The pull-direction, inferred-parameter and tie parsers live in
:mod:`treeinfer.tree.options` (re-exported here)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ..errors import TreeFileError, check_positive
from .lump import Lump, body_inertial

# the pull direction, inferred parameters and tie live in tree_options (re-exported here)
from .options import (  # noqa: F401 -- re-exported: the old import path keeps working
    DIRECTION_WORDS,
    PARAMETERS,
    TIES,
    parse_direction,
    parse_parameters,
    parse_tie,
    parse_tie_shape,
    parse_tree_pull,
    resolve_tie_shape,
)

# Default prior boxes (natural units). Kp in N m/rad, Kd in N m s/rad. Chosen for branches of
# a few cm radius and up to ~1.5 m: gravity sag of a few degrees to tens of degrees.
DEFAULT_KP_BOUNDS = (5.0, 500.0)
DEFAULT_KD_BOUNDS = (0.05, 10.0)
DEFAULT_DENSITY = 700.0  # kg/m^3, typical fresh hardwood
DEFAULT_FIXED_KP = 2000.0
DEFAULT_FIXED_KD = 20.0

# Plausibility limits: values outside are certainly a mistake (a unit slip or a typo) and would
# reach MuJoCo as degenerate bodies (mass or inertia below its mjMINVAL = 1e-15), overflow in
# float32 simulation, or need millions of substeps. Errors name the branch and field.
MAX_BRANCH_LENGTH = 50.0  # m; a longer single branch is millimetres or centimetres read as metres
WARN_BRANCH_LENGTH = 5.0  # m; longer branches get a warning from tree_scale_warnings
MIN_RADIUS = 1.0e-4  # m (0.1 mm)
MAX_RADIUS = 5.0  # m
DENSITY_RANGE = (1.0, 1.0e5)  # kg/m^3; wood is 300-1200, lead 11 000
MIN_MASS = 1.0e-9  # kg; far above MuJoCo's mjMINVAL, so float32 rollouts stay well-posed
MIN_INERTIA = 1.0e-14  # kg m^2, principal inertia about the centre of mass
KP_RANGE = (1.0e-6, 1.0e8)  # N m/rad: every prior bound and fixed gain must lie inside
KD_RANGE = (1.0e-8, 1.0e6)  # N m s/rad
# Names the generated models use themselves: ``world`` is MuJoCo's body 0 (a branch of that
# name cannot be compiled). The URDF export's own ``base_link``/``base_fixed`` are refused by
# :func:`treeinfer.tree.urdf.to_urdf`, since a tree using them still simulates.
RESERVED_NAMES = frozenset({"world"})
# suffixes of generated element names: branch ``b`` makes geom ``b_geom`` (MJCF) and
# ``b_visual`` / ``b_collision`` (URDF); a branch named like that would shadow one of them.
_GENERATED_SUFFIXES = ("_geom", "_visual", "_collision")


@dataclass(frozen=True)
class Branch:
    """One cylindrical branch and the joint at its base.

    Attributes:
      name: unique name; also the MJCF body/joint name.
      parent: parent branch name, or None for the root.
      length: m. radius: m.
      angle_deg: fork angle relative to the parent's direction, in the bending plane (deg).
      azimuth_deg: rotation of the bending plane about the parent's axis (deg).
      attach: where along the parent it forks, as a fraction of the parent's length.
      density: wood density, kg/m^3 (None: the tree's default).
      kp, kd: fixed joint stiffness/damping used when this joint is not inferred
        (None: the tree's defaults).
      fixed: True welds the branch to its parent (no joint at all).
      twist_deg: rotation of the branch frame, and so of its hinge, about the branch's own
        axis after the fork (deg; 0: the hinge is normal to the plane of the branch and its
        parent). Lets a hinge take any direction across the branch without a welded body.
      lump: mass welded into the branch's body (:class:`treeinfer.tree.lump.Lump`), or None.
    """

    name: str
    parent: str | None
    length: float
    radius: float
    angle_deg: float = 0.0
    azimuth_deg: float = 0.0
    attach: float = 1.0
    density: float | None = None
    kp: float | None = None
    kd: float | None = None
    fixed: bool = False
    twist_deg: float = 0.0
    lump: Lump | None = None


@dataclass(frozen=True)
class Bounds:
    """Prior box of one joint in natural units: Kp in N m/rad, Kd in N m s/rad."""

    kp: tuple[float, float] = DEFAULT_KP_BOUNDS
    kd: tuple[float, float] = DEFAULT_KD_BOUNDS


@dataclass(frozen=True)
class Tree:
    """A validated tree description. Build one with :func:`make_tree` or :func:`load_tree`."""

    name: str
    branches: tuple[Branch, ...]
    grasp_branch: str
    grasp_fraction: float
    inferred: tuple[str, ...]  # joint (= branch) names, grasped branch first, then up the tree
    bounds: dict[str, Bounds] = field(default_factory=dict)
    base_position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    base_pitch_deg: float = 0.0
    base_yaw_deg: float = 0.0
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)
    density: float = DEFAULT_DENSITY
    fixed_kp: float = DEFAULT_FIXED_KP
    fixed_kd: float = DEFAULT_FIXED_KD
    # the data set's default pull direction (``pull: {direction: ...}``): "down", "horizontal"
    # or a world vector (x, y, z) of any non-zero length (see treeinfer.data.pulls)
    pull_direction: str | tuple[float, float, float] = "down"
    # gains the samplers move (``inference: {parameters: [kp]}``): ("kp", "kd") or ("kp",)
    parameters: tuple[str, ...] = ("kp", "kd")
    # stiffness tied along the stem (``inference: {tie: taper, tie_scale: TAU}``, see
    # treeinfer.inference.static.tied): None (every joint free) or "taper"; tie_scale None (hard
    # tie, one free scale) or the std TAU > 0 of each joint's log-stiffness about the taper (soft
    # tie)
    tie: str | None = None
    tie_scale: float | None = None
    # ``tie: shape``'s relative stiffnesses (``inference.tie_shape``), one positive number per
    # inferred joint in the order of ``inferred`` (Kp_j = scale * tie_shape[j]); else None
    tie_shape: tuple[float, ...] | None = None
    # the user's own URDF/MJCF (treeinfer.tree.usermodel): the validated ``model:`` section, or None
    model: dict | None = None

    # ---- lookups -------------------------------------------------------------------------
    @property
    def names(self) -> tuple[str, ...]:
        return tuple(b.name for b in self.branches)

    def branch(self, name: str) -> Branch:
        for b in self.branches:
            if b.name == name:
                return b
        raise TreeFileError(f"unknown branch '{name}'; the tree has: {', '.join(self.names)}")

    def children(self, name: str) -> tuple[str, ...]:
        return tuple(b.name for b in self.branches if b.parent == name)

    def ancestors(self, name: str) -> tuple[str, ...]:
        """Names from ``name`` itself up to the root."""
        out, cur = [], self.branch(name)
        while cur is not None:
            out.append(cur.name)
            cur = self.branch(cur.parent) if cur.parent is not None else None
        return tuple(out)

    @property
    def n_inferred(self) -> int:
        return len(self.inferred)

    def parameter_labels(self) -> list[str]:
        """Labels of the parameter vector: ``Kp[j]`` for each inferred joint, then ``Kd[j]``."""
        return [f"Kp[{n}]" for n in self.inferred] + [f"Kd[{n}]" for n in self.inferred]

    def inferred_pairs(self) -> list[tuple[int, int]]:
        """(parent index, child index) into ``inferred`` for each inferred joint whose nearest
        jointed ancestor is also inferred: the pairs the inequality prior constrains."""
        idx = {n: i for i, n in enumerate(self.inferred)}
        pairs = []
        for child in self.inferred:
            for anc in self.ancestors(child)[1:]:
                if self.branch(anc).fixed:
                    continue
                if anc in idx:
                    pairs.append((idx[anc], idx[child]))
                break
        return pairs

    def bounds_array(self) -> tuple[np.ndarray, np.ndarray]:
        """Prior box as (lower [2R], upper [2R]) in natural units, ordered like the labels."""
        lo = [self.bounds[n].kp[0] for n in self.inferred] + [
            self.bounds[n].kd[0] for n in self.inferred
        ]
        hi = [self.bounds[n].kp[1] for n in self.inferred] + [
            self.bounds[n].kd[1] for n in self.inferred
        ]
        return np.asarray(lo, float), np.asarray(hi, float)

    def fixed_gains(self, name: str) -> tuple[float, float]:
        b = self.branch(name)
        return (self.fixed_kp if b.kp is None else b.kp, self.fixed_kd if b.kd is None else b.kd)

    def with_grasp(self, fraction: float, branch: str | None = None) -> Tree:
        _check_fraction(fraction, "grasp.fraction")
        name = self.grasp_branch if branch is None else branch
        self.branch(name)
        return replace(self, grasp_fraction=float(fraction), grasp_branch=name)

    def total_length(self) -> float:
        return float(sum(b.length for b in self.branches))


# ---- geometry ---------------------------------------------------------------------------------
def rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def base_rotation(tree: Tree) -> np.ndarray:
    # rot_y(-pitch) lifts the x-axis towards +z for a positive pitch.
    return rot_z(math.radians(tree.base_yaw_deg)) @ rot_y(-math.radians(tree.base_pitch_deg))


def local_rotation(b: Branch) -> np.ndarray:
    """Rotation of a branch frame relative to its parent's frame (or the base frame)."""
    r = rot_x(math.radians(b.azimuth_deg)) @ rot_y(-math.radians(b.angle_deg))
    # a twist only where given: every other tree keeps its rotation to the last bit
    return r @ rot_x(math.radians(b.twist_deg)) if b.twist_deg != 0.0 else r


def local_offset(tree: Tree, b: Branch) -> np.ndarray:
    """Joint position in the parent's frame (the root: in the base frame, i.e. zero)."""
    if b.parent is None:
        return np.zeros(3)
    return np.array([b.attach * tree.branch(b.parent).length, 0.0, 0.0])


def world_frames(tree: Tree) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """World (position [3], rotation [3,3]) of every branch frame at the rest pose."""
    frames: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for b in tree.branches:  # parents come before children (validated)
        if b.parent is None:
            p0, r0 = np.asarray(tree.base_position, float), base_rotation(tree)
        else:
            p0, r0 = frames[b.parent]
        frames[b.name] = (p0 + r0 @ local_offset(tree, b), r0 @ local_rotation(b))
    return frames


def cylinder_inertia(b: Branch, density: float) -> tuple[float, np.ndarray]:
    """Mass (kg) and principal inertia about the centre of mass (kg m^2), axis along x."""
    m = density * math.pi * b.radius**2 * b.length
    ia = 0.5 * m * b.radius**2
    it = m * (3 * b.radius**2 + b.length**2) / 12.0
    return m, np.array([ia, it, it])


def branch_density(tree: Tree, b: Branch) -> float:
    return tree.density if b.density is None else b.density


def branch_inertial(tree: Tree, b: Branch) -> tuple[float, np.ndarray, np.ndarray]:
    """(mass kg, centre of mass [3] m, inertia [3, 3] kg m^2 about it) of the branch's body in
    its frame: the cylinder's, plus its ``lump``."""
    m, principal = cylinder_inertia(b, branch_density(tree, b))
    return body_inertial(m, principal, b.length, b.lump)


def quat_from_matrix(r: np.ndarray) -> np.ndarray:
    """(w, x, y, z) unit quaternion of a rotation matrix (MuJoCo convention)."""
    import mujoco

    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.asarray(r, float).reshape(-1))
    return q


# ---- construction and validation -----------------------------------------------------------
def _no_bool(v: Any, fld: str, where: str, expected: str) -> None:
    if isinstance(v, bool):
        raise TreeFileError(
            f"{where}{fld}: expected {expected}, got {v!r} "
            "(YAML reads yes/no/on/off as booleans; write a number)"
        )


def _check_fraction(f: Any, fld: str, where: str = "") -> float:
    _no_bool(f, fld, where, "a number in (0, 1]")
    try:
        f = float(f)
    except (TypeError, ValueError):
        raise TreeFileError(f"{where}{fld}: expected a number in (0, 1], got {f!r}") from None
    if not (0.0 < f <= 1.0) or math.isnan(f):
        raise TreeFileError(
            f"{where}{fld}: must be in (0, 1] (a fraction of the branch length), got {f}"
        )
    return f


def _positive(v: Any, fld: str, where: str = "") -> float:
    _no_bool(v, fld, where, "a positive number")
    return check_positive(v, f"{where}{fld}:", error=TreeFileError)


def _finite(v: Any, fld: str, where: str = "") -> float:
    _no_bool(v, fld, where, "a number")
    try:
        v = float(v)
    except (TypeError, ValueError):
        raise TreeFileError(f"{where}{fld}: expected a number, got {v!r}") from None
    if not math.isfinite(v):
        raise TreeFileError(f"{where}{fld}: must be finite, got {v}")
    return v


def _bounds_pair(v: Any, fld: str, where: str = "") -> tuple[float, float]:
    if not isinstance(v, (list, tuple)) or len(v) != 2:
        raise TreeFileError(f"{where}{fld}: expected [lower, upper], got {v!r}")
    lo, hi = _positive(v[0], fld + "[0]", where), _positive(v[1], fld + "[1]", where)
    if not lo < hi:
        raise TreeFileError(f"{where}{fld}: lower bound {lo} must be below upper bound {hi}")
    _gain_in_range(lo, fld + "[0]", where)
    _gain_in_range(hi, fld + "[1]", where)
    return (lo, hi)


def _gain_in_range(v: float, fld: str, where: str = "") -> float:
    """Refuse gains no branch can have (Kp outside KP_RANGE, Kd outside KD_RANGE): they
    overflow float32 rollouts or need absurd numbers of simulation substeps."""
    leaf = fld.split(".")[-1].split("[")[0].lower()
    lo, hi, unit = (*KD_RANGE, "N m s/rad") if leaf == "kd" else (*KP_RANGE, "N m/rad")
    if not lo <= v <= hi:
        raise TreeFileError(
            f"{where}{fld}: {v:g} {unit} is outside the plausible range [{lo:g}, {hi:g}] {unit} "
            "for a branch joint; check the value and its unit"
        )
    return v


def _density_in_range(v: float, fld: str, where: str = "") -> float:
    lo, hi = DENSITY_RANGE
    if not lo <= v <= hi:
        raise TreeFileError(
            f"{where}{fld}: {v:g} kg/m^3 is outside the plausible range [{lo:g}, {hi:g}] kg/m^3 "
            "(wood is about 300-1200); check the value and its unit"
        )
    return v


def _check_masses(tree: Tree) -> None:
    """Every branch's mass and inertia well above MuJoCo's mjMINVAL (degenerate bodies)."""
    for i, b in enumerate(tree.branches):
        w = f"branches[{i}] ('{b.name}'): "
        m, inertia = cylinder_inertia(b, branch_density(tree, b))
        if not math.isfinite(m) or m < MIN_MASS:
            raise TreeFileError(
                f"{w}mass {m:.3g} kg (density {branch_density(tree, b):g} kg/m^3, radius "
                f"{b.radius:g} m, length {b.length:g} m) is below {MIN_MASS:g} kg: a degenerate "
                "body; check density and radius"
            )
        if not np.all(np.isfinite(inertia)) or float(inertia.min()) < MIN_INERTIA:
            raise TreeFileError(
                f"{w}inertia {float(inertia.min()):.3g} kg m^2 about the branch axis is below "
                f"{MIN_INERTIA:g} kg m^2: a degenerate body; check radius and density"
            )


def tree_scale_warnings(tree: Tree, source: str = "") -> list[str]:
    """Warnings for a tree whose size looks like the wrong unit but is not certainly wrong
    (a branch longer than WARN_BRANCH_LENGTH m, or thicker than a quarter of its length)."""
    pre = f"{source}: " if source else ""
    out = []
    for i, b in enumerate(tree.branches):
        if b.length > WARN_BRANCH_LENGTH:
            out.append(
                f"{pre}branches[{i}] ('{b.name}'): length {b.length:g} m is unusually long "
                "for one branch; are the lengths in metres?"
            )
        if b.radius > 0.25 * b.length and b.radius > 0.2:
            out.append(
                f"{pre}branches[{i}] ('{b.name}'): radius {b.radius:g} m is unusually "
                "thick; are the radii in metres?"
            )
    return out


def tree_to_dict(tree: Tree) -> dict[str, Any]:
    """The file representation of ``tree`` (round-trips through :func:`tree_from_dict`)."""
    branches = []
    for b in tree.branches:
        rb: dict[str, Any] = {
            "name": b.name,
            "parent": b.parent,
            "length": b.length,
            "radius": b.radius,
        }
        for k in ("angle_deg", "azimuth_deg", "twist_deg"):
            if getattr(b, k) != 0.0:
                rb[k] = getattr(b, k)
        if b.attach != 1.0:
            rb["attach"] = b.attach
        for k in ("density", "kp", "kd"):
            if getattr(b, k) is not None:
                rb[k] = getattr(b, k)
        if b.fixed:
            rb["fixed"] = True
        if b.lump is not None:
            rb["lump"] = b.lump.to_dict()
        branches.append(rb)
    out = {
        "name": tree.name,
        "base": {
            "position": list(tree.base_position),
            "pitch_deg": tree.base_pitch_deg,
            "yaw_deg": tree.base_yaw_deg,
        },
        "gravity": list(tree.gravity),
        "density": tree.density,
        "fixed": {"kp": tree.fixed_kp, "kd": tree.fixed_kd},
        "branches": branches,
        "grasp": {"branch": tree.grasp_branch, "fraction": tree.grasp_fraction},
        "inference": {
            "joints": list(tree.inferred),
            "prior": {
                "joints": {
                    n: {"kp": list(tree.bounds[n].kp), "kd": list(tree.bounds[n].kd)}
                    for n in tree.inferred
                }
            },
        },
    }
    # written only when not the default, so that older trees' files (and hashes) are unchanged
    if tree.parameters != ("kp", "kd"):
        out["inference"]["parameters"] = list(tree.parameters)
    if tree.tie is not None:
        out["inference"]["tie"] = tree.tie
        if tree.tie_scale is not None:
            out["inference"]["tie_scale"] = float(tree.tie_scale)
        if tree.tie == "shape" and tree.tie_shape is not None:  # by joint: order-proof
            out["inference"]["tie_shape"] = {
                n: float(v) for n, v in zip(tree.inferred, tree.tie_shape)
            }
    if tree.pull_direction != "down":
        pd = tree.pull_direction
        out["pull"] = {"direction": pd if isinstance(pd, str) else [float(x) for x in pd]}
    if tree.model is not None:
        out["model"] = dict(tree.model)
    return out
