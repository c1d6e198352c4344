"""Masses welded into a branch's body (``lump:`` of a branch in the tree file).

Why: a QSM's tree off the grasp's chain (:mod:`treeinfer.tree.qsm_convert`, ``rest="lump"``)
had been welded on as extra jointless bodies. The fused simulator's program grows with the
number of bodies times the joints above each, so a converted 8-joint chain carried 18 bodies
and took many times the compile of a hand-written 8-joint tree. A lump is instead part of its
branch's rigid body: the body's mass, centre of mass and inertia are the cylinder's plus the
lump's, so the model has one body per branch like every other tree.

A lump is given in its branch's frame (origin at the joint, x along the branch, y the hinge):
``mass`` (kg), ``com`` [x, y, z] (m) and ``inertia`` [ixx, iyy, izz, ixy, ixz, iyz] (kg m^2,
about ``com``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import TreeFileError

_KEYS = ("mass", "com", "inertia")


@dataclass(frozen=True)
class Lump:
    """Rigid mass welded to a branch, in the branch's frame (module docstring)."""

    mass: float
    com: tuple[float, float, float]
    inertia: tuple[float, float, float, float, float, float]  # ixx iyy izz ixy ixz iyz

    def tensor(self) -> np.ndarray:
        """The 3x3 inertia tensor about ``com`` (kg m^2)."""
        xx, yy, zz, xy, xz, yz = self.inertia
        return np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]], float)

    def to_dict(self) -> dict[str, Any]:
        return {
            "mass": float(self.mass),
            "com": [float(x) for x in self.com],
            "inertia": [float(x) for x in self.inertia],
        }


def lump_from_parts(mass: float, com, tensor) -> Lump:
    """A :class:`Lump` from a mass, a centre [3] and a 3x3 tensor about it (symmetrised)."""
    t = 0.5 * (np.asarray(tensor, float) + np.asarray(tensor, float).T)
    return Lump(
        mass=float(mass),
        com=tuple(float(x) for x in np.asarray(com, float)),
        inertia=tuple(float(t[i, j]) for i, j in ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))),
    )


def check_lump(lump: Lump, where: str) -> Lump:
    """Refuse a lump no rigid body can have (``where`` prefixes the error: file and branch)."""
    w = f"{where}lump: "
    if not (math.isfinite(lump.mass) and lump.mass > 0):
        raise TreeFileError(f"{w}mass: expected a positive number of kg, got {lump.mass!r}")
    if len(lump.com) != 3 or not all(math.isfinite(x) for x in lump.com):
        raise TreeFileError(f"{w}com: expected three finite numbers [x, y, z] (m)")
    if len(lump.inertia) != 6 or not all(math.isfinite(x) for x in lump.inertia):
        raise TreeFileError(
            f"{w}inertia: expected six finite numbers [ixx, iyy, izz, ixy, ixz, iyz] (kg m^2)"
        )
    ev = np.linalg.eigvalsh(lump.tensor())
    scale = max(float(np.abs(ev).max()), 1e-300)
    if ev[0] < -1e-9 * scale or ev[0] + ev[1] < ev[2] * (1 - 1e-9):
        raise TreeFileError(
            f"{w}inertia: principal moments {', '.join(f'{x:.4g}' for x in ev)} kg m^2 are not "
            "those of a rigid body (each must be >= 0 and at most the sum of the other two)"
        )
    return lump


def parse_lump(raw: Any, where: str) -> Lump | None:
    """The ``lump:`` mapping of a branch in a tree file (None when absent)."""
    if raw is None:
        return None
    if not isinstance(raw, dict) or set(raw) != set(_KEYS):
        raise TreeFileError(f"{where}lump: expected a mapping with exactly {list(_KEYS)}")

    def numbers(v, n, fld):
        if not isinstance(v, (list, tuple)) or len(v) != n:
            raise TreeFileError(f"{where}lump.{fld}: expected a list of {n} numbers, got {v!r}")
        try:
            if any(isinstance(x, bool) for x in v):
                raise TypeError
            return tuple(float(x) for x in v)
        except (TypeError, ValueError):
            raise TreeFileError(f"{where}lump.{fld}: expected numbers, got {v!r}") from None

    (mass,) = numbers([raw["mass"]], 1, "mass")
    return check_lump(
        Lump(mass, numbers(raw["com"], 3, "com"), numbers(raw["inertia"], 6, "inertia")), where
    )


def body_inertial(mass: float, principal, length: float, lump: Lump | None):
    """(mass, com [3], 3x3 inertia about com) in the branch frame of a cylinder of ``mass`` and
    ``principal`` moments (axis along x, centre at ``length / 2``) with ``lump`` welded on."""
    com = np.array([length / 2, 0.0, 0.0])
    tensor = np.diag(np.asarray(principal, float))
    if lump is None:
        return float(mass), com, tensor
    m2, c2 = lump.mass, np.asarray(lump.com, float)
    total = mass + m2
    c = (mass * com + m2 * c2) / total

    def shift(m, p):  # parallel-axis term of a point mass m at p about c
        d = p - c
        return m * (float(d @ d) * np.eye(3) - np.outer(d, d))

    return total, c, tensor + shift(mass, com) + lump.tensor() + shift(m2, c2)


def cylinders_lump(mass, start, end, radius, origin, rot) -> Lump:
    """The lump of solid cylinders (``mass`` [n] kg, axis ``start``-``end`` [n, 3], ``radius``
    [n], in the world frame) in the frame at ``origin`` with axes ``rot`` [3, 3] (columns):
    their mass, centre of mass and inertia about it, each cylinder's own inertia included."""
    mass = np.asarray(mass, float)
    centre = 0.5 * (start + end)
    axis = end - start
    length = np.linalg.norm(axis, axis=1)
    u = axis / np.maximum(length, 1e-300)[:, None]
    ia = 0.5 * mass * radius**2
    it = mass * (3 * radius**2 + length**2) / 12.0
    total = float(mass.sum())
    com = (mass[:, None] * centre).sum(0) / total
    d = centre - com
    eye = np.eye(3)
    tensor = np.zeros((3, 3))
    for k in range(len(mass)):
        uu = np.outer(u[k], u[k])
        tensor += it[k] * (eye - uu) + ia[k] * uu
        tensor += mass[k] * (float(d[k] @ d[k]) * eye - np.outer(d[k], d[k]))
    return lump_from_parts(total, rot.T @ (com - origin), rot.T @ tensor @ rot)
