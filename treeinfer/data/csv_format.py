"""Reading a user's CSV for ``treeinfer import-csv`` (:mod:`treeinfer.data.import_csv`): the unit
tables and ``--units`` parsing, delimiter sniffing and column selection by name or index, and the
time base (wrap-around, jitter, ``--dt``); errors name the file and line. Re-exported by
:mod:`treeinfer.data.import_csv`."""

from __future__ import annotations

import csv
import io
import math
import os
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..errors import ConfigError, TrajectoryFileError, where
from .trajectories import DT_REL_TOL, MIN_ROWS, _is_number

G0 = 9.80665  # m/s^2, standard gravity (definition of the kilogram-force)
TIME_UNITS = {"s": 1.0, "ms": 1e-3}
FORCE_UNITS = {
    "N": 1.0,
    "mN": 1e-3,
    "kN": 1e3,
    "gf": G0 * 1e-3,
    "kgf": G0,
    "lbf": 0.45359237 * G0,  # avoirdupois pound (exact) times standard gravity
}
DISPLACEMENT_UNITS = {"m": 1.0, "cm": 1e-2, "mm": 1e-3, "in": 0.0254}
_TABLES = {"time": TIME_UNITS, "force": FORCE_UNITS, "displacement": DISPLACEMENT_UNITS}
DEFAULT_UNITS = {"time": "s", "force": "N", "displacement": "m"}
REST_FRACTION = 0.05  # activity threshold: this share of the largest |tared force|
REST_NOISE_FACTOR = 4.0  # ... or this many robust noise standard deviations, whichever is larger
JITTER_TOL = DT_REL_TOL  # relative step deviation above which times are resampled
# ----------------------------------------------------------------------------- units


def _unit_key(table: Mapping[str, float], unit: str, quantity: str) -> str:
    for k in table:
        if k == unit:
            return k
    lower = {k.lower(): k for k in table}
    if unit.lower() in lower and unit not in ("MN",):  # "MN" (meganewton) is not "mN"
        return lower[unit.lower()]
    raise ConfigError(f"units: unknown {quantity} unit {unit!r}; known: {', '.join(table)}")


def parse_units(units: str | Mapping[str, str] | None) -> dict[str, str]:
    """``"time=ms,force=gf,displacement=mm"`` (or a mapping) -> canonical unit names.

    Quantities not given keep s, N, m.

    Raises:
        ConfigError: unknown quantity or unit, malformed text.
    """
    out = dict(DEFAULT_UNITS)
    if units is None:
        return out
    if isinstance(units, str):
        pairs = {}
        for part in [p.strip() for p in units.split(",") if p.strip()]:
            if "=" not in part:
                raise ConfigError(
                    f"units: expected quantity=unit pairs like 'time=ms,force=gf', got {part!r}"
                )
            k, v = (s.strip() for s in part.split("=", 1))
            pairs[k] = v
        units = pairs
    for k, v in units.items():
        q = str(k).strip().lower()
        if q not in _TABLES:
            raise ConfigError(f"units: unknown quantity {k!r}; expected time, force, displacement")
        out[q] = _unit_key(_TABLES[q], str(v).strip(), q)
    return out


# ----------------------------------------------------------------------------- reading


class _Columns(NamedTuple):
    values: dict[str, np.ndarray]  # quantity -> [N] raw floats
    lines: np.ndarray  # [N] 1-based file line of each row
    names: dict[str, str]  # quantity -> column as found ("force" or "#2")


def _sniff_delimiter(sample: str) -> str:
    try:
        return csv.Sniffer().sniff(sample, delimiters=",;\t ").delimiter
    except csv.Error:
        return ","


def _pick(spec: str | int, header: list[str] | None, ncols: int, path, line, quantity) -> int:
    """Index of the column ``spec`` (header name, case-insensitive, or 0-based index)."""
    if isinstance(spec, str):
        key = spec.strip().strip('"').lower()
        if header is not None:
            names = [h.strip().strip('"').lower() for h in header]
            if key in names:
                return names.index(key)
        if not key.lstrip("-").isdigit():
            found = ", ".join(repr(h) for h in header) if header else "(no header line)"
            raise TrajectoryFileError(
                f"{where(path, line)}: no {quantity} column named {spec!r}; columns: {found}"
            )
        spec = int(key)
    if not 0 <= spec < ncols:
        raise TrajectoryFileError(
            f"{where(path, line)}: {quantity} column index {spec} is out of range; "
            f"the file has {ncols} column(s), numbered from 0"
        )
    return spec


def read_columns(
    path: str | os.PathLike,
    columns: Mapping[str, str | int | None],
    delimiter: str | None = None,
) -> _Columns:
    """Read the wanted columns of a logger CSV as floats.

    ``#`` comment lines and blank lines are skipped anywhere; the first other line is a header
    if any of its cells is not a number. Delimiter: sniffed among ``, ; tab space`` unless given.

    Args:
        columns: quantity -> column (name or 0-based index), ``None`` to skip.

    Raises:
        TrajectoryFileError: naming file and line: unreadable, missing column, ragged row,
            non-numeric or empty cell.
    """
    from ..io.safe_load import read_regular_file
    from .types import MAX_FILE_BYTES

    path = Path(path)
    try:  # a FIFO or device is refused unopened; a huge file before it is read
        raw = read_regular_file(path, "CSV file", TrajectoryFileError, max_bytes=MAX_FILE_BYTES)
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise TrajectoryFileError(f"{path}: not UTF-8 text (byte {e.start})") from None
    rows: list[tuple[int, str]] = []
    for lineno, line in enumerate(text.split("\n"), start=1):
        line = line.rstrip("\r")
        if line.strip() and not line.lstrip().startswith("#"):
            rows.append((lineno, line))
    if not rows:
        raise TrajectoryFileError(f"{path}: no data (only blank or comment lines)")
    delim = delimiter or _sniff_delimiter("\n".join(r for _, r in rows[:20]))

    def split(line: str, lineno: int) -> list[str]:
        try:
            cells = next(csv.reader(io.StringIO(line), delimiter=delim, skipinitialspace=True))
        except csv.Error as e:  # e.g. a field over the csv module's size limit
            raise TrajectoryFileError(
                f"{path}, line {lineno}: cannot split the line ({e})"
            ) from None
        if delim == " ":
            cells = [c for c in cells if c != ""]
        return [c.strip() for c in cells]

    first_line, first = rows[0]
    cells = split(first, first_line)
    header = None if all(_is_number(c) for c in cells) else cells
    ncols = len(cells)
    wanted = {q: c for q, c in columns.items() if c is not None}
    index = {q: _pick(c, header, ncols, path, first_line, q) for q, c in wanted.items()}
    names = {q: (header[i] if header is not None else f"#{i}") for q, i in index.items()}
    data_rows = rows[1:] if header is not None else rows
    vals = {q: [] for q in index}
    lines = []
    for lineno, line in data_rows:
        cells = split(line, lineno)
        if len(cells) != ncols:
            raise TrajectoryFileError(
                f"{where(path, lineno)}: row has {len(cells)} cell(s) but the "
                f"{'header' if header is not None else 'first row'} has {ncols}"
            )
        for q, i in index.items():
            c = cells[i]
            try:
                v = float(c)
            except ValueError:
                what = "empty cell" if not c else f"non-numeric value {c[:30]!r}"
                raise TrajectoryFileError(
                    f"{where(path, lineno)}, column '{names[q]}' ({q}): {what}"
                ) from None
            if not math.isfinite(v):
                raise TrajectoryFileError(
                    f"{where(path, lineno)}, column '{names[q]}' ({q}): {c!r} (NaN/inf)"
                )
            vals[q].append(v)
        lines.append(lineno)
    if len(lines) < MIN_ROWS:
        raise TrajectoryFileError(
            f"{path}: only {len(lines)} data row(s); at least {MIN_ROWS} are needed"
        )
    return _Columns({q: np.asarray(v, float) for q, v in vals.items()}, np.asarray(lines), names)


# ----------------------------------------------------------------------------- processing


def _robust_sd(x: np.ndarray) -> float:
    """Noise standard deviation from first differences (MAD; insensitive to slow ramps)."""
    d = np.diff(x)
    if d.size == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2.0))


def _rest_length(f: np.ndarray, threshold: float) -> int:
    """Number of leading samples at rest: up to the foot of the first ramp (the last sample
    before |f - rest| starts rising towards the first sample above ``threshold``)."""
    base = float(np.median(f[: max(3, min(10, f.size // 20))]))
    a = np.abs(f - base)
    active = np.flatnonzero(a > threshold)
    if not active.size:
        return int(f.size)
    n = int(active[0])
    if n == 0:
        return 0
    while n > 0 and a[n - 1] < a[n]:  # the slow start of a ramp is below the threshold
        n -= 1
    return n + 1


def _threshold(f: np.ndarray) -> float:
    span = float(np.max(np.abs(f - np.median(f[:3]))))
    return max(REST_FRACTION * span, REST_NOISE_FACTOR * _robust_sd(f), 1e-12)


def _time_base(
    t_raw: np.ndarray | None,
    t_unit: str,
    dt: float | None,
    n: int,
    path,
    lines: np.ndarray,
    steps: list[str],
) -> tuple[np.ndarray, bool]:
    """Seconds [N]; returns (time, uniform). ``uniform`` False means resampling is needed."""
    if t_raw is None:
        steps.append(f"no time column: uniform time base t = i * {dt:g} s")
        return dt * np.arange(n), True
    t = t_raw * TIME_UNITS[t_unit]
    if t_unit != "s":
        steps.append(f"time: {t_unit} -> s (x {TIME_UNITS[t_unit]:g})")
    d = np.diff(t)
    back = np.flatnonzero(d <= 0)
    pos = d[d > 0]
    if back.size:
        i = int(back[0]) + 1
        drop = float(t[i - 1] - t[i])
        wraps = [int(k) + 1 for k in back if (t[k] - t[k + 1]) > 0.25 * (np.ptp(t) or 1.0)]
        kind = "wraps around" if wraps else "goes backwards"
        msg = (
            f"time column {kind} at {where(path, int(lines[i]))} "
            f"({t[i - 1]:g} s -> {t[i]:g} s, a drop of {drop:g} s)"
        )
        if dt is None:
            if not wraps or len(wraps) != back.size or pos.size == 0:
                raise TrajectoryFileError(
                    f"{msg}; give --dt to rebuild a uniform time base from the sample rate"
                )
            step = float(np.median(pos))
            jumps = np.zeros(n)
            for k in wraps:
                jumps[k] = t[k - 1] - t[k] + step
            t = t + np.cumsum(jumps)
            steps.append(
                f"{msg}: counter wrap-around; unwrapped {len(wraps)} time(s) assuming the "
                f"median step {step:g} s across each wrap"
            )
        else:
            steps.append(f"{msg}: counter wrap-around; time column replaced (see --dt)")
    if dt is not None:
        med = float(np.median(pos)) if pos.size else float("nan")
        note = ""
        if math.isfinite(med) and abs(med - dt) > 0.05 * dt:
            note = f" (the time column's median step is {med:g} s)"
            warnings.warn(f"{path}: --dt {dt:g} s differs from the time column{note}", stacklevel=3)
        steps.append(f"time column ignored: uniform time base t = i * {dt:g} s{note}")
        return dt * np.arange(n), True
    d = np.diff(t)
    step = float(np.median(d))
    if step <= 0:
        raise TrajectoryFileError(f"{path}: time column does not increase")
    dev = np.abs(d - step) / step
    if np.any(dev > JITTER_TOL):
        steps.append(
            f"time steps vary from {d.min():g} s to {d.max():g} s (jitter; median {step:g} s): "
            f"resampled by linear interpolation onto a uniform {step:g} s grid"
        )
        return t, False
    return t, True
