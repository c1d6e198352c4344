"""Force–deformation trajectories: the observed data.

A trajectory is what the robot measured during one pull on a branch: the force
it applied and the resulting displacement of the grasp point, both projected on
the gravity axis (positive downward), sampled on a uniform time grid.

On disk a trajectory is one CSV file::

    time,force,displacement[,velocity]
    0.00,0.0,0.0
    0.01,0.5,0.0001
    ...

in seconds, newtons, metres (and metres per second). Files written by treeinfer begin with the
header line, so ``pandas.read_csv``, the ``csv`` module and spreadsheets read them as they are;
provenance goes beside them (``import.json`` of the importers, a run's ``config.json``).
Reading also accepts ``#`` comment lines anywhere (before or after the header). Everything a
user can get wrong in such a file raises :class:`~treeinfer.errors.TrajectoryFileError`
naming the file, the 1-based line and the problem.

Layout: the types and their validation live in :mod:`treeinfer.data.types`,
``true_params.json`` in :mod:`treeinfer.data.true_params`, the band CSV and ``import.json`` in
:mod:`treeinfer.data.side_files`; this module reads and writes the recordings and re-exports them.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ConfigError, TrajectoryFileError
from ..io.atomic import atomic_write_text
from .side_files import (  # noqa: F401 -- re-exported: the old import path keeps working
    BAND_COLUMNS,
    PROVENANCE_FILE,
    band_csv_text,
    write_band_csv,
    write_provenance,
)
from .true_params import (  # noqa: F401 -- re-exported: the old import path keeps working
    GAIN_UNITS,
    TRUE_PARAMS_FILE,
    check_positive_params,
    read_true_params,
    true_params_record,
    write_true_params,
)
from .types import (  # noqa: F401 -- re-exported: the old import path keeps working
    DIR_DT_RTOL,
    DT_REL_TOL,
    MAX_DISPLACEMENT,
    MAX_DT,
    MAX_FILE_BYTES,
    MAX_FORCE,
    MAX_VELOCITY,
    MIN_ROWS,
    OPTIONAL_COLUMNS,
    REQUIRED_COLUMNS,
    Observations,
    Trajectory,
    _err,
    _validate_arrays,
    validate_trajectory,
)

__all__ = [
    "OPTIONAL_COLUMNS",
    "REQUIRED_COLUMNS",
    "Observations",
    "Trajectory",
    "add_noise",
    "band_csv_text",
    "ground_truth_velocity",
    "read_trajectory",
    "read_trajectory_dir",
    "stack_trajectories",
    "validate_trajectory",
    "velocity_from_displacement",
    "write_band_csv",
    "write_provenance",
    "write_trajectory",
]

# ----------------------------------------------------------------------------- CSV I/O


def _parse_header(cells: list[str], path, line: int) -> list[str]:
    names = [c.strip().strip('"').strip("'").strip().lower() for c in cells]
    expected = ",".join(REQUIRED_COLUMNS) + "[," + ",".join(OPTIONAL_COLUMNS) + "]"
    if all(_is_number(c) for c in names):
        raise _err(path, line, f"missing header line; expected '{expected}' before the data")
    if any(n == "" for n in names):
        raise _err(path, line, f"empty column name in header (stray comma?); expected '{expected}'")
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise _err(path, line, f"duplicate column(s) {dup} in header")
    unknown = [n for n in names if n not in REQUIRED_COLUMNS + OPTIONAL_COLUMNS]
    if unknown:
        raise _err(path, line, f"unknown column(s) {unknown}; expected '{expected}'")
    missing = [n for n in REQUIRED_COLUMNS if n not in names]
    if missing:
        raise _err(path, line, f"missing column(s) {missing}; expected '{expected}'")
    return names


def _is_number(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def _short(s: str, n: int = 30) -> str:
    return repr(s if len(s) <= n else s[:n] + "...")


def read_trajectory(path: str | os.PathLike) -> Trajectory:
    """Read one trajectory CSV (see module docstring for the format).

    Returns:
        A validated :class:`Trajectory` (float64 arrays, ``source`` = file name).

    Raises:
        TrajectoryFileError: unreadable file, bad header, bad cell, too few rows,
            non-uniform or non-increasing time, or values in the wrong unit.
    """
    from ..io.safe_load import read_regular_file

    path = Path(path)
    # regular files only: a FIFO would block, /dev/zero would fill memory
    raw = read_regular_file(path, "trajectory file", TrajectoryFileError, max_bytes=MAX_FILE_BYTES)
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise TrajectoryFileError(f"{path}: not UTF-8 text (byte {e.start})") from None

    header: list[str] | None = None
    rows: list[list[float]] = []
    lines: list[int] = []
    # str.splitlines also splits on \x0b, \x1c, ... which would shift line numbers.
    for lineno, line in enumerate(text.split("\n"), start=1):
        line = line.rstrip("\r")
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        cells = line.split(",")
        if header is None:
            header = _parse_header(cells, path, lineno)
            continue
        if len(cells) != len(header):
            raise _err(
                path,
                lineno,
                f"row has {len(cells)} cell(s) but the header has {len(header)} column(s)",
            )
        row = []
        for name, cell in zip(header, cells):
            c = cell.strip()
            try:
                v = float(c)
            except ValueError:
                what = "empty cell" if not c else f"non-numeric value {_short(c)}"
                raise _err(path, lineno, f"column '{name}': {what}") from None
            if not math.isfinite(v):
                raise _err(path, lineno, f"column '{name}' is {_short(c)} (NaN/inf not allowed)")
            row.append(v)
        rows.append(row)
        lines.append(lineno)

    if header is None:
        raise _err(path, None, "file is empty (no header, no data)")
    if not rows:
        raise _err(path, None, "header only, no data rows")
    data = np.asarray(rows, dtype=float).reshape(len(rows), len(header))
    col = {name: data[:, j] for j, name in enumerate(header)}
    _validate_arrays(
        col["time"], col["force"], col["displacement"], col.get("velocity"), path, lines
    )
    return Trajectory(
        time=col["time"],
        force=col["force"],
        displacement=col["displacement"],
        velocity=col.get("velocity"),
        source=path.name,
    )


def write_trajectory(
    path: str | os.PathLike, traj: Trajectory, comments: Sequence[str] = ()
) -> Path:
    """Validate ``traj`` and write it atomically as CSV; floats round-trip exactly.

    The file begins with the header line (no comments), so any CSV reader parses it.

    Args:
        path: destination ``.csv``.
        traj: the trajectory; ``velocity`` is written only if not ``None``.
        comments: deprecated and ignored: provenance belongs in a JSON file beside the CSVs
            (see :func:`write_provenance`), not in the CSV where it breaks ``pandas.read_csv``.
    """
    if comments:
        import warnings

        warnings.warn(
            "write_trajectory(comments=...) is ignored: CSVs begin with the header line; "
            "write provenance with write_provenance()",
            DeprecationWarning,
            stacklevel=2,
        )
    traj = validate_trajectory(traj._replace(source=traj.source or str(path)))
    cols = [traj.time, traj.force, traj.displacement]
    names = list(REQUIRED_COLUMNS)
    if traj.velocity is not None:
        cols.append(traj.velocity)
        names.append("velocity")
    out = [",".join(names)]
    # repr() gives the shortest string that parses back to the same float64.
    out.extend(",".join(repr(float(v)) for v in row) for row in zip(*cols))
    return atomic_write_text(path, "\n".join(out) + "\n")


def _check_common_dt(trajs: Sequence[Trajectory], rtol: float, context: str) -> float:
    dts = [t.dt for t in trajs]
    ref = dts[0]
    bad = [(t.source, d) for t, d in zip(trajs, dts) if abs(d - ref) > rtol * abs(ref)]
    if bad:
        listed = ", ".join(f"{s or '<unnamed>'} (dt={d:.9g} s)" for s, d in bad)
        raise TrajectoryFileError(
            f"{context}: trajectories must share one time step; {trajs[0].source or '<unnamed>'} "
            f"has dt={ref:.9g} s but {listed}; resample them to a common step"
        )
    return float(ref)


def read_trajectory_dir(directory: str | os.PathLike, pattern: str = "*.csv") -> list[Trajectory]:
    """Read every file matching ``pattern`` in ``directory``, sorted by name.

    Raises:
        TrajectoryFileError: no such folder, no matching file, any bad file, or
            files whose time steps differ (the mismatched files are named).
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise TrajectoryFileError(f"{directory}: trajectory folder does not exist")
    files = sorted(p for p in directory.glob(pattern) if p.is_file())
    if not files:
        raise TrajectoryFileError(f"{directory}: no trajectory files matching '{pattern}'")
    trajs = [read_trajectory(p) for p in files]
    _check_common_dt(trajs, DIR_DT_RTOL, str(directory))
    return trajs


# ----------------------------------------------------------------------------- numerics


def velocity_from_displacement(displacement, dt):
    """Second-order finite-difference velocity along the last axis.

    Central differences inside, second-order one-sided differences at both ends:
    the scheme of ``numpy.gradient(x, dt, axis=-1, edge_order=2)``.

    Args:
        displacement: [..., T] metres, T >= 3; a jax array (works under jit/vmap)
            or a numpy array (then computed in numpy, keeping float64).
        dt: time step in seconds (scalar).

    Returns:
        [..., T] metres per second, same array type as ``displacement``.
    """
    # One formula for numpy and jax: numpy keeps float64 for data handling,
    # jnp makes it traceable for the simulator and likelihood.
    xp = np if isinstance(displacement, np.ndarray) and not isinstance(dt, jax.Array) else jnp
    x = xp.asarray(displacement)
    if x.shape[-1] < 3:
        raise ValueError(f"need at least 3 samples along the last axis, got shape {x.shape}")
    inv = 1.0 / (2.0 * dt)
    first = (-3.0 * x[..., 0:1] + 4.0 * x[..., 1:2] - x[..., 2:3]) * inv
    inner = (x[..., 2:] - x[..., :-2]) * inv
    last = (3.0 * x[..., -1:] - 4.0 * x[..., -2:-1] + x[..., -3:-2]) * inv
    return xp.concatenate([first, inner, last], axis=-1)


def ground_truth_velocity(traj: Trajectory) -> np.ndarray:
    """[T] m/s: the recorded velocity if present, else differentiated displacement."""
    if traj.velocity is not None:
        return np.asarray(traj.velocity, dtype=float)
    return velocity_from_displacement(np.asarray(traj.displacement, dtype=float), traj.dt)


def stack_trajectories(trajs: Sequence[Trajectory]) -> Observations:
    """Stack trajectories of one time step into padded ``[B, T]`` arrays.

    Shorter trajectories are padded with their last force/displacement value
    (velocity 0) and masked out (``mask`` False).

    Raises:
        TrajectoryFileError: empty input or differing time steps.
    """
    trajs = list(trajs)
    if not trajs:
        raise TrajectoryFileError("no trajectories given")
    dt = _check_common_dt(trajs, DIR_DT_RTOL, "stacking trajectories")
    b, t_max = len(trajs), max(t.n_steps for t in trajs)
    force = np.zeros((b, t_max))
    disp = np.zeros((b, t_max))
    vel = np.zeros((b, t_max))
    mask = np.zeros((b, t_max), dtype=bool)
    for i, tr in enumerate(trajs):
        n = tr.n_steps
        f = np.asarray(tr.force, dtype=float)
        x = np.asarray(tr.displacement, dtype=float)
        force[i, :n], force[i, n:] = f, f[-1]
        disp[i, :n], disp[i, n:] = x, x[-1]
        vel[i, :n] = ground_truth_velocity(tr)
        mask[i, :n] = True
    return Observations(force, disp, vel, mask, dt)


def add_noise(
    traj: Trajectory,
    sigma_force: float,
    sigma_displacement: float,
    rng: np.random.Generator | int,
) -> Trajectory:
    """Add independent Gaussian noise to force (N) and displacement (m).

    The recorded velocity is dropped, so :func:`ground_truth_velocity`
    recomputes it from the noisy displacement. ``rng`` is a numpy Generator or a seed.
    """
    if not (sigma_force >= 0 and sigma_displacement >= 0):
        raise ConfigError(
            f"noise standard deviations must be >= 0, got sigma_force={sigma_force}, "
            f"sigma_displacement={sigma_displacement}"
        )
    rng = np.random.default_rng(rng)
    f = np.asarray(traj.force, dtype=float)
    x = np.asarray(traj.displacement, dtype=float)
    return Trajectory(
        time=np.asarray(traj.time, dtype=float).copy(),
        force=f + sigma_force * rng.standard_normal(f.shape),
        displacement=x + sigma_displacement * rng.standard_normal(x.shape),
        velocity=None,
        source=f"{traj.source}+noise(force={sigma_force:g}N,disp={sigma_displacement:g}m)",
    )


# ==== force-profile files (treeinfer predict --force) ==========================================
class ForceProfile(NamedTuple):
    """A force profile to predict: ``time [T]`` s, ``force [T]`` N (downward); ``displacement
    [T]`` m when the file also recorded the response (drawn as ground truth), else None."""

    time: np.ndarray
    force: np.ndarray
    displacement: np.ndarray | None
    source: str

    @property
    def dt(self) -> float:
        return float((self.time[-1] - self.time[0]) / (len(self.time) - 1))


def read_force_profile(path: str | os.PathLike) -> ForceProfile:
    """A trajectory CSV (``time,force,displacement[,velocity]``) or a ``time,force`` CSV.

    The two-column form is checked like a trajectory (uniform increasing time in s, forces in N)
    and errors name the file and line."""
    from ..io.safe_load import read_regular_file

    path = Path(path)
    raw = read_regular_file(path, "force file", TrajectoryFileError, max_bytes=MAX_FILE_BYTES)
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise TrajectoryFileError(f"{path}: not UTF-8 text (byte {e.start})") from None
    lines = [(n, ln.rstrip("\r")) for n, ln in enumerate(text.split("\n"), start=1)]
    body = [(n, ln) for n, ln in lines if ln.strip() and not ln.strip().startswith("#")]
    if not body:
        raise TrajectoryFileError(
            f"{path}: file is empty (expected a header 'time,force' or 'time,force,displacement')"
        )
    header = [c.strip().strip('"').strip("'").lower() for c in body[0][1].split(",")]
    if "displacement" in header:
        tr = read_trajectory(path)
        return ForceProfile(tr.time, tr.force, tr.displacement, path.name)
    if sorted(header) != ["force", "time"]:
        raise TrajectoryFileError(
            f"{path}, line {body[0][0]}: header {header}; expected 'time,force' (a force "
            "profile) or 'time,force,displacement[,velocity]' (a trajectory)"
        )
    rows, where_line = [], []
    for n, ln in body[1:]:
        cells = ln.split(",")
        if len(cells) != 2:
            raise TrajectoryFileError(
                f"{path}, line {n}: row has {len(cells)} cell(s) but the header has 2 columns"
            )
        try:
            vals = [float(c) for c in cells]
        except ValueError:
            raise TrajectoryFileError(
                f"{path}, line {n}: non-numeric value in {ln.strip()!r}"
            ) from None
        if not all(math.isfinite(v) for v in vals):
            raise TrajectoryFileError(f"{path}, line {n}: NaN/inf not allowed")
        rows.append(vals)
        where_line.append(n)
    if not rows:
        raise TrajectoryFileError(f"{path}: header only, no data rows")
    a = np.asarray(rows, float)
    col = {name: a[:, j] for j, name in enumerate(header)}
    tr = validate_trajectory(
        Trajectory(col["time"], col["force"], np.zeros(len(a)), None, str(path))
    )
    return ForceProfile(tr.time, tr.force, None, path.name)
