"""Wood properties for QSM trees, and the prior boxes of a hinge that stands for a length of
branch.

A hinge at the base of a link of length ``L`` and base radius ``r`` lumps the bending of that
length of wood. An Euler-Bernoulli cantilever of modulus ``E`` and second moment of area
``I = pi r^4 / 4`` turns at its base like a torsional spring ``Kp = c E I / L``, with ``c = 1``
for a moment at the tip, ``c = 3`` for a force at the tip (deflection ``F L^3 / 3 E I`` read
as a rotation about the base) and ``c = gamma K_Theta = 0.85 * 2.65 = 2.25`` for Howell's
pseudo-rigid-body hinge (Howell, *Compliant Mechanisms*, 2001, ch. 5). The stiffness box
spans ``c`` in [1, 3] and ``E`` in [0.5, 1.5] times the species' value (green wood of one
species varies by about +-25% between trees, juvenile wood and branches are softer: Wood
Handbook, FPL-GTR-190, 2010, ch. 5).

The damping box comes from the damping ratio: ``Kd = 2 zeta sqrt(Kp J)`` with ``J`` the
moment of inertia the hinge carries about its axis and ``zeta`` in [0.01, 0.5] (trees' first
modes show a few to about 20% of critical damping in free-vibration tests: James, Haritos &
Ades 2006, Mechanical stability of trees under dynamic loads, Am. J. Bot. 93: 1522-1530).

Densities and moduli of green (freshly cut) wood: :data:`SPECIES`. Modulus of elasticity in
static bending of small clear green specimens and specific gravity on green volume from the
USDA Wood Handbook (FPL-GTR-190, 2010), Table 5-3a (values rounded; the table is the source
to check). The density of green wood is ``1000 * G * (1 + MC)`` with a moisture content MC of
0.8 (sapwood of green hardwoods is about 60-100% moisture, ibid. Table 4-1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..errors import ConfigError

GREEN_MOISTURE = 0.8  # moisture content of green wood (fraction of dry mass)
C_RANGE = (1.0, 3.0)  # Kp = c E I / L: tip moment (1) to tip force (3)
E_SPREAD = (0.5, 1.5)  # the box's modulus range, times the species' value
ZETA_RANGE = (0.01, 0.5)  # damping ratio of a hinge


@dataclass(frozen=True)
class Wood:
    """Green wood: ``density`` kg/m^3 (mass of the living branch per volume), ``modulus`` Pa
    (modulus of elasticity in bending), and where the values came from."""

    density: float
    modulus: float
    name: str


def _green(g: float, e_gpa: float, name: str) -> Wood:
    return Wood(density=1000.0 * g * (1.0 + GREEN_MOISTURE), modulus=e_gpa * 1e9, name=name)


# specific gravity (green volume) and MOE green (GPa), Wood Handbook Table 5-3a
SPECIES: dict[str, Wood] = {
    "green-hardwood": _green(0.50, 8.0, "green hardwood (a typical temperate species)"),
    "kentucky-coffeetree": _green(0.53, 8.9, "Gymnocladus dioicus, green"),
    "red-maple": _green(0.49, 9.6, "Acer rubrum, green"),
    "sugar-maple": _green(0.56, 10.7, "Acer saccharum, green"),
    "northern-red-oak": _green(0.56, 9.3, "Quercus rubra, green"),
    "white-oak": _green(0.60, 8.6, "Quercus alba, green"),
    "quaking-aspen": _green(0.35, 5.9, "Populus tremuloides, green"),
    "black-cherry": _green(0.47, 9.0, "Prunus serotina, green"),
    "white-ash": _green(0.55, 9.9, "Fraxinus americana, green"),
}
DEFAULT_SPECIES = "green-hardwood"


def wood(species: str | None = None, density: float | None = None, modulus: float | None = None):
    """The wood of ``species`` (default green hardwood), with ``density`` (kg/m^3) or
    ``modulus`` (Pa) given by the user replacing the table's."""
    key = (species or DEFAULT_SPECIES).strip().lower().replace(" ", "-").replace("_", "-")
    if key not in SPECIES:
        raise ConfigError(f"species {species!r}: unknown; known: {', '.join(sorted(SPECIES))}")
    w = SPECIES[key]
    name = w.name
    for v, what, lo, hi in ((density, "density", 100.0, 2000.0), (modulus, "modulus", 1e8, 1e11)):
        if v is not None and not (math.isfinite(v) and lo <= v <= hi):
            unit = "kg/m^3" if what == "density" else "Pa"
            raise ConfigError(f"wood {what} {v!r} {unit}: expected a value in [{lo:g}, {hi:g}]")
    if density is not None or modulus is not None:
        name += (
            " ("
            + ", ".join(
                s
                for s in (
                    f"density {density:g} kg/m^3 given" if density is not None else "",
                    f"modulus {modulus / 1e9:g} GPa given" if modulus is not None else "",
                )
                if s
            )
            + ")"
        )
    return Wood(
        density=w.density if density is None else float(density),
        modulus=w.modulus if modulus is None else float(modulus),
        name=name,
    )


def stiffness_box(w: Wood, base_radius: float, length: float) -> tuple[float, float]:
    """(lo, hi) N m/rad of a hinge lumping ``length`` m of branch of base radius
    ``base_radius`` m (module docstring)."""
    second_moment = math.pi * base_radius**4 / 4.0
    ei_l = w.modulus * second_moment / length
    return (C_RANGE[0] * E_SPREAD[0] * ei_l, C_RANGE[1] * E_SPREAD[1] * ei_l)


def damping_box(kp_box: tuple[float, float], carried_inertia: float) -> tuple[float, float]:
    """(lo, hi) N m s/rad for a hinge of stiffness box ``kp_box`` carrying
    ``carried_inertia`` kg m^2 about its axis."""
    lo = 2.0 * ZETA_RANGE[0] * math.sqrt(kp_box[0] * carried_inertia)
    hi = 2.0 * ZETA_RANGE[1] * math.sqrt(kp_box[1] * carried_inertia)
    return (lo, hi)
