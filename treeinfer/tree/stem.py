"""A synthetic stand-in for real quasi-static stem pushes, and the cantilever baseline.

Real data this imitates: a stepper pushes a plant stem sideways at one height while a load
cell logs the force, every 0.5 s, for tens of seconds; the same stem is pushed at three
heights. The logger writes raw CSV: a millisecond counter that wraps around, the load in
grams-force with an offset at rest, the stepper position in millimetres including the approach
before contact, and noise on both.

The stem is **not** a hinge chain: it is a tapered elastic Euler-Bernoulli cantilever (clamped at
the ground, diameter tapering linearly, small deflections, self-weight neglected). Its deflection
at the load point under a point load ``F`` at height ``h`` is, by the unit-load method,

    x(h) = F * integral_0^h (h - z)^2 / EI(z) dz,     EI(z) = E pi d(z)^4 / 64,

evaluated with ``scipy.integrate.quad`` (tests check it against ``scipy.integrate.solve_bvp`` on
``w'' = M / EI`` and against ``F h^3 / 3EI`` for a uniform stem). A hinge chain fitted to such
data has model error; the noise model has to absorb it honestly.

The baseline is the one-parameter uniform cantilever ``x = F h^3 / (3 EI)`` with ``EI`` fitted
by least squares to the training heights (:func:`fit_cantilever`).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..errors import ConfigError
from ..io.atomic import atomic_write_text

__all__ = [
    "Stem",
    "StemProfile",
    "StemPush",
    "cantilever_displacement",
    "compliance",
    "fit_cantilever",
    "matched_hinges",
    "push_recording",
    "branch_at_height",
    "stem_tree",
    "write_stem_logs",
]

G0 = 9.80665


class Stem(NamedTuple):
    """A tapered stem: height m, base and tip diameters m, Young's modulus Pa, density kg/m^3."""

    height: float = 0.40
    base_diameter: float = 0.010
    tip_diameter: float = 0.006
    youngs_modulus: float = 2.0e9
    density: float = 900.0

    def diameter(self, z):
        """Diameter [m] at height ``z`` [m] (linear taper)."""
        return self.base_diameter + (self.tip_diameter - self.base_diameter) * (
            np.asarray(z, float) / self.height
        )

    def ei(self, z):
        """Bending stiffness EI(z) [N m^2]."""
        return self.youngs_modulus * math.pi * self.diameter(z) ** 4 / 64.0


class StemProfile(NamedTuple):
    """A stem whose diameter is measured at a few heights (piecewise linear between them, held
    constant beyond the first and last): heights [n] m increasing in [0, height], diameters [n]
    m. Duck-types :class:`Stem` for :func:`compliance` and :func:`matched_hinges`."""

    height: float
    heights: tuple[float, ...]
    diameters: tuple[float, ...]
    youngs_modulus: float = 2.0e9
    density: float = 900.0

    def diameter(self, z):
        """Diameter [m] at height ``z`` [m]."""
        return np.interp(np.asarray(z, float), self.heights, self.diameters)

    def ei(self, z):
        """Bending stiffness EI(z) [N m^2]."""
        return self.youngs_modulus * math.pi * self.diameter(z) ** 4 / 64.0


def compliance(stem: Stem, h: float) -> float:
    """Deflection per newton [m/N] at height ``h`` under a point load at ``h`` (see module)."""
    from scipy.integrate import quad

    if not 0 < h <= stem.height:
        raise ConfigError(f"height {h} m outside the stem (0, {stem.height}] m")
    val, _ = quad(lambda z: (h - z) ** 2 / float(stem.ei(z)), 0.0, h, epsabs=0, epsrel=1e-12)
    return float(val)


PRB_GAMMA = 0.85  # pseudo-rigid-body characteristic radius of an end-loaded cantilever (Howell)


def matched_hinges(
    stem: Stem, heights: Sequence[float], gamma: float = PRB_GAMMA
) -> tuple[np.ndarray, np.ndarray]:
    """A hinge chain whose compliance at each push height equals the tapered beam's.

    One hinge per push height ``h_1 < ... < h_n`` (m): hinge k at the pseudo-rigid-body pivot
    of the beam piece between the push heights below and at it,
    ``z_k = h_{k-1} + (1 - gamma) (h_k - h_{k-1})`` (``h_0 = 0``; ``gamma = 0.85``: Howell's
    characteristic radius, the pivot that reproduces an end-loaded cantilever's tip path), and
    stiffnesses solving ``sum_{k <= i} (h_i - z_k)^2 / K_k = c(h_i)`` for every i (a lower
    triangular system in ``1 / K``), ``c`` the beam's compliance :func:`compliance` (the
    stem's taper; E only scales every K, so the relative stiffnesses need the diameters alone).

    Returns:
        (z [n] hinge heights m, shape [n] relative stiffnesses ``K_k / max K``). With the scale
        inferred (a taper tie of this shape) the chain reproduces the beam at every push height,
        the held-out one included, up to the beam's E.

    Raises:
        ConfigError: heights not increasing inside the stem, or no positive stiffness solves
            the system (pushes too close together for this gamma).
    """
    h = np.asarray(heights, float)
    if h.ndim != 1 or h.size < 1 or np.any(np.diff(h) <= 0) or h[0] <= 0 or h[-1] > stem.height:
        raise ConfigError(f"heights: expected increasing heights in (0, {stem.height}] m, got {h}")
    if not 0.0 < gamma < 1.0:
        raise ConfigError(f"gamma: expected a number in (0, 1), got {gamma!r}")
    below = np.concatenate([[0.0], h[:-1]])
    z = below + (1.0 - gamma) * (h - below)
    arms = np.where(z[None, :] < h[:, None], (h[:, None] - z[None, :]) ** 2, 0.0)  # [i, k]
    flex = np.linalg.solve(arms, np.array([compliance(stem, float(v)) for v in h]))  # 1/K
    if not np.all(flex > 0):
        raise ConfigError(
            f"matched hinges: no positive stiffness matches the beam at heights {h.tolist()} "
            f"with gamma {gamma:g} (1/K = {flex.tolist()})"
        )
    k = 1.0 / flex
    return z, k / k.max()


class StemPush(NamedTuple):
    """One push as the logger saw it (true values, before logger artefacts).

    Attributes:
        time: [T] s from the logger start. force: [T] N on the stem. displacement: [T] m of
        the stem at the load point. stepper: [T] m stepper position (approach gap included).
        height: m.
    """

    time: np.ndarray
    force: np.ndarray
    displacement: np.ndarray
    stepper: np.ndarray
    height: float


def push_recording(
    stem: Stem,
    height: float,
    dt: float = 0.5,
    idle: float = 5.0,
    gap: float = 0.002,
    speed: float = 0.0005,
    max_deflection: float = 0.010,
    hold: float = 3.0,
) -> StemPush:
    """A displacement-controlled push: idle, approach ``gap`` at ``speed`` m/s, push until the
    stem deflects ``max_deflection`` m, hold, retract to the start, idle.

    The load cell is taken as rigid (stem deflection = stepper travel beyond contact)."""
    c = compliance(stem, height)
    travel = gap + max_deflection
    t_push = travel / speed
    total = idle + t_push + hold + t_push + idle
    t = dt * np.arange(int(total / dt) + 1)
    s = np.interp(
        t,
        [0, idle, idle + t_push, idle + t_push + hold, idle + 2 * t_push + hold, total],
        [0, 0, travel, travel, 0, 0],
    )
    x = np.clip(s - gap, 0.0, None)
    return StemPush(t, x / c, x, s, float(height))


def write_stem_logs(
    folder: str | os.PathLike,
    stem: Stem | None = None,
    heights: Sequence[float] = (0.12, 0.24, 0.36),
    seed: int = 0,
    dt: float = 0.5,
    force_offset_gf: float = 6.0,
    force_noise_gf: float = 0.5,
    position_noise_mm: float = 0.05,
    jitter_ms: float = 3.0,
    counter_start_ms: int = 52_000,
    counter_wrap_ms: int = 65_536,
) -> list[tuple[Path, StemPush]]:
    """Write one raw logger CSV per height, ``push_<mm>mm.csv`` (``millis,load_g,pos_mm``).

    Artefacts: a 16-bit millisecond counter starting at ``counter_start_ms`` (so it wraps during
    a push), timing jitter, a load offset at rest and Gaussian noise on load and position.

    Returns:
        (path, true push) per height, in order.
    """
    stem = Stem() if stem is None else stem
    rng = np.random.default_rng(seed)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for k, h in enumerate(heights):
        push = push_recording(stem, h, dt=dt)
        n = push.time.size
        start = counter_start_ms + 7919 * k  # each push starts at its own counter value
        ms = np.round(start + 1000 * push.time + rng.uniform(-jitter_ms, jitter_ms, n))
        ms = ms.astype(np.int64) % counter_wrap_ms
        load = push.force / G0 * 1000 + force_offset_gf + force_noise_gf * rng.standard_normal(n)
        pos = push.stepper * 1000 + position_noise_mm * rng.standard_normal(n)
        lines = ["millis,load_g,pos_mm"]
        lines += [f"{a},{b:.2f},{c:.3f}" for a, b, c in zip(ms, load, pos)]
        path = folder / f"push_{round(1000 * h)}mm.csv"
        atomic_write_text(path, "\n".join(lines) + "\n")
        out.append((path, push))
    return out


def stem_tree(
    stem: Stem | None = None,
    n_links: int = 3,
    kp_bounds=(0.5, 100.0),
    hinges: str = "bases",
    tie: str | None = None,
    tie_scale: float | None = None,
    push_heights: Sequence[float] = (0.12, 0.24, 0.36),
):
    """A vertical chain of ``n_links`` hinges approximating ``stem``, every joint inferred: the
    hinge model to fit to pushes. The stem is cut into ``n_links`` equal segments;
    ``hinges="bases"`` puts each hinge at its segment's base (links = segments);
    ``"midpoints"`` at its segment's middle (a fixed stub of half a segment at the ground, a
    half-length top link): a beam segment replaced by a hinge at its middle with
    ``K = E I / l`` reproduces the beam's deflection to second order (see
    ``experiments/stem_pushes.py --analytic``); ``"matched"`` puts one hinge per push height
    at :func:`matched_hinges`' pivots (``push_heights``; ``n_links`` is then their number).
    Radii follow the taper at each link's middle.
    ``tie``/``tie_scale``: the tree file's ``inference: {tie: taper, tie_scale: TAU}``
    (:mod:`treeinfer.inference.static.tied`)."""
    from .description import Bounds, Branch, make_tree

    if hinges not in ("bases", "midpoints", "matched"):
        raise ConfigError(f"hinges: expected 'bases', 'midpoints' or 'matched', got {hinges!r}")
    stem = Stem() if stem is None else stem
    seg = stem.height / n_links
    if hinges == "matched":  # one hinge per push height (matched_hinges), a stub below
        z, _ = matched_hinges(stem, push_heights)
        cuts = [0.0, *z.tolist(), stem.height]
        spans = [(a, b, k == 0) for k, (a, b) in enumerate(zip(cuts[:-1], cuts[1:]))]
        n_links = len(z)
    elif hinges == "bases":
        spans = [(i * seg, (i + 1) * seg, False) for i in range(n_links)]
    else:
        cuts = [0.0] + [(i + 0.5) * seg for i in range(n_links)] + [stem.height]
        spans = [(a, b, k == 0) for k, (a, b) in enumerate(zip(cuts[:-1], cuts[1:]))]
    branches, parent = [], None
    for k, (a, b, fixed) in enumerate(spans):
        name = "stub" if fixed else f"link{k - (0 if hinges == 'bases' else 1)}"
        r = float(stem.diameter((a + b) / 2)) / 2
        branches.append(Branch(name, parent, b - a, r, fixed=fixed))
        parent = name
    return make_tree(
        branches,
        grasp_branch=f"link{n_links - 1}",
        grasp_fraction=1.0,
        levels=n_links,
        bounds=Bounds(kp=tuple(kp_bounds)),
        name="stem",
        base_pitch_deg=90.0,
        density=stem.density,
        tie=tie,
        tie_scale=tie_scale,
    )


def branch_at_height(tree, height: float) -> tuple[str, float]:
    """(jointed branch, distance from its joint) of the point at ``height`` m up a vertical
    chain such as :func:`stem_tree` builds (the topmost jointed branch starting below it)."""
    from .description import world_frames

    frames = world_frames(tree)
    base_z = float(tree.base_position[2])
    best = None
    for b in tree.branches:
        z0 = float(frames[b.name][0][2]) - base_z
        if not b.fixed and z0 <= height + 1e-12:
            if best is None or z0 > best[1]:
                best = (b.name, z0)
    if best is None:
        raise ConfigError(f"height {height} m: no jointed branch starts below it")
    return best[0], height - best[1]


def cantilever_displacement(force, height, ei):
    """``x = F h^3 / (3 EI)`` [m] for force [N], height [m], EI [N m^2] (broadcasting)."""
    return np.asarray(force, float) * np.asarray(height, float) ** 3 / (3.0 * ei)


def fit_cantilever(forces: Sequence, displacements: Sequence, heights: Sequence[float]) -> float:
    """Least-squares EI [N m^2] of ``x = F h^3 / 3EI`` over every point of every push.

    Linear in ``c = 1 / 3EI``: ``c = sum(x a) / sum(a^2)`` with ``a = F h^3``.
    """
    a = np.concatenate([np.asarray(f, float) * h**3 for f, h in zip(forces, heights)])
    x = np.concatenate([np.asarray(d, float) for d in displacements])
    den = float(a @ a)
    if den == 0:
        raise ConfigError("fit_cantilever: all forces are zero")
    c = float(x @ a) / den
    if c <= 0:
        raise ConfigError("fit_cantilever: displacement falls as force rises; check signs")
    return 1.0 / (3.0 * c)
