"""Export a :class:`~treeinfer.tree.description.Tree` to MJCF (MuJoCo) and URDF.

Both describe the same multibody: one body per branch, a hinge about the branch frame's y-axis
at its base (absent for ``fixed`` branches), a cylinder along the frame's x-axis whose mass and
inertia come from the wood density (plus the branch's welded ``lump``, if any), and a ``grasp``
site on the grasped branch. The joint
spring has ``springref = 0``, so the passive torque is ``-Kp * psi - Kd * psi_dot`` about the
geometric rest angle: the paper's PD controller with zero target.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from .description import (
    Tree,
    base_rotation,
    branch_density,
    cylinder_inertia,
    local_offset,
    local_rotation,
    quat_from_matrix,
)
from .types import branch_inertial

GRASP_SITE = "grasp"
_WOOD_RGBA = "0.45 0.30 0.15 1"


def _fmt(v) -> str:
    return " ".join(f"{float(x):.10g}" for x in np.atleast_1d(v))


def to_mjcf(tree: Tree, timestep: float = 0.002, integrator: str = "implicitfast") -> str:
    """MJCF XML string for ``tree``.

    Args:
      timestep: simulation step, s. integrator: MuJoCo integrator name; ``implicitfast``
        integrates joint damping implicitly, which keeps lightly and heavily damped joints stable.
    """
    root = ET.Element("mujoco", model=tree.name)
    ET.SubElement(root, "compiler", angle="radian", autolimits="true")
    opt = ET.SubElement(
        root,
        "option",
        timestep=f"{timestep:.10g}",
        integrator=integrator,
        gravity=_fmt(tree.gravity),
    )
    # A contact-free articulated chain: skip collision detection and the constraint solver.
    ET.SubElement(opt, "flag", contact="disable", constraint="disable")
    world = ET.SubElement(root, "worldbody")
    bodies = {}
    for b in tree.branches:
        parent_el = world if b.parent is None else bodies[b.parent]
        if b.parent is None:
            pos, rot = (
                np.asarray(tree.base_position, float),
                base_rotation(tree) @ local_rotation(b),
            )
        else:
            pos, rot = local_offset(tree, b), local_rotation(b)
        body = ET.SubElement(
            parent_el, "body", name=b.name, pos=_fmt(pos), quat=_fmt(quat_from_matrix(rot))
        )
        bodies[b.name] = body
        if not b.fixed:
            kp, kd = tree.fixed_gains(b.name)
            ET.SubElement(
                body,
                "joint",
                name=b.name,
                type="hinge",
                axis="0 1 0",
                pos="0 0 0",
                stiffness=f"{kp:.10g}",
                damping=f"{kd:.10g}",
                springref="0",
            )
        if b.lump is None:
            mass, inertia = cylinder_inertia(b, branch_density(tree, b))
            ET.SubElement(
                body,
                "inertial",
                pos=_fmt([b.length / 2, 0, 0]),
                mass=f"{mass:.10g}",
                diaginertia=_fmt(inertia),
            )
        else:  # a welded lump: one body, its inertia the cylinder's plus the lump's
            mass, com, full = branch_inertial(tree, b)
            ET.SubElement(
                body,
                "inertial",
                pos=_fmt(com),
                mass=f"{mass:.10g}",
                fullinertia=_fmt([full[0, 0], full[1, 1], full[2, 2], full[0, 1], full[0, 2],
                                  full[1, 2]]),
            )  # fmt: skip
        ET.SubElement(
            body,
            "geom",
            name=f"{b.name}_geom",
            type="cylinder",
            fromto=_fmt([0, 0, 0, b.length, 0, 0]),
            size=f"{b.radius:.10g}",
            contype="0",
            conaffinity="0",
            mass="0",
            rgba=_WOOD_RGBA,
        )
        if b.name == tree.grasp_branch:
            ET.SubElement(
                body,
                "site",
                name=GRASP_SITE,
                pos=_fmt([tree.grasp_fraction * b.length, 0, 0]),
                size="0.01",
            )
    from ..io.limits import deep_recursion

    with deep_recursion(len(tree.branches)):  # the stdlib's XML walks recurse per nesting level
        ET.indent(root)
        return ET.tostring(root, encoding="unicode")


def to_mjmodel(tree: Tree, timestep: float = 0.002, integrator: str = "implicitfast"):
    """Compiled ``mujoco.MjModel`` of ``tree``."""
    import mujoco

    return mujoco.MjModel.from_xml_string(to_mjcf(tree, timestep, integrator))


def write_mjcf(tree: Tree, path: str | Path, timestep: float = 0.002) -> Path:
    from ..io.atomic import atomic_write_text

    return atomic_write_text(path, to_mjcf(tree, timestep))
