"""URDF export of a :class:`~treeinfer.tree.description.Tree`, and loading users' own MJCF/URDF
models.

The URDF describes the same multibody as :func:`treeinfer.tree.export.to_mjcf`: link ``world`` (the
world itself), a massless link ``base_link`` welded to it by the fixed joint ``base_fixed`` that
carries the base pose, then one link per branch, hinged to its parent by a revolute joint of the
same name about the branch frame's y-axis (a fixed joint for ``fixed`` branches). Each link has a
full ``<inertial>`` (solid wood cylinder) and a cylinder ``<visual>``/``<collision>`` along the
link's x-axis (URDF cylinders run along z, hence ``rpy="0 pi/2 0"``).

URDF has no joint stiffness. The file carries the damping (``<dynamics damping>``) and, in a
``<mujoco>`` extension element that MuJoCo's URDF importer reads (it honours ``<compiler>``,
``<option>`` and ``<size>`` there and nothing else), the compiler settings that keep the model
as written (``fusestatic="false"`` keeps fixed branches as bodies; visual geoms are kept) and the
contact-free options. The stiffness (``jnt_stiffness``, with ``springref = 0``) and the ``grasp``
site must be added on top: :func:`mjmodel_from_urdf` does that through ``mujoco.MjSpec``.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from ..errors import ConfigError, TreeFileError
from .description import (
    Tree,
    base_rotation,
    local_offset,
    local_rotation,
)
from .export import GRASP_SITE
from .types import branch_inertial

WORLD_LINK = "world"
BASE_LINK = "base_link"
BASE_JOINT = "base_fixed"
JOINT_LIMIT = math.pi  # rad; wide enough never to act on a branch
_BIG = (
    1e6  # effort (N m) and velocity (rad/s) limits: URDF requires them, nothing should reach them
)
_WOOD_RGBA = "0.45 0.30 0.15 1"
# integrator option: lower-case key -> (MJCF keyword, mjtIntegrator member)
_INTEGRATORS = {
    "euler": ("Euler", "mjINT_EULER"),
    "rk4": ("RK4", "mjINT_RK4"),
    "implicit": ("implicit", "mjINT_IMPLICIT"),
    "implicitfast": ("implicitfast", "mjINT_IMPLICITFAST"),
}


def _fmt(v) -> str:
    return " ".join(repr(float(x)) for x in np.atleast_1d(v))


def rpy_from_matrix(r: np.ndarray) -> np.ndarray:
    """URDF roll, pitch, yaw (rad) of a rotation matrix: ``r = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.

    Pitch and yaw come from the x-column; the roll is read off what is left, ``(Rz Ry)^T r``, which
    stays accurate at and near gimbal lock (pitch = +-pi/2, where the yaw is set to 0)."""
    from .description import rot_y, rot_z

    r = np.asarray(r, float)
    c = math.hypot(r[0, 0], r[1, 0])
    pitch = math.atan2(-r[2, 0], c)
    yaw = math.atan2(r[1, 0], r[0, 0]) if c > 1e-12 else 0.0
    rest = (rot_z(yaw) @ rot_y(pitch)).T @ r  # = Rx(roll)
    roll = math.atan2(rest[2, 1], rest[1, 1])
    return np.array([roll, pitch, yaw])


def _origin(parent: ET.Element, xyz, rot: np.ndarray | None = None) -> ET.Element:
    rpy = np.zeros(3) if rot is None else rpy_from_matrix(rot)
    return ET.SubElement(parent, "origin", xyz=_fmt(xyz), rpy=_fmt(rpy))


def _check_names(tree: Tree) -> None:
    clash = {WORLD_LINK, BASE_LINK, BASE_JOINT} & set(tree.names)
    if clash:
        raise TreeFileError(
            f"branches: name(s) {sorted(clash)} are reserved in the URDF export; rename the branch"
        )


def to_urdf(tree: Tree, timestep: float = 0.002, integrator: str = "implicitfast") -> str:
    """URDF XML string for ``tree`` (see the module docstring for the layout).

    Args:
      timestep: s, and integrator: written into the ``<mujoco><option>`` extension only.
    """
    _check_names(tree)
    if integrator.lower() not in _INTEGRATORS:
        raise ConfigError(
            f"integrator: unknown '{integrator}'; choose one of {sorted(_INTEGRATORS)}"
        )
    robot = ET.Element("robot", name=tree.name)
    robot.append(
        ET.Comment(
            " Joint stiffness Kp (N m/rad, about the rest angle 0) is not part of URDF; "
            "treeinfer sets it after loading (treeinfer.tree.urdf.mjmodel_from_urdf). "
        )
    )
    mj = ET.SubElement(robot, "mujoco")
    ET.SubElement(
        mj,
        "compiler",
        angle="radian",
        discardvisual="false",
        fusestatic="false",
        balanceinertia="false",
    )
    opt = ET.SubElement(
        mj,
        "option",
        timestep=repr(float(timestep)),
        integrator=_INTEGRATORS[integrator.lower()][0],
        gravity=_fmt(tree.gravity),
    )
    ET.SubElement(opt, "flag", contact="disable", constraint="disable")
    mat = ET.SubElement(robot, "material", name="wood")
    ET.SubElement(mat, "color", rgba=_WOOD_RGBA)

    ET.SubElement(robot, "link", name=WORLD_LINK)
    ET.SubElement(robot, "link", name=BASE_LINK)
    j = ET.SubElement(robot, "joint", name=BASE_JOINT, type="fixed")
    ET.SubElement(j, "parent", link=WORLD_LINK)
    ET.SubElement(j, "child", link=BASE_LINK)
    _origin(j, tree.base_position, base_rotation(tree))

    cyl_rot = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # Ry(pi/2): z -> x
    for b in tree.branches:
        link = ET.SubElement(robot, "link", name=b.name)
        mass, com, full = branch_inertial(tree, b)
        inert = ET.SubElement(link, "inertial")
        _origin(inert, com)
        ET.SubElement(inert, "mass", value=repr(float(mass)))
        # without a lump the off-diagonal terms are exact zeros: the file is as before
        off = lambda i, j: "0" if full[i, j] == 0.0 else repr(float(full[i, j]))
        ET.SubElement(
            inert,
            "inertia",
            ixx=repr(float(full[0, 0])),
            ixy=off(0, 1),
            ixz=off(0, 2),
            iyy=repr(float(full[1, 1])),
            iyz=off(1, 2),
            izz=repr(float(full[2, 2])),
        )
        for kind in ("visual", "collision"):
            el = ET.SubElement(link, kind, name=f"{b.name}_{kind}")
            _origin(el, [b.length / 2, 0, 0], cyl_rot)
            geom = ET.SubElement(el, "geometry")
            ET.SubElement(
                geom, "cylinder", radius=repr(float(b.radius)), length=repr(float(b.length))
            )
            if kind == "visual":
                ET.SubElement(el, "material", name="wood")

        j = ET.SubElement(robot, "joint", name=b.name, type="fixed" if b.fixed else "revolute")
        ET.SubElement(j, "parent", link=BASE_LINK if b.parent is None else b.parent)
        ET.SubElement(j, "child", link=b.name)
        _origin(j, local_offset(tree, b), local_rotation(b))
        if not b.fixed:
            _, kd = tree.fixed_gains(b.name)
            ET.SubElement(j, "axis", xyz="0 1 0")
            ET.SubElement(j, "dynamics", damping=repr(float(kd)))
            ET.SubElement(
                j,
                "limit",
                lower=repr(-JOINT_LIMIT),
                upper=repr(JOINT_LIMIT),
                effort=repr(_BIG),
                velocity=repr(_BIG),
            )
    from ..io.limits import deep_recursion

    with deep_recursion(len(tree.branches)):  # the stdlib's XML walks recurse per nesting level
        ET.indent(robot)
        return ET.tostring(robot, encoding="unicode")


def write_urdf(
    tree: Tree, path: str | Path, timestep: float = 0.002, integrator: str = "implicitfast"
) -> Path:
    """Write :func:`to_urdf` to ``path`` atomically."""
    from ..io.atomic import atomic_write_text

    return atomic_write_text(path, to_urdf(tree, timestep, integrator))


def mjmodel_from_urdf(
    urdf: str,
    tree: Tree,
    timestep: float = 0.002,
    integrator: str = "implicitfast",
    source: str = "<urdf>",
):
    """Compile a URDF string with MuJoCo's own URDF importer and complete it from ``tree``.

    Sets every tree joint's stiffness (``Kp``, ``springref = 0``) and damping from the tree (the
    fixed gains; the simulator overwrites the inferred ones), the timestep, integrator and gravity,
    disables contacts and the constraint solver, and adds the ``grasp`` site, as
    :func:`treeinfer.tree.export.to_mjmodel` has them.

    Raises:
      TreeFileError: MuJoCo cannot parse the URDF (its message included), or a tree branch has no
        body/joint in it.
    """
    import mujoco

    key = integrator.lower()
    if key not in _INTEGRATORS:
        raise ConfigError(
            f"integrator: unknown '{integrator}'; choose one of {sorted(_INTEGRATORS)}"
        )
    try:
        spec = mujoco.MjSpec.from_string(urdf)
    except ValueError as e:  # MuJoCo's parser message, with the line
        raise TreeFileError(f"{source}: MuJoCo cannot parse this URDF: {e}") from None
    spec.option.timestep = float(timestep)
    spec.option.integrator = getattr(mujoco.mjtIntegrator, _INTEGRATORS[key][1])
    spec.option.gravity = np.asarray(tree.gravity, float)
    spec.option.disableflags |= (
        mujoco.mjtDisableBit.mjDSBL_CONTACT | mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
    )
    for b in tree.branches:
        if spec.body(b.name) is None:
            raise TreeFileError(
                f"{source}: no link named '{b.name}' (branch of tree '{tree.name}')"
            )
        if b.fixed:
            continue
        joint = spec.joint(b.name)
        if joint is None:
            raise TreeFileError(
                f"{source}: no joint named '{b.name}' (branch of tree '{tree.name}')"
            )
        kp, kd = tree.fixed_gains(b.name)
        # MjSpec holds stiffness/damping as [linear, polynomial terms...]: keep them linear
        joint.stiffness = [kp] + [0.0] * (len(joint.stiffness) - 1)
        joint.damping = [kd] + [0.0] * (len(joint.damping) - 1)
        joint.springref = 0.0
    if spec.site(GRASP_SITE) is None:
        length = tree.branch(tree.grasp_branch).length
        spec.body(tree.grasp_branch).add_site(
            name=GRASP_SITE, pos=[tree.grasp_fraction * length, 0, 0], size=[0.01, 0.01, 0.01]
        )
    try:
        return spec.compile()
    except ValueError as e:
        raise TreeFileError(f"{source}: MuJoCo cannot compile this URDF: {e}") from None


def load_model_file(path: str | Path):
    """A user's own model as a ``mujoco.MjModel``: MJCF (``.xml``/``.mjcf``) or URDF (``.urdf``).

    Raises:
      TreeFileError: missing file, unknown suffix, or MuJoCo's parse/compile error (included).
    """
    import mujoco

    path = Path(path)
    kinds = {".xml": "MJCF", ".mjcf": "MJCF", ".urdf": "URDF"}
    if path.suffix.lower() not in kinds:
        raise TreeFileError(
            f"{path}: unknown model file type '{path.suffix}'; expected .xml (MJCF) or .urdf"
        )
    if not path.is_file():
        raise TreeFileError(f"{path}: no such file")
    from .model_paths import check_model_paths

    check_model_paths(path)  # no FIFO, device or link loop among the files MuJoCo opens
    try:
        return mujoco.MjModel.from_xml_path(str(path))
    except ValueError as e:  # MuJoCo's message names the element and line
        raise TreeFileError(
            f"{path}: MuJoCo cannot load this {kinds[path.suffix.lower()]} file: {e}"
        ) from None
