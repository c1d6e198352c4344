"""Geometry of a user's URDF/MJCF as MuJoCo compiles it (for :mod:`treeinfer.tree.usermodel`): the
probe model, inertias from the link geometry, each link's axis and length, and the checks and
opt-in repairs of degenerate inertias (errors name the link)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..errors import TreeFileError
from .model_section import MODEL_SUFFIXES

MIN_MASS = 1e-9  # kg: below it a moving link counts as massless
_CYLINDERS = (3, 5)  # mjGEOM_CAPSULE, mjGEOM_CYLINDER


# ---- geometry of a loaded spec ----------------------------------------------------------------
def _load_spec(path: Path):
    import mujoco

    if path.suffix.lower() not in MODEL_SUFFIXES:
        raise TreeFileError(
            f"{path}: unknown model file type '{path.suffix}'; expected .urdf or .xml/.mjcf (MJCF)"
        )
    if not path.is_file():
        raise TreeFileError(f"{path}: no such model file")
    from .model_paths import check_model_paths

    check_model_paths(path)  # no FIFO, device or link loop among the files MuJoCo opens
    try:
        spec = mujoco.MjSpec.from_file(str(path))
    except Exception as e:  # MuJoCo's own message says what is wrong with the file
        raise TreeFileError(
            f"{path}: MuJoCo cannot load this {MODEL_SUFFIXES[path.suffix.lower()]} file: {e}"
        ) from None
    spec.compiler.fusestatic = False  # fixed links stay bodies (branches may name them)
    return spec


def _probe(spec, path: Path):
    """Compiled copy of ``spec`` with every inertia replaced by a unit one: the kinematics and
    geometry of the model even when its own inertias do not compile."""
    probe = spec.copy()
    for b in probe.bodies:
        b.mass, b.inertia, b.ipos = 1.0, [1.0, 1.0, 1.0], [0.0, 0.0, 0.0]
        b.fullinertia = [math.nan] * 6
        b.explicitinertial = True
    for g in probe.geoms:
        g.mass = 0.0
    try:
        return probe.compile()
    except Exception as e:
        raise TreeFileError(f"{path}: MuJoCo cannot compile this model: {e}") from None


def _geom_inertials(spec, path: Path) -> dict[str, tuple[float, np.ndarray]]:
    """{body name: (mass kg, [3, 3] inertia)} as MuJoCo computes them from the geoms of bodies
    without an explicit inertial (explicit ones replaced by unit inertials to compile)."""
    probe = spec.copy()
    for b in probe.bodies:
        if b.explicitinertial:
            b.mass, b.inertia, b.fullinertia = 1.0, [1.0, 1.0, 1.0], [math.nan] * 6
    probe.compiler.boundmass, probe.compiler.boundinertia = 0.0, 0.0
    try:
        m = probe.compile()
    except Exception as e:  # a geom-derived inertial MuJoCo refuses: its message names the body
        raise TreeFileError(
            f"{path}: MuJoCo cannot compile this model: {e}; fix the geoms' "
            "mass/density or give the body an <inertial>"
        ) from None
    return {
        m.body(i).name: (float(m.body_mass[i]), np.diag(m.body_inertia[i]))
        for i in range(1, m.nbody)
    }


def _quat_z(q) -> np.ndarray:
    import mujoco

    r = np.zeros(9)
    mujoco.mju_quat2Mat(r, np.asarray(q, float))
    return r.reshape(3, 3)[:, 2]


def link_axis(m, body: int) -> tuple[np.ndarray, np.ndarray, float | None] | None:
    """(start [3], end [3] in the body frame, m; radius m or None) of a link's axis, or None."""
    best = None
    for g in range(m.ngeom):
        if m.geom_bodyid[g] != body or int(m.geom_type[g]) not in _CYLINDERS:
            continue
        half = float(m.geom_size[g][1])
        if best is None or half > best[0]:
            c, z = np.asarray(m.geom_pos[g], float), _quat_z(m.geom_quat[g])
            best = (half, c - half * z, c + half * z, float(m.geom_size[g][0]))
    if best is not None:
        _, a, b, r = best
        return (a, b, r) if np.linalg.norm(a) <= np.linalg.norm(b) else (b, a, r)
    kids = [i for i in range(1, m.nbody) if m.body_parentid[i] == body]
    if kids:
        far = max(kids, key=lambda i: np.linalg.norm(m.body_pos[i]))
        if np.linalg.norm(m.body_pos[far]) > 0:
            return np.zeros(3), np.asarray(m.body_pos[far], float), None
    return None


def _spec_inertia(b) -> np.ndarray:
    """[3, 3] inertia tensor (kg m^2, about the com) of a spec body, in its inertial frame."""
    full = np.asarray(b.fullinertia, float)
    if np.all(np.isfinite(full)):
        xx, yy, zz, xy, xz, yz = full
        return np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
    return np.diag(np.asarray(b.inertia, float))


def _degenerate(mass: float, inertia: np.ndarray) -> str | None:
    """Why a moving link's mass/inertia cannot be simulated, or None."""
    if not math.isfinite(mass) or mass <= MIN_MASS:
        return f"mass {mass:g} kg"
    ev = np.sort(np.linalg.eigvalsh(inertia))
    if not np.all(np.isfinite(ev)) or ev[0] <= 1e-12 * max(1.0, ev[-1]) or ev[0] <= 0:
        return f"inertia eigenvalues {np.round(ev, 12).tolist()} kg m^2 (not positive definite)"
    if ev[0] + ev[1] < ev[2] * (1 - 1e-9):
        return f"inertia eigenvalues {ev.tolist()} violate A + B >= C"
    return None


def _repair(b, m_probe, bid: int, how: str, density: float) -> str:
    """Repair a spec body's inertial in place; a description of what was done."""
    mass = float(b.mass)
    ax = link_axis(m_probe, bid) if how == "geometry" else None
    if how == "geometry" and ax is not None and ax[2] is not None:
        a, e, r = ax
        length = float(np.linalg.norm(e - a))
        if not (math.isfinite(mass) and mass > MIN_MASS):
            mass = density * math.pi * r**2 * length
        ia, it = 0.5 * mass * r**2, mass * (3 * r**2 + length**2) / 12.0
        z = (e - a) / length
        # principal frame with the cylinder axis along z: columns x', y', z
        x = np.cross([0.0, 1.0, 0.0], z) if abs(z[1]) < 0.9 else np.cross([1.0, 0.0, 0.0], z)
        x /= np.linalg.norm(x)
        rot = np.stack([x, np.cross(z, x), z], axis=1)
        tensor = rot @ np.diag([it, it, ia]) @ rot.T
        b.mass, b.ipos, b.iquat = mass, (a + e) / 2, [1.0, 0.0, 0.0, 0.0]
        b.fullinertia = [
            tensor[0, 0],
            tensor[1, 1],
            tensor[2, 2],
            tensor[0, 1],
            tensor[0, 2],
            tensor[1, 2],
        ]
        b.explicitinertial = True
        return (
            f"solid cylinder r={r:.4g} m, L={length:.4g} m, mass {mass:.4g} kg "
            f"(Ixx..Izz {np.round(np.diag(tensor), 9).tolist()} kg m^2)"
        )
    # floor: eigenvalues raised to a 1 cm radius of gyration (or 1e-9 kg m^2)
    if not (math.isfinite(mass) and mass > MIN_MASS):
        mass = 1e-3
    i0 = _spec_inertia(b)
    i0 = np.where(np.isfinite(i0), i0, 0.0)
    ev, vec = np.linalg.eigh((i0 + i0.T) / 2)
    floor = max(1e-9, mass * 1e-4)
    ev = np.maximum(ev, floor)
    ev[np.argmax(ev)] = min(ev.max(), np.sort(ev)[0] + np.sort(ev)[1])
    t = vec @ np.diag(ev) @ vec.T
    b.mass = mass
    b.fullinertia = [t[0, 0], t[1, 1], t[2, 2], t[0, 1], t[0, 2], t[1, 2]]
    b.explicitinertial = True
    return f"inertia eigenvalues floored at {floor:.3g} kg m^2, mass {mass:.4g} kg"
