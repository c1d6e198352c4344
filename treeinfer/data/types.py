"""The trajectory types (:class:`Trajectory`, :class:`Observations`), the limits every recording is
checked against, and their validation (:func:`validate_trajectory`; errors name the file and
line). Re-exported by :mod:`treeinfer.data.trajectories`, which reads and writes the files."""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from ..errors import TrajectoryFileError, where

REQUIRED_COLUMNS = ("time", "force", "displacement")
OPTIONAL_COLUMNS = ("velocity",)

# Plausibility limits: values beyond these almost always mean a wrong unit.
MIN_ROWS = 3  # the second-order velocity scheme needs three samples
DT_REL_TOL = 1e-3  # allowed relative deviation of each time step from the median step
MAX_FILE_BYTES = 256 * 1024 * 1024  # a trajectory CSV larger than this is not a pull recording
MAX_DT = 2.0  # s; quasi-static pushes log every 0.1-1 s; 2 s or more is almost surely ms
MAX_DISPLACEMENT = 5.0  # m
MAX_FORCE = 1.0e4  # N
MAX_VELOCITY = 50.0  # m/s
DIR_DT_RTOL = 1e-6  # trajectories loaded together must share one time step


class Trajectory(NamedTuple):
    """One measured (or simulated) pull.

    Attributes:
        time: [T] seconds, strictly increasing, uniform step.
        force: [T] newtons applied on the branch along gravity, positive downward.
        displacement: [T] metres of the grasp point from its rest position along
            gravity, positive downward.
        velocity: [T] metres per second (positive downward) if recorded, else ``None``
            (then :func:`ground_truth_velocity` differentiates ``displacement``).
        source: file name or label, used in messages and plots.
    """

    time: np.ndarray
    force: np.ndarray
    displacement: np.ndarray
    velocity: np.ndarray | None = None
    source: str = ""

    @property
    def n_steps(self) -> int:
        """Number of samples T."""
        return int(np.shape(self.time)[0])

    @property
    def dt(self) -> float:
        """Time step in seconds (span / (T - 1), the least rounding-sensitive estimate)."""
        t = np.asarray(self.time, dtype=float)
        return float((t[-1] - t[0]) / (t.shape[0] - 1))


class Observations(NamedTuple):
    """A batch of trajectories on one time grid, padded to the longest.

    Attributes:
        force: [B, T] newtons, positive downward; padded with each row's last value.
        displacement: [B, T] metres, positive downward; padded with each row's last value.
        velocity: [B, T] metres per second; padded with 0 (at rest).
        mask: [B, T] bool, True on real samples, False on padding.
        dt: time step in seconds shared by all rows.
    """

    force: np.ndarray
    displacement: np.ndarray
    velocity: np.ndarray
    mask: np.ndarray
    dt: float


# ----------------------------------------------------------------------------- validation


def _err(path, line, problem: str) -> TrajectoryFileError:
    loc = where(path if path is not None else "<trajectory>", line)
    return TrajectoryFileError(f"{loc}: {problem}")


def _line_of(lines: Sequence[int] | None, i: int) -> int | None:
    return None if lines is None else lines[i]


def _validate_arrays(
    time: np.ndarray,
    force: np.ndarray,
    displacement: np.ndarray,
    velocity: np.ndarray | None,
    path,
    lines: Sequence[int] | None = None,
) -> None:
    """Check shapes, finiteness, time grid and units; ``lines[i]`` is the file line of row i."""
    named = {"time": time, "force": force, "displacement": displacement}
    if velocity is not None:
        named["velocity"] = velocity
    for name, a in named.items():
        if a.ndim != 1:
            raise _err(path, None, f"column '{name}' must be one-dimensional, got shape {a.shape}")
    n = time.shape[0]
    for name, a in named.items():
        if a.shape[0] != n:
            raise _err(path, None, f"column '{name}' has {a.shape[0]} values but 'time' has {n}")
    if n == 0:
        raise _err(path, None, "no data rows")
    if n < MIN_ROWS:
        raise _err(path, None, f"only {n} data row(s); at least {MIN_ROWS} are needed")
    for name, a in named.items():
        bad = np.flatnonzero(~np.isfinite(a))
        if bad.size:
            i = int(bad[0])
            raise _err(path, _line_of(lines, i), f"column '{name}' is {a[i]} (NaN/inf not allowed)")

    with np.errstate(over="ignore", invalid="ignore"):
        steps = np.diff(time)
    bad = np.flatnonzero(~(steps > 0))
    if bad.size:
        i = int(bad[0]) + 1
        raise _err(
            path,
            _line_of(lines, i),
            f"time {float(time[i])!r} s is not after the previous time {float(time[i - 1])!r} s "
            "(time must be strictly increasing)",
        )
    if not np.all(np.isfinite(steps)):
        raise _err(path, None, "time values too large (step overflows)")
    dt = float(np.median(steps))
    if dt >= MAX_DT:
        raise _err(
            path,
            _line_of(lines, 1),
            f"time step is {dt:g} s; looks like milliseconds, expected seconds "
            f"(steps of {MAX_DT:g} s or more are not plausible for a pull)",
        )
    bad = np.flatnonzero(np.abs(steps - dt) > DT_REL_TOL * dt)
    if bad.size:
        i = int(bad[0]) + 1
        raise _err(
            path,
            _line_of(lines, i),
            f"uneven time step: {steps[i - 1]:g} s from the previous row, expected {dt:g} s "
            f"(relative tolerance {DT_REL_TOL:g}); resample to a fixed step",
        )

    for values, limit, message in (
        (
            displacement,
            MAX_DISPLACEMENT,
            "displacement {v:g} exceeds {limit:g} m; looks like millimetres, expected metres",
        ),
        (
            force,
            MAX_FORCE,
            "force {v:g} N exceeds {limit:g} N, which is implausible for a branch; "
            "expected newtons",
        ),
        (
            velocity,
            MAX_VELOCITY,
            "velocity {v:g} exceeds {limit:g} m/s; "
            "looks like millimetres per second, expected metres per second",
        ),
    ):
        if values is None:
            continue
        i = int(np.argmax(np.abs(values)))
        if abs(values[i]) > limit:
            raise _err(path, _line_of(lines, i), message.format(v=values[i], limit=limit))


def validate_trajectory(traj: Trajectory) -> Trajectory:
    """Return ``traj`` with float64 arrays after checking it as :func:`read_trajectory` would.

    Raises:
        TrajectoryFileError: naming ``traj.source`` and the problem.
    """
    arrs = [np.asarray(a, dtype=float) for a in (traj.time, traj.force, traj.displacement)]
    vel = None if traj.velocity is None else np.asarray(traj.velocity, dtype=float)
    _validate_arrays(*arrs, vel, traj.source or None)
    return Trajectory(*arrs, vel, traj.source)
