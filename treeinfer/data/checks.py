"""Plausibility checks of training data against a tree, before inference: per-file statistics
(compliance, rest, units, velocity consistency, duplicates) judged against what the tree can do
(:mod:`treeinfer.tree.plausibility`). Re-exported by :mod:`treeinfer.evaluation.checks`."""

from __future__ import annotations

import hashlib
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..tree.description import Tree
from ..tree.plausibility import (
    MAX_BRANCH_SPEED,
    MIXED_RATIO,
    REST_FORCE,
    REST_FRACTION,
    REST_MIN,
    SCALE_ERROR,
    SCALE_WARN,
    SPEED_MARGIN,
    VELOCITY_MISMATCH,
    ZERO_ATOL,
    Finding,
    grasp_reach,
    response_range,
)
from .stream_checks import stream_checks


# ---- per-trajectory statistics ---------------------------------------------------------------
def _compliance(force: np.ndarray, disp: np.ndarray) -> float | None:
    """Least-squares slope of displacement on force through the start point (m/N); None when
    the force does not vary."""
    df = force - force[0]
    dx = disp - disp[0]
    den = float(df @ df)
    if den <= ZERO_ATOL:
        return None
    return float(df @ dx) / den


def _integrated(v: np.ndarray, dt: float) -> np.ndarray:
    """Trapezoidal integral of ``v`` from 0 (same length)."""
    out = np.zeros_like(v)
    out[1:] = np.cumsum(0.5 * (v[1:] + v[:-1]) * dt)
    return out


def _label(t, paths, i) -> str:
    if paths is not None and i < len(paths) and paths[i] is not None:
        return str(paths[i])
    return t.source or f"trajectory {i}"


def _sha256(path) -> str | None:
    try:
        h = hashlib.sha256()
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        return h.hexdigest()
    except OSError:
        return None


def _scale_causes(c: float, c_stiff: float, c_soft: float) -> list[str]:
    """Unit mistakes that would bring the compliance ``c`` (m/N) into the tree's range."""

    def fits(x):
        return c_stiff / SCALE_WARN <= x <= c_soft * SCALE_WARN

    out = []
    if fits(1.0 / c):
        out.append("the force and displacement columns were swapped")
    for factor, what in (
        (100.0, "displacement is in cm (not m)"),
        (1000.0, "displacement is in mm (not m), or force in kN (not N)"),
    ):
        if fits(c / factor):
            out.append(what)
    return out


SPEED_WINDOWS = (10, 30, 100)  # samples over which the time-unit check measures speed
# The time-unit finding is an error (the clock, not a sensor glitch) when a file moves this many
# times faster than the energy bound allows (noise term included), or when every file of a set
# of two or more breaks the bound: the bound is a physical one (kinetic energy <= the pull's
# work), already with SPEED_MARGIN, and a glitch does not repeat in every recording.
TIME_UNIT_ERROR = 2.0


def speed_limit(f: np.ndarray, x: np.ndarray, dt: float, mobility: float):
    """(fastest plausible grasp-point speed in m/s, how it was set, the noise term) for the
    time-unit check; a k-sample difference may exceed the speed by ``noise term / k`` m/s.

    Physics, not a fixed threshold: the tree starts at rest and is passive (springs, dampers,
    gravity about a stable rest pose), so its kinetic energy never exceeds the work the pull
    has done, ``W <= max|F| * range(x)``; a grasp-point speed v costs at least
    ``v^2 / (2 mobility)`` of kinetic energy (``mobility`` the largest eigenvalue of
    ``J M^-1 J^T`` over the prior box's rest poses, :func:`treeinfer.tree.plausibility.
    response_range`). Hence ``v <= sqrt(2 mobility max|F| range(x))``, times
    :data:`SPEED_MARGIN` (the pose moves during the pull). White noise of std sigma moves a
    k-sample difference by up to ~5 sqrt(2) sigma (over a few hundred samples): that divided by
    ``k dt``. A release (force dropped, the branch springing back at its own frequency) stays
    under it; the same pull with time in minutes moves 60x faster than its energy allows."""
    work = float(np.max(np.abs(f))) * float(np.ptp(x))
    try:
        from .noise_estimate import estimate_white_noise

        sigma = estimate_white_noise(x[None], what="displacement").sigma
    except ConfigError:
        sigma = 0.0
    noise = 5.0 * np.sqrt(2.0) * sigma / dt
    if not (mobility > 0 and np.isfinite(mobility)):
        return MAX_BRANCH_SPEED, f"at most {MAX_BRANCH_SPEED:g} m/s", noise
    v = SPEED_MARGIN * float(np.sqrt(2.0 * mobility * work))
    why = f"the pull's work, at most {work:.3g} J, moves it at {v:.3g} m/s at most"
    return v, why, noise


def _ratio_text(r: float) -> str:
    return f"{r:.3g}x"


def data_checks(
    tree: Tree,
    trajectories: Sequence,
    paths: Sequence[str | os.PathLike | None] | None = None,
    grasp_fraction: float | None = None,
    tree_file: str | os.PathLike | None = None,
) -> list[Finding]:
    """Plausibility findings for training ``trajectories`` on ``tree`` (module docstring).

    Args:
      tree: the tree (with its prior box). trajectories: validated
        :class:`~treeinfer.data.trajectories.Trajectory` s (time s, force N, displacement m,
        optional velocity m/s, all positive downward). paths: their files (byte-identical
        duplicates; messages), default ``Trajectory.source``. grasp_fraction: where the data
        were recorded (None: the tree's). tree_file: named in tree findings.

    Returns:
      Findings, errors where the data are certainly wrong, warnings otherwise.
    """
    from ..tree.description import tree_scale_warnings

    out: list[Finding] = []
    tname = str(tree_file) if tree_file is not None else f"tree '{tree.name}'"
    out += [Finding("warning", tname, "tree-scale", w) for w in tree_scale_warnings(tree)]
    c_stiff, c_soft, mobility = response_range(tree, grasp_fraction)
    # the compliance range is that of a pull down at the tree's grasp: no scale check for other
    # pull directions (the tree file's pull.direction), or where a down pull cannot move the
    # grasp point (a vertical stem: its compliance along gravity is zero)
    scale_ok = c_soft > 0 and c_stiff > 0 and getattr(tree, "pull_direction", "down") == "down"
    reach = grasp_reach(tree, grasp_fraction)
    comps: dict[int, float] = {}
    fast: dict[int, float] = {}  # index in out of a time-unit finding -> how far over the bound

    for i, t in enumerate(trajectories):
        name = _label(t, paths, i)
        f = np.asarray(t.force, float)
        x = np.asarray(t.displacement, float)
        dt = float(t.dt)
        fmax, xrange = float(np.max(np.abs(f))), float(np.ptp(x))
        if fmax <= ZERO_ATOL and float(np.max(np.abs(x))) <= ZERO_ATOL:
            out.append(
                Finding(
                    "error",
                    name,
                    "all-zero",
                    "force and displacement are all zero: nothing to learn from "
                    "(the posterior would be the prior)",
                )
            )
            continue
        if fmax <= ZERO_ATOL:
            out.append(
                Finding(
                    "error",
                    name,
                    "all-zero",
                    f"force is zero throughout while the displacement spans {xrange:.3g} m: "
                    "the force column is missing or was not recorded",
                )
            )
            continue
        if float(np.max(np.abs(x))) <= ZERO_ATOL:
            out.append(
                Finding(
                    "error",
                    name,
                    "all-zero",
                    f"displacement is zero throughout while the force reaches {fmax:.3g} N: "
                    "the displacement column is missing or was not recorded",
                )
            )
            continue

        # streams against each other: at rest under no load, cause before effect
        out += stream_checks(name, f, x, dt)

        # reach: the grasp point cannot move further than its lever arm allows
        xmax = float(np.max(np.abs(x)))
        if xmax > 2.0 * reach:
            out.append(
                Finding(
                    "error",
                    name,
                    "reach",
                    f"displacement reaches {xmax:.3g} m but the grasp point is {reach:.3g} m "
                    f"from the nearest hinge and cannot move more than {2 * reach:.3g} m: "
                    "displacement in cm/mm, swapped columns, or an offset?",
                )
            )

        # rest: displacement from the rest position starts near 0 when the force does
        x0 = float(x[0])
        if abs(x0) > max(REST_FRACTION * max(xrange, 1e-12), REST_MIN):
            sev = "error" if abs(f[0]) <= REST_FORCE * fmax else "warning"
            out.append(
                Finding(
                    sev,
                    name,
                    "rest",
                    f"displacement starts at {x0:.3g} m (its range is {xrange:.3g} m) while "
                    f"the force starts at {f[0]:.3g} N: displacement must be measured from "
                    "the branch's rest position (subtract the first sample?)",
                )
            )

        # sign and scale through the quasi-static compliance
        c = _compliance(f, x)
        if c is not None:
            comps[i] = c
            corr = float(np.corrcoef(f, x)[0, 1]) if np.ptp(x) > 0 else 0.0
            if c < 0 and corr < -0.3:
                out.append(
                    Finding(
                        "error",
                        name,
                        "sign",
                        f"displacement moves against the force (correlation {corr:.2f}, slope "
                        f"{c:.3g} m/N): both are positive downward; flip the sign of one "
                        "column (e.g. --force-sign -1 on import-bag)",
                    )
                )
            elif c > 0 and scale_ok:
                if c > c_soft * SCALE_WARN:
                    r = c / c_soft
                    causes = _scale_causes(c, c_stiff, c_soft)
                    sev = "error" if r > SCALE_ERROR or causes else "warning"
                    hint = (
                        "; ".join(causes)
                        if causes
                        else "displacement in cm or mm instead of m, or force in kN instead of N?"
                    )
                    out.append(
                        Finding(
                            sev,
                            name,
                            "scale",
                            f"displacement per newton is {c:.3g} m/N, {_ratio_text(r)} more than "
                            f"the most the tree allows over the prior box's stiffnesses "
                            f"({c_soft:.3g} m/N); it would fit if: {hint}",
                        )
                    )
                elif c < c_stiff / SCALE_WARN:
                    r = c_stiff / c
                    sev = "error" if r > SCALE_ERROR * 10 else "warning"
                    out.append(
                        Finding(
                            sev,
                            name,
                            "scale",
                            f"displacement per newton is {c:.3g} m/N, {_ratio_text(r)} less than "
                            f"the least the tree gives over the prior box's stiffnesses "
                            f"({c_stiff:.3g} m/N): the branch may be stiffer than "
                            "the prior box allows (widen inference.prior.kp), or displacement "
                            "is in km / force in mN?",
                        )
                    )

        # velocity column against the displacement it should be the slope of
        if t.velocity is not None:
            v = np.asarray(t.velocity, float)
            dx = x - x[0]
            xi = _integrated(v, dt)
            scale = float(np.sqrt(np.mean(dx**2)))
            if scale > ZERO_ATOL:
                mis = float(np.sqrt(np.mean((xi - dx) ** 2))) / scale
                if mis > VELOCITY_MISMATCH:
                    den = float(xi @ xi)
                    a = float(xi @ dx) / den if den > ZERO_ATOL else 0.0
                    scaled_fit = float(np.sqrt(np.mean((a * xi - dx) ** 2))) / scale
                    if float(np.max(np.abs(v))) <= ZERO_ATOL:
                        why = "the velocity column is all zero"
                    elif scaled_fit > VELOCITY_MISMATCH:
                        why = (
                            "the velocity column does not follow the displacement "
                            "(noise or another signal?)"
                        )
                    elif a < -0.5 and abs(abs(a) - 1) < 0.3:
                        why = "the velocity column has the opposite sign"
                    elif abs(a) > 3 or (0 < abs(a) < 1 / 3):
                        why = (
                            "the velocity column is "
                            f"{1 / a if a else float('inf'):.3g}x the slope of "
                            "the displacement (another unit, or time in other units?)"
                        )
                    else:
                        why = (
                            "the velocity column does not follow the displacement "
                            "(noise or another signal?)"
                        )
                    out.append(
                        Finding(
                            "error",
                            name,
                            "velocity",
                            f"{why}: integrated, it misses the displacement by {mis:.0%} of its "
                            "RMS; drop the column to differentiate the displacement instead",
                        )
                    )

        # time unit: the grasp point cannot move faster than the work the pull did allows
        if len(x) >= 3:
            limit, why, noise_speed = speed_limit(f, x, dt, mobility)
            # the largest change over k samples, for several k: a short window sees a fast
            # release, a long one averages the noise down (a slow pull under heavy noise)
            worst, at = 0.0, None
            for k in sorted({min(k, len(x) - 1) for k in SPEED_WINDOWS}):
                speed_k = float(np.max(np.abs(x[k:] - x[:-k]))) / (k * dt)
                ratio = speed_k / (limit + noise_speed / k)
                if ratio > 1.0 and ratio > worst:
                    worst, at = ratio, (k, speed_k)
            if at is not None:
                k, speed_k = at
                speed = float(np.max(np.abs(np.diff(x)))) / dt
                fast[len(out)] = worst
                out.append(
                    Finding(
                        "error" if worst >= TIME_UNIT_ERROR else "warning",
                        name,
                        "time-unit",
                        f"the grasp point moves at {speed_k:.3g} m/s over {k} samples "
                        f"(steps of {dt:.3g} s; peak single-step {speed:.3g} m/s), {worst:.3g}x "
                        f"faster than the tree can ({why}, noise included): is time in minutes "
                        "instead of seconds (or displacement not in metres)?",
                    )
                )

    # every file of the set faster than the tree can move: the clock, not a glitch in one file
    if len(fast) == len(trajectories) >= 2:
        for j in fast:
            out[j] = out[j]._replace(
                severity="error", message=out[j].message + " (every file of the set is)"
            )

    # mixed units between files
    if len(comps) >= 2:
        med = float(np.median(list(comps.values())))
        for i, c in comps.items():
            if c > 0 and med > 0 and max(c / med, med / c) > MIXED_RATIO:
                name = _label(trajectories[i], paths, i)
                r = c / med
                out.append(
                    Finding(
                        "error",
                        name,
                        "mixed-units",
                        f"displacement per newton {c:.3g} m/N is {_ratio_text(max(r, 1 / r))} "
                        f"{'more' if r > 1 else 'less'} than the other files' median ({med:.3g} "
                        "m/N): one file in other units (cm vs m, kN vs N)?",
                    )
                )

    # duplicates: identical bytes or identical arrays
    seen: dict[str, int] = {}
    for i, t in enumerate(trajectories):
        key = None
        p = paths[i] if paths is not None and i < len(paths) else None
        if p is not None and Path(p).is_file():
            digest = _sha256(p)
            key = f"file:{digest}" if digest else None
        arr_key = (
            "arr:"
            + hashlib.sha256(
                np.ascontiguousarray(
                    np.stack([np.asarray(t.force, float), np.asarray(t.displacement, float)])
                ).tobytes()
            ).hexdigest()
        )
        for k in (key, arr_key):
            if k is None:
                continue
            if k in seen:
                j = seen[k]
                what = (
                    "byte-identical to"
                    if k.startswith("file:")
                    else "has the same force and displacement as"
                )
                out.append(
                    Finding(
                        "error",
                        _label(t, paths, i),
                        "duplicate",
                        f"{what} {_label(trajectories[j], paths, j)}: the same recording twice "
                        "counts its evidence twice (overconfident posterior); remove one",
                    )
                )
                break
            seen[k] = i
    return out
