"""Candidate pulls for :mod:`treeinfer.design`: the grid, their force profiles, and the
stated future manipulation (:class:`Target`) a ``--target`` score is about."""

from __future__ import annotations

import itertools
import math
import re
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from ..data.forces import format_spec, from_spec
from ..errors import ConfigError

# Timing of each profile kind, as fractions of the pull's duration (the middle of the ranges
# treeinfer.data.forces.random_specs draws from): a candidate is fixed by kind, peak and grasp
# alone.
STANDARD_TIMING: dict[str, dict[str, float]] = {
    "ramp": {"start": 0.05, "ramp": 0.5},
    "hold": {"start": 0.05, "ramp": 0.2, "hold": 0.2, "release": 0.15},
    "release": {"start": 0.05, "ramp": 0.3, "release": 0.2},
    "step": {"start": 0.1, "rise": 0.1},
}


# ==== candidates ==================================================================================
class Candidate(NamedTuple):
    """One candidate pull.

    grasp_fraction: where along the grasped branch (0 at its joint, 1 at its tip).
    peak_force: N, the profile's peak (downward along gravity unless ``direction`` is given).
    profile_kind: a key of :data:`treeinfer.data.forces.SHAPES` (timing: :data:`STANDARD_TIMING`).
    direction: None (along gravity) or a [3] unit vector in the world frame.
    """

    grasp_fraction: float
    peak_force: float
    profile_kind: str = "ramp"
    direction: tuple[float, float, float] | None = None

    def to_dict(self) -> dict:
        return {
            "grasp_fraction": float(self.grasp_fraction),
            "peak_force": float(self.peak_force),
            "profile_kind": self.profile_kind,
            "direction": None if self.direction is None else [float(v) for v in self.direction],
        }


def _check_direction(d, where: str):
    if d is None:
        return None
    try:
        v = np.asarray(d, float).reshape(3)
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: a direction must be 3 numbers (x, y, z), got {d!r}") from None
    n = float(np.linalg.norm(v))
    if not np.all(np.isfinite(v)) or n == 0:
        raise ConfigError(f"{where}: a direction must be a finite non-zero vector, got {d!r}")
    return tuple(float(x) for x in v / n)


def _check_candidate(c: Candidate, where: str = "candidate") -> Candidate:
    g, f = c.grasp_fraction, c.peak_force
    if not (isinstance(g, (int, float, np.floating)) and math.isfinite(g) and 0 < g <= 1):
        raise ConfigError(f"{where}: grasp_fraction must be in (0, 1], got {g!r}")
    if not (isinstance(f, (int, float, np.floating)) and math.isfinite(f)):
        raise ConfigError(f"{where}: peak_force must be a finite number of newtons, got {f!r}")
    if c.profile_kind not in STANDARD_TIMING:
        raise ConfigError(
            f"{where}: profile_kind must be one of {sorted(STANDARD_TIMING)}, "
            f"got {c.profile_kind!r}"
        )
    return Candidate(float(g), float(f), c.profile_kind, _check_direction(c.direction, where))


def candidate_grid(
    grasp_fractions: Sequence[float],
    peak_forces: Sequence[float],
    profile_kinds: Sequence[str] = ("ramp",),
    directions: Sequence | None = None,
) -> list[Candidate]:
    """Every combination of the given grasp fractions, peak forces (N), kinds and directions
    (None: along gravity only), in that nesting order (directions innermost)."""
    dirs = [None] if directions is None or len(directions) == 0 else list(directions)
    for name, seq in (
        ("grasp_fractions", grasp_fractions),
        ("peak_forces", peak_forces),
        ("profile_kinds", profile_kinds),
    ):
        if len(seq) == 0:
            raise ConfigError(f"candidates: {name} is empty")
    return [
        _check_candidate(Candidate(float(g), float(f), k, d), f"candidate (g={g}, F={f}, {k})")
        for g, f, k, d in itertools.product(grasp_fractions, peak_forces, profile_kinds, dirs)
    ]


def candidate_spec(c: Candidate, duration: float) -> str:
    """The :mod:`treeinfer.data.forces` spec of a candidate's profile over ``duration`` s."""
    timing = {k: round(v * duration, 6) for k, v in STANDARD_TIMING[c.profile_kind].items()}
    return format_spec(c.profile_kind, peak=c.peak_force, **timing)


def candidate_forces(candidates: Sequence[Candidate], duration: float, dt: float) -> np.ndarray:
    """[C, T] N: the candidates' force profiles sampled every ``dt`` s."""
    return np.stack([from_spec(candidate_spec(c, duration), duration, dt) for c in candidates])


class Target(NamedTuple):
    """A future manipulation whose predictive band should shrink: the displacement trajectory
    at ``grasp_fraction`` under a ``profile_kind`` pull of ``peak_force`` N (standard timing)."""

    grasp_fraction: float
    peak_force: float
    profile_kind: str = "ramp"
    direction: tuple[float, float, float] | None = None

    def candidate(self) -> Candidate:
        return Candidate(*self)

    def describe(self) -> str:
        d = "" if self.direction is None else f" along {list(self.direction)}"
        return (
            f"displacement at grasp fraction {self.grasp_fraction:g} under a {self.profile_kind} "
            f"pull of {self.peak_force:g} N{d}"
        )


_TARGET_KEYS = {"grasp": "grasp_fraction", "peak": "peak_force", "kind": "profile_kind"}


def parse_target(text: str) -> Target:
    """``"grasp=0.5,peak=5[,kind=ramp]"`` -> :class:`Target` (grasp fraction, N, profile kind)."""
    where = f"--target {text!r}"
    fields: dict = {}
    for item in filter(None, (s.strip() for s in str(text).split(","))):
        m = re.fullmatch(r"(\w+)\s*=\s*(\S+)", item)
        if not m or m.group(1) not in _TARGET_KEYS:
            raise ConfigError(f"{where}: expected grasp=G,peak=F[,kind=K], got item {item!r}")
        key, val = _TARGET_KEYS[m.group(1)], m.group(2)
        if key != "profile_kind":
            try:
                val = float(val)
            except ValueError:
                raise ConfigError(f"{where}: {m.group(1)} must be a number, got {val!r}") from None
        fields[key] = val
    missing = [k for k, v in _TARGET_KEYS.items() if v not in fields and k != "kind"]
    if missing:
        raise ConfigError(
            f"{where}: missing {', '.join(missing)} (expected grasp=G,peak=F[,kind=K])"
        )
    c = _check_candidate(Candidate(**fields), where)
    return Target(*c)
