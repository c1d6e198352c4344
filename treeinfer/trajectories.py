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

from ._io import atomic_write_text
from .errors import ConfigError, TrajectoryFileError, where

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

    i = int(np.argmax(np.abs(displacement)))
    if abs(displacement[i]) > MAX_DISPLACEMENT:
        raise _err(
            path,
            _line_of(lines, i),
            f"displacement {displacement[i]:g} exceeds {MAX_DISPLACEMENT:g} m; "
            "looks like millimetres, expected metres",
        )
    i = int(np.argmax(np.abs(force)))
    if abs(force[i]) > MAX_FORCE:
        raise _err(
            path,
            _line_of(lines, i),
            f"force {force[i]:g} N exceeds {MAX_FORCE:g} N, which is implausible for a branch; "
            "expected newtons",
        )
    if velocity is not None:
        i = int(np.argmax(np.abs(velocity)))
        if abs(velocity[i]) > MAX_VELOCITY:
            raise _err(
                path,
                _line_of(lines, i),
                f"velocity {velocity[i]:g} exceeds {MAX_VELOCITY:g} m/s; "
                "looks like millimetres per second, expected metres per second",
            )


def validate_trajectory(traj: Trajectory) -> Trajectory:
    """Return ``traj`` with float64 arrays after checking it as :func:`read_trajectory` would.

    Raises:
        TrajectoryFileError: naming ``traj.source`` and the problem.
    """
    arrs = [np.asarray(a, dtype=float) for a in (traj.time, traj.force, traj.displacement)]
    vel = None if traj.velocity is None else np.asarray(traj.velocity, dtype=float)
    _validate_arrays(*arrs, vel, traj.source or None)
    return Trajectory(*arrs, vel, traj.source)


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
    from .safe_load import read_regular_file

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


BAND_COLUMNS = ("time", "force", "recorded", "mean", "lower", "upper")


def band_csv_text(
    time,
    force,
    recorded,
    mean,
    lower,
    upper,
    predictive_lower=None,
    predictive_upper=None,
) -> str:
    """One recording's prediction as CSV text, header first, for users' own plots and scores.

    Columns ``time,force,recorded,mean,lower,upper`` (s, N, m, m, m, m): ``lower``/``upper``
    bound the 95% band over the parameters; with ``predictive_lower``/``predictive_upper``
    (the band including observation noise) two more columns of those names follow.
    ``recorded`` may be ``None`` (a force profile without displacement): an empty column;
    NaN (padding) is written as an empty cell too.
    """
    cols = [time, force, recorded, mean, lower, upper]
    names = list(BAND_COLUMNS)
    if predictive_lower is not None or predictive_upper is not None:
        if predictive_lower is None or predictive_upper is None:
            raise ConfigError("band CSV: give both predictive_lower and predictive_upper")
        cols += [predictive_lower, predictive_upper]
        names += ["predictive_lower", "predictive_upper"]
    n = len(np.asarray(time))
    arrs = []
    for name, c in zip(names, cols):
        if c is None:
            arrs.append(np.full(n, np.nan))
            continue
        a = np.asarray(c, dtype=float).reshape(-1)
        if a.shape[0] != n:
            raise ConfigError(f"band CSV: column '{name}' has {a.shape[0]} values, time {n}")
        arrs.append(a)
    out = [",".join(names)]
    out.extend(
        ",".join(repr(float(v)) if math.isfinite(v) else "" for v in row) for row in zip(*arrs)
    )
    return "\n".join(out) + "\n"


def write_band_csv(path: str | os.PathLike, *columns, **kwargs) -> Path:
    """Write :func:`band_csv_text` atomically to ``path`` (same arguments)."""
    return atomic_write_text(path, band_csv_text(*columns, **kwargs))


PROVENANCE_FILE = "import.json"


def write_provenance(directory: str | os.PathLike, entries: dict) -> Path:
    """Write ``<directory>/import.json``: how the folder's CSVs were made (JSON object; keys are
    free-form, e.g. ``{"source": ..., "options": {...}, "files": {"a.csv": [steps...]}}``)."""
    from ._io import atomic_write_json

    return atomic_write_json(Path(directory) / PROVENANCE_FILE, entries)


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


# ==== true_params.json: the one reader and writer ================================================
TRUE_PARAMS_FILE = "true_params.json"
GAIN_UNITS = {"kp": "N m/rad", "kd": "N m s/rad"}


def check_positive_params(values: Sequence[float], labels: Sequence[str], where: str) -> np.ndarray:
    """``values`` as a float array [len(labels)], each a positive finite number (ConfigError
    naming ``where`` and the label otherwise)."""
    from .errors import ConfigError

    if len(values) != len(labels):
        raise ConfigError(
            f"{where}: expected {len(labels)} numbers, in the order {', '.join(labels)}; "
            f"got {len(values)}"
        )
    out = np.empty(len(labels))
    for i, (v, lab) in enumerate(zip(values, labels)):
        try:
            f = float(v)
        except (TypeError, ValueError):
            raise ConfigError(f"{where}: {lab} must be a number, got {v!r}") from None
        if not (math.isfinite(f) and f > 0):
            raise ConfigError(f"{where}: {lab} must be a positive finite number, got {v!r}")
        out[i] = f
    return out


def read_true_params(tree, path: str | os.PathLike, where: str | None = None) -> np.ndarray:
    """True parameters [2R] (Kp of each inferred joint of ``tree``, then Kd; natural units) from
    a JSON file: a ``true_params.json`` (``{"kp": {joint: value}, "kd": {joint: value}}``),
    ``{"theta_log": [2R natural logs]}`` or a plain list of 2R numbers. ``where`` names the file
    in error messages (default: its path)."""

    from .errors import ConfigError

    labels = tree.parameter_labels()
    where = str(path) if where is None else where
    from .safe_load import load_file

    try:
        d = load_file(path, "parameter file", ConfigError, fmt="json")
    except ConfigError as e:
        msg = str(e)
        raise ConfigError(msg.replace(str(path), where, 1) if where != str(path) else msg) from None
    if isinstance(d, list):
        return check_positive_params(d, labels, where)
    if not isinstance(d, dict):
        raise ConfigError(
            f"{where}: expected an object with 'kp' and 'kd' (or 'theta_log'), or a list"
        )
    if "kp" in d or "kd" in d:
        vals = []
        for key in ("kp", "kd"):
            m = d.get(key)
            if not isinstance(m, dict):
                raise ConfigError(
                    f"{where}: field '{key}' must map joint names to values, got {m!r}"
                )
            missing = [n for n in tree.inferred if n not in m]
            extra = sorted(set(m) - set(tree.inferred))
            if missing or extra:
                raise ConfigError(
                    f"{where}: field '{key}' must give exactly the inferred joints "
                    f"{list(tree.inferred)}"
                    + (f"; missing {missing}" if missing else "")
                    + (f"; not inferred: {extra}" if extra else "")
                )
            vals += [m[n] for n in tree.inferred]
        return check_positive_params(vals, labels, where)
    if "theta_log" in d:
        t = d["theta_log"]
        if not isinstance(t, list) or len(t) != len(labels):
            raise ConfigError(
                f"{where}: field 'theta_log' must be a list of {len(labels)} numbers "
                f"({', '.join(labels)})"
            )
        try:
            vals = [math.exp(float(x)) for x in t]
        except (TypeError, ValueError, OverflowError):
            raise ConfigError(f"{where}: field 'theta_log' must hold numbers, got {t!r}") from None
        return check_positive_params(vals, labels, where)
    raise ConfigError(f"{where}: expected fields 'kp' and 'kd' (or 'theta_log'), found {sorted(d)}")


def true_params_record(tree, kp, kd, source: str, log_units: bool = True) -> dict:
    """The ``true_params.json`` object of gains ``kp``, ``kd`` [R] (natural units)."""
    units = dict(GAIN_UNITS)
    if log_units:
        units["theta_log"] = "natural log of kp, kd"
    return {
        "labels": tree.parameter_labels(),
        "kp": {n: float(v) for n, v in zip(tree.inferred, kp)},
        "kd": {n: float(v) for n, v in zip(tree.inferred, kd)},
        "theta_log": [float(math.log(v)) for v in np.concatenate([kp, kd])],
        "units": units,
        "source": source,
    }


def write_true_params(path: str | os.PathLike, record: dict) -> Path:
    """Write a :func:`true_params_record` atomically (JSON)."""
    from ._io import atomic_write_json

    return atomic_write_json(Path(path), record)


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
    from .safe_load import read_regular_file

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
