"""Import a logger's CSV files as treeinfer trajectories (``treeinfer import-csv``).

A load-cell/stepper logger writes columns in its own units (grams-force, millimetres,
milliseconds), its own time base (a counter that wraps around, jitter) and records idle time
before and after the push. :func:`import_csv` turns each source file into one standard
trajectory CSV (seconds, newtons, metres on a uniform grid; :mod:`treeinfer.data.trajectories`),
writes the data folder's ``pulls.yaml`` (grasp point and direction, :mod:`treeinfer.data.pulls`) and
``import.json`` (what was done to each file), and returns the list of every transformation it
applied, in order:

1. read the named columns (by header name, case-insensitive, or 0-based index);
2. time: seconds from the unit table; a backward jump (counter wrap-around) is detected and
   unwrapped with the median step; uneven steps (jitter) are resampled by linear interpolation
   onto a uniform grid; ``dt`` instead rebuilds a uniform base ``t = i dt`` (no time column, or
   one not to be trusted);
3. force and displacement to newtons and metres from the unit table;
4. ``tare``: subtract the mean force over the rest samples at the start;
5. ``trim``: drop the idle lead-in (force at rest and displacement still, widened to the foot of
   the ramp) and, only when the pull ends with a release (the force back at rest), the idle
   tail after it, keeping one rest sample on each side; a pull that ends on a loaded hold (a
   plateau of force, which identifies the stiffness best) keeps its end whole. What was removed
   is said in the steps and recorded in pulls.yaml (``trimmed``);
6. ``zero_displacement``: ``"first"`` subtracts the first sample's displacement; ``"contact"``
   keeps only the samples in contact (from the last rest sample before the force rises to the
   first after it returns to rest) and measures from the contact position (a line through the
   first loaded samples extrapolated to zero force; the last rest sample if too few);
7. a sign check: force and displacement should rise together (warns otherwise).

Errors raise :class:`~treeinfer.errors.TrajectoryFileError` naming the file and line.
"""

from __future__ import annotations

import json
import math
import os
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..errors import ConfigError, TrajectoryFileError
from ..io.atomic import atomic_write_text
from ..io.ownership import move_aside, refuse_overlap
from .csv_format import (  # noqa: F401 -- re-exported: the old import path keeps working
    DEFAULT_UNITS,
    DISPLACEMENT_UNITS,
    FORCE_UNITS,
    G0,
    JITTER_TOL,
    REST_FRACTION,
    REST_NOISE_FACTOR,
    TIME_UNITS,
    _rest_length,
    _robust_sd,
    _threshold,
    _time_base,
    parse_units,
    read_columns,
)
from .pulls import (
    PULLS_FILE,
    PullSpec,
    parse_direction,
    pulls_from_dict,
    read_pulls,
    spec_to_dict,
    write_pulls,
)
from .trajectories import (
    MIN_ROWS,
    PROVENANCE_FILE,
    Trajectory,
    validate_trajectory,
    write_trajectory,
)

__all__ = [
    "DISPLACEMENT_UNITS",
    "FORCE_UNITS",
    "TIME_UNITS",
    "ImportResult",
    "convert_file",
    "import_csv",
    "parse_units",
    "read_columns",
]

ZERO_MODES = ("first", "contact", None)


class ImportResult(NamedTuple):
    """What :func:`import_csv` wrote.

    Attributes:
        paths: the trajectory CSVs written, in source order.
        sidecar: the data folder's ``pulls.yaml``.
        steps: per written CSV name, the transformations applied, in order (plain sentences).
    """

    paths: list[Path]
    sidecar: Path
    steps: dict[str, list[str]]

    def report(self) -> str:
        """The steps as printable text, one block per file."""
        out = []
        for name, steps in self.steps.items():
            out.append(f"{name}:")
            out.extend(f"  - {s}" for s in steps)
        return "\n".join(out)


class Trimmed(NamedTuple):
    """What ``trim`` removed from one recording: ``lead_in`` samples before the pull, ``tail``
    samples after the release; ``ends`` is ``"release"`` (the force back at rest at the end)
    or ``"loaded hold"`` (force still applied: the end is kept whole)."""

    lead_in: int
    tail: int
    n: int
    ends: str

    def sentence(self, t: np.ndarray) -> str:
        head = (
            f"trim: dropped {self.lead_in} idle sample(s) of lead-in (t < {t[self.lead_in]:g} s)"
            if self.lead_in
            else "trim: no idle lead-in to drop"
        )
        if self.ends == "loaded hold":
            tail = "kept the end whole: the pull ends on a loaded hold (force still applied)"
        elif self.tail:
            tail = (
                f"dropped {self.tail} idle sample(s) after the release "
                f"(t > {t[self.n - self.tail - 1]:g} s)"
            )
        else:
            tail = "no idle tail after the release to drop"
        return f"{head}; {tail} (one rest sample kept on each trimmed side)"

    def record(self, t: np.ndarray) -> dict:
        """The pulls.yaml entry's ``trimmed`` field (s of the source's time base)."""
        return {
            "lead_in_samples": int(self.lead_in),
            "tail_samples": int(self.tail),
            "kept_from_s": float(round(t[self.lead_in] - t[0], 9)),
            "kept_to_s": float(round(t[self.n - self.tail - 1] - t[0], 9)),
            "ends_with": self.ends,
        }


def _trim_bounds(f: np.ndarray, x: np.ndarray, thr: float, path) -> tuple[int, int, Trimmed]:
    """``(lo, hi, Trimmed)``: the samples ``[lo, hi)`` that ``trim`` keeps.

    The lead-in is idle while the force stays at its starting rest level and the displacement
    still. The tail is idle only after a release: when the last samples' force is back at the
    starting rest level (within the activity threshold). A pull that ends with force still
    applied ends on a loaded hold, the samples that identify the stiffness best, and keeps
    its end whole (issue 29: the old rule took the last samples' level as "rest" and cut the
    whole hold away)."""
    rest = float(np.median(f[:3]))
    xthr = max(REST_FRACTION * float(np.ptp(x)), REST_NOISE_FACTOR * _robust_sd(x), 1e-15)
    a = np.abs(f - rest)
    first_active = np.flatnonzero((a > thr) | (np.abs(x - x[0]) > xthr))
    if first_active.size == 0:
        raise TrajectoryFileError(
            f"{path}: nothing happens in this recording (force and displacement at rest "
            "throughout); nothing to import"
        )
    # widen to the foot of the ramp (as bags.find_pulls): the first samples of a slow ramp sit
    # below the threshold but are already part of the push
    s = int(first_active[0])
    while s > 0 and a[s - 1] < a[s]:
        s -= 1
    lo, hi = max(0, s - 1), f.size
    released = abs(float(np.median(f[-3:])) - rest) <= thr
    if released:
        # the release's own rest level (a load cell may drift a little over the pull)
        b = np.abs(f - np.median(f[-3:]))
        last_active = np.flatnonzero((b > thr) | (np.abs(x - x[-1]) > xthr))
        e = int(last_active[-1]) if last_active.size else f.size - 1
        while e < f.size - 1 and b[e + 1] < b[e]:
            e += 1
        hi = min(f.size, e + 2)
    ends = "release" if released else "loaded hold"
    return lo, hi, Trimmed(lo, f.size - hi, f.size, ends)


def convert_file(
    path: str | os.PathLike,
    *,
    time: str | int | None = "time",
    force: str | int = "force",
    displacement: str | int = "displacement",
    units: str | Mapping[str, str] | None = None,
    dt: float | None = None,
    tare: bool = False,
    zero_displacement: str | None = "first",
    trim: bool = False,
    delimiter: str | None = None,
    record: dict | None = None,
) -> tuple[Trajectory, list[str]]:
    """Convert one logger CSV into a :class:`Trajectory` (see the module docstring).

    ``record``: a dict that receives what ``trim`` removed (:meth:`Trimmed.record`), for the
    data folder's pulls.yaml.

    Returns:
        (trajectory in s, N, m on a uniform grid starting at 0, list of steps applied).

    Raises:
        TrajectoryFileError: naming file and line (columns, cells, time base, too few rows).
        ConfigError: bad options.
    """
    path = Path(path)
    u = parse_units(units)
    if dt is not None and not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
        raise ConfigError(f"dt: must be a positive number of seconds, got {dt!r}")
    if zero_displacement not in ZERO_MODES:
        raise ConfigError(
            f"zero_displacement: expected 'first', 'contact' or None, got {zero_displacement!r}"
        )
    if time is None and dt is None:
        raise ConfigError(f"{path}: no time column given; give dt (--dt) to build a time base")
    cols = read_columns(
        path, {"time": time, "force": force, "displacement": displacement}, delimiter
    )
    steps = [
        f"read {cols.lines.size} rows of {path.name}: "
        + ", ".join(f"{q} <- column '{c}'" for q, c in cols.names.items())
    ]
    n = cols.lines.size
    t, uniform = _time_base(cols.values.get("time"), u["time"], dt, n, path, cols.lines, steps)
    f = cols.values["force"] * FORCE_UNITS[u["force"]]
    x = cols.values["displacement"] * DISPLACEMENT_UNITS[u["displacement"]]
    if u["force"] != "N":
        steps.append(f"force: {u['force']} -> N (x {FORCE_UNITS[u['force']]:.9g})")
    if u["displacement"] != "m":
        steps.append(
            f"displacement: {u['displacement']} -> m (x {DISPLACEMENT_UNITS[u['displacement']]:g})"
        )
    if not uniform:
        step = float(np.median(np.diff(t)))
        grid = t[0] + step * np.arange(int(np.floor((t[-1] - t[0]) / step + 1e-9)) + 1)
        f, x = np.interp(grid, t, f), np.interp(grid, t, x)
        t = grid
    if t.size < MIN_ROWS:
        raise TrajectoryFileError(f"{path}: only {t.size} samples after resampling")

    thr = _threshold(f)
    if tare:
        n_rest = _rest_length(f, thr)
        if n_rest < 1:
            raise TrajectoryFileError(
                f"{path}: cannot tare: the force is not at rest at the start (first sample "
                "already above the activity threshold)"
            )
        n_rest = min(n_rest, f.size)
        offset = float(np.mean(f[:n_rest]))
        f = f - offset
        steps.append(
            f"tare: subtracted {offset:.6g} N (mean force over the first {n_rest} samples, at rest)"
        )
        thr = _threshold(f)
    lo, hi = 0, f.size
    if trim:
        lo, hi, trimmed = _trim_bounds(f, x, thr, path)
        steps.append(trimmed.sentence(t))
        if record is not None:
            record.update(trimmed.record(t))
    x_contact = None
    if zero_displacement == "contact":
        base = np.median(f[lo : lo + 3])
        a = np.abs(f - base)
        active = lo + np.flatnonzero(a[lo:hi] > thr)
        if active.size == 0:
            raise TrajectoryFileError(f"{path}: no contact found: the force never rises")
        c = int(active[0])
        while c > lo and a[c - 1] < a[c]:  # back to the foot of the ramp: the last rest sample
            c -= 1
        e = int(active[-1])
        while e < hi - 1 and a[e + 1] < a[e]:  # forward to the foot of the release
            e += 1
        if c > lo:
            steps.append(
                f"contact: dropped {c - lo} approach sample(s) before the force rises "
                f"(t = {t[c] - t[0]:g} s)"
            )
        if e + 1 < hi:
            steps.append(
                f"contact: dropped {hi - e - 1} sample(s) after the force returns to rest "
                "(contact lost: displacement no longer the branch's)"
            )
        # Contact lies between two samples; a line through the first loaded samples
        # (threshold .. 30% of the peak) extrapolated to zero force locates it.
        peak = c + int(np.argmax(a[c : e + 1]))
        rise = np.arange(c, peak + 1)
        sel = rise[(a[rise] > thr) & (a[rise] <= 0.3 * a[peak])]
        if sel.size >= 3 and np.ptp(f[sel]) > 0:
            _, icpt = np.polyfit(f[sel] - base, x[sel], 1)
            x_contact = float(icpt)
            steps.append(
                f"contact position from a line through {sel.size} early loaded samples "
                f"extrapolated to zero force: {x_contact:.6g} m"
            )
        lo, hi = c, e + 1
    t, f, x = t[lo:hi], f[lo:hi], x[lo:hi]
    if t.size < MIN_ROWS:
        raise TrajectoryFileError(
            f"{path}: only {t.size} sample(s) left after trimming; at least {MIN_ROWS} needed"
        )
    if zero_displacement is not None:
        x0 = float(x[0]) if x_contact is None else x_contact
        x = x - x0
        what = "the first sample" if zero_displacement == "first" else "contact"
        steps.append(f"displacement measured from {what} (subtracted {x0:.6g} m)")
    t = t - t[0]
    if f.size >= 3 and np.std(f) > 0 and np.std(x) > 0:
        r = float(np.corrcoef(f, x)[0, 1])
        if r < 0:
            msg = (
                f"{path}: force and displacement move in opposite directions (correlation "
                f"{r:.2f}); check the sign of the load cell or of the displacement"
            )
            warnings.warn(msg, stacklevel=2)
            steps.append(f"WARNING: {msg.split(': ', 1)[1]}")
    traj = validate_trajectory(Trajectory(t, f, x, None, path.name))
    return traj, steps


def _per_source(value, n: int, name: str) -> list:
    if value is None or isinstance(value, (str, int, float)):
        return [value] * n
    vals = list(value)
    if len(vals) != n:
        raise ConfigError(f"{name}: {len(vals)} value(s) given for {n} source file(s)")
    return vals


def import_csv(
    sources: Sequence[str | os.PathLike],
    out: str | os.PathLike,
    *,
    time: str | int | None = "time",
    force: str | int = "force",
    displacement: str | int = "displacement",
    units: str | Mapping[str, str] | None = None,
    dt: float | None = None,
    tare: bool = False,
    zero_displacement: str | None = "first",
    trim: bool = False,
    grasp_branch: str | None = None,
    grasp_fraction=None,
    grasp_distance=None,
    direction=None,
    delimiter: str | None = None,
    overwrite: bool = False,
    tree=None,
) -> ImportResult:
    """Convert logger CSVs into a treeinfer data folder.

    Each source becomes ``<out>/<source stem>.csv``; ``<out>/pulls.yaml`` gets one entry per
    written file (merged into an existing one, so several calls with different grasp points
    fill one folder); ``<out>/import.json`` records the source, options and steps per file.

    Args:
        sources: logger CSV files.
        out: data folder (created; existing files are kept, same-named CSVs need ``overwrite``).
        time, force, displacement: columns, by header name (case-insensitive) or 0-based index;
            ``time=None`` with ``dt``: no time column.
        units: ``"time=ms,force=gf,displacement=mm"`` or a mapping; see the unit tables.
        dt: s; rebuild a uniform time base ``i * dt`` (time column missing or unreliable).
        tare: subtract the rest force at the start.
        zero_displacement: ``"first"``, ``"contact"`` or ``None`` (keep as logged).
        trim: drop idle samples at the start and end.
        grasp_branch, grasp_fraction | grasp_distance: grasp point written to the sidecar
            (scalars, or one value per source).
        direction: ``down``, ``horizontal``, a vector or ``"x,y,z"`` (one, or one per source).
        tree: if given, the sidecar entries are validated against it.

    Returns:
        :class:`ImportResult` (paths, sidecar, steps per file).
    """
    sources = [Path(s) for s in sources]
    if not sources:
        raise ConfigError("import-csv: no source files given")
    n = len(sources)
    branches = _per_source(grasp_branch, n, "grasp_branch")
    fracs = _per_source(grasp_fraction, n, "grasp_fraction")
    dists = _per_source(grasp_distance, n, "grasp_distance")
    dirs = (
        [direction] * n
        if direction is None
        or isinstance(direction, str)
        or (len(direction) == 3 and not isinstance(direction[0], (str, list, tuple)))
        else _per_source(direction, n, "direction")
    )
    if any(a is not None for a in fracs) and any(b is not None for b in dists):
        raise ConfigError(
            "give either grasp_fraction (--grasp-fraction) or grasp_distance "
            "(--grasp-distance), not both"
        )
    names = [s.stem + ".csv" for s in sources]
    dup = sorted({m for m in names if names.count(m) > 1})
    if dup:
        raise ConfigError(f"import-csv: several sources would be written as {dup}; rename them")
    out = Path(out)
    # the data folder may not be, hold or lie inside a source (a converted file would replace
    # its own source, or the next import would read its own output)
    refuse_overlap(out, sources, "data folder")
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{out}: exists and is not a folder")
    if not overwrite:
        clash = [m for m in names if (out / m).exists()]
        if clash:
            raise ConfigError(f"{out}: already holds {clash}; pass --force to replace them")
    specs = {}
    for m, b, fr, di, dr in zip(names, branches, fracs, dists, dirs):
        specs[m] = PullSpec(
            branch=b,
            fraction=None if fr is None else float(fr),
            distance=None if di is None else float(di),
            direction=None if dr is None else parse_direction(dr, f"direction for {m}"),
        )
    side = out / PULLS_FILE
    # not is_file(): a FIFO or folder named pulls.yaml is refused by the reader, not replaced
    existing = read_pulls(side, tree) if side.exists() or side.is_symlink() else None
    merged = dict(existing.pulls) if existing else {}
    merged.update(specs)
    # validate the sidecar before converting (cheap, and nothing is written on error)
    pulls_from_dict(
        {
            "default": spec_to_dict(existing.default) if existing else None,
            "pulls": {k: spec_to_dict(v) for k, v in merged.items()},
        },
        tree,
        str(side),
    )
    results, records = [], []
    for src in sources:
        records.append({})
        results.append(
            convert_file(
                src,
                time=time,
                force=force,
                displacement=displacement,
                units=units,
                dt=dt,
                tare=tare,
                zero_displacement=zero_displacement,
                trim=trim,
                delimiter=delimiter,
                record=records[-1],
            )
        )
    for m, rec in zip(names, records):  # what --trim removed, beside the grasp point
        if rec:
            merged[m] = merged[m]._replace(trimmed=rec)
    out.mkdir(parents=True, exist_ok=True)
    paths, steps = [], {}
    for (traj, st), m, src in zip(results, names, sources):
        move_aside(out / m, what="trajectory file")  # --force keeps the one it replaces
        p = write_trajectory(out / m, traj._replace(source=m))
        paths.append(p)
        steps[m] = st + [f"wrote {m}: {traj.n_steps} samples, dt {traj.dt:g} s"]
    header = "grasp point and pull direction per trajectory (treeinfer import-csv)"
    write_pulls(side, merged, existing.default if existing else None, header)
    prov_path = out / PROVENANCE_FILE
    prov = {}
    if prov_path.is_file():
        try:
            prov = json.loads(prov_path.read_text())
        except (OSError, ValueError):
            prov = {}
    files = prov.setdefault("files", {})
    options = {
        "time": time,
        "force": force,
        "displacement": displacement,
        "units": parse_units(units),
        "dt": dt,
        "tare": tare,
        "zero_displacement": zero_displacement,
        "trim": trim,
    }
    for m, src in zip(names, sources):
        files[m] = {
            "tool": "treeinfer import-csv",
            "source": str(src),
            "options": options,
            "steps": steps[m],
        }
    atomic_write_text(prov_path, json.dumps(prov, indent=2, sort_keys=True) + "\n")
    return ImportResult(paths, side, steps)
