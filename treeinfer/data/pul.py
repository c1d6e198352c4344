"""Read ``.pul`` files: static winch pulling tests of trees (force in the cable, two 2-axis
inclinometers, elastometers), as written by the logger used by Hill, Bennion & Lovelock (2024),
*Mangrove tree strength estimated with field experiments*, Ecological Engineering 203: 107259,
doi:10.1016/j.ecoleng.2024.107259 (data: ``jack-w-hill/mangrove-tree-strength``).

A ``.pul`` file is one JSON object::

    {"name": ..., "inclino_tara": "x;y", "inclino2_tara": "x;y", "force_tara": "0",
     "dlen_tara": "n1;n2", "data": [cycle, ...]}

and each polling cycle holds one reading per sensor, ``{"val", "raw", "timestamp"}``:

* ``inclino``/``inclino2``: ``raw`` ``"X=+00.026\\r\\nY=+00.038"``, two-axis tilt in degrees;
  ``val`` is the *unsigned* resultant change since the tare, so this reader keeps the raw axes
  (the signed tilt along the pull is made in :mod:`treeinfer.data.pull_test`);
* ``force``: ``raw`` ``"    0.44M\\x03\\x02"``: kN (a leading ``-`` when negative, a status
  letter, control characters); ``val`` is ``raw`` x 101.9534 (kgf);
* ``dlen``: elastometer counters (read for completeness, not used by the model);
* ``timestamp``: ISO 8601 with 7 decimals and a UTC offset (``datetime.fromisoformat`` takes at
  most 6 on Python 3.11, hence the regular expression).

A cycle may lack a sensor (kept as a missing reading). Malformed content raises
:class:`~treeinfer.errors.TrajectoryFileError` naming the file, the line and the field
(``data[i].force.raw``); the files are usually one line, so the message also gives the cycle
index and the column.
"""

from __future__ import annotations

import datetime
import json
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import TrajectoryFileError, where
from ..io.safe_load import read_regular_file

__all__ = ["INCLINOMETERS", "PUL_SUFFIX", "PulFile", "SensorSeries", "read_pul"]

PUL_SUFFIX = ".pul"
INCLINOMETERS = ("inclino", "inclino2")
MAX_PUL_BYTES = 200 * 1024 * 1024  # the public files are 0.3-2 MB

_TIME = re.compile(r"^(\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d)(\.\d+)?(Z|[+-]\d\d:\d\d)?$")
_XY = re.compile(r"^\s*X=\s*([+-]?\d+(?:\.\d*)?)\s*[\r\n]+\s*Y=\s*([+-]?\d+(?:\.\d*)?)\s*$")
_FORCE = re.compile(r"^[\s\x00-\x1f]*(-?)\s*(\d+(?:\.\d*)?)\s*([A-Za-z]?)[\s\x00-\x1f]*$")
_DLEN = re.compile(r"^\s*\[\s*(-?\d+)\s*,\s*(-?\d+)\s*\]\s*$")


@dataclass(frozen=True)
class SensorSeries:
    """One sensor's readings in file order: ``t`` [n] s since the epoch, ``values`` [n] or
    [n, 2] (inclinometer X, Y in degrees; force in kN; elastometer counts), ``cycle`` [n] the
    index of each reading's cycle in ``data``."""

    t: np.ndarray
    values: np.ndarray
    cycle: np.ndarray

    @property
    def n(self) -> int:
        return int(self.t.size)


@dataclass(frozen=True)
class PulFile:
    """A parsed ``.pul`` file: the raw sensor series and the tares (``inclino`` X, Y in degrees;
    ``dlen`` counts). ``inclinometers`` holds the channels present (trees 1-3 have one)."""

    path: Path
    name: str
    n_cycles: int
    force: SensorSeries  # kN, as in ``raw``
    inclinometers: dict[str, SensorSeries]  # raw X, Y in degrees (tare not subtracted)
    tares: dict[str, tuple[float, ...]]
    dlen: SensorSeries | None = None


def _line_col(text: str, pos: int) -> tuple[int, int]:
    line = text.count("\n", 0, pos) + 1
    return line, pos - (text.rfind("\n", 0, pos) + 1) + 1


def _cycle_positions(text: str) -> list[int]:
    """Character offset of each element of the top-level ``data`` array (for error messages
    only: the content is parsed by ``json.loads``)."""
    m = re.search(r'"data"\s*:\s*\[', text)
    if m is None:
        return []
    dec, pos, out = json.JSONDecoder(), m.end(), []
    while True:
        while pos < len(text) and text[pos] in " \t\r\n,":
            pos += 1
        if pos >= len(text) or text[pos] == "]":
            return out
        out.append(pos)
        try:
            _, pos = dec.raw_decode(text, pos)
        except ValueError:
            return out


class _Where:
    """Locates a cycle in the file's text, lazily (only when there is an error to report)."""

    def __init__(self, path: Path, text: str):
        self.path, self.text, self._pos = path, text, None

    def __call__(self, i: int | None, fld: str) -> str:
        if i is None:
            return where(self.path, None, fld)
        if self._pos is None:
            self._pos = _cycle_positions(self.text)
        if i < len(self._pos):
            line, col = _line_col(self.text, self._pos[i])
            return f"{where(self.path, line, f'data[{i}].{fld}')} (cycle {i}, column {col})"
        return where(self.path, None, f"data[{i}].{fld}")


def _text(loc) -> str:
    """A location: a string, or a callable that makes one (only when an error is raised: a
    cycle's line is found by scanning the file)."""
    return loc() if callable(loc) else str(loc)


def parse_timestamp(s: object, loc) -> float:
    """``'2023-05-03T15:05:21.0982130+10:00'`` -> seconds since the epoch (float)."""
    m = _TIME.match(s) if isinstance(s, str) else None
    if m is None:
        raise TrajectoryFileError(f"{_text(loc)}: not an ISO 8601 timestamp: {s!r}")
    tz = m.group(3) or "+00:00"
    tz = "+00:00" if tz == "Z" else tz
    try:
        base = datetime.datetime.fromisoformat(m.group(1) + tz).timestamp()
    except ValueError:
        raise TrajectoryFileError(f"{_text(loc)}: not a valid date and time: {s!r}") from None
    return base + float(m.group(2) or 0.0)


def parse_xy(raw: object, loc) -> tuple[float, float]:
    """``'X=+00.026\\r\\nY=+00.038'`` -> (0.026, 0.038) degrees."""
    m = _XY.match(raw) if isinstance(raw, str) else None
    if m is None:
        raise TrajectoryFileError(f"{_text(loc)}: expected 'X=<deg>\\r\\nY=<deg>', got {raw!r}")
    return float(m.group(1)), float(m.group(2))


def parse_force(raw: object, loc) -> float:
    """``'-   0.01N\\x03\\x02'`` -> -0.01 (kN)."""
    m = _FORCE.match(raw) if isinstance(raw, str) else None
    if m is None:
        raise TrajectoryFileError(
            f"{_text(loc)}: expected a force reading like '  0.44M', got {raw!r}"
        )
    return float(m.group(2)) * (-1.0 if m.group(1) else 1.0)


def _tare(d: dict, key: str, n: int, loc) -> tuple[float, ...] | None:
    if key not in d:
        return None
    parts = str(d[key]).split(";")
    try:
        vals = tuple(float(p) for p in parts)
    except ValueError:
        vals = ()
    if len(vals) != n or not all(np.isfinite(vals)):
        raise TrajectoryFileError(
            f"{loc(None, key)}: expected {n} number(s) separated by ';', got {d[key]!r}"
        )
    return vals


def read_pul(path: str | os.PathLike) -> PulFile:
    """Parse a ``.pul`` file (see the module docstring); errors name the file, line and field."""
    path = Path(path)
    raw = read_regular_file(path, "pulling test file", TrajectoryFileError, MAX_PUL_BYTES)
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise TrajectoryFileError(f"{path}: not UTF-8 text (byte {e.start})") from None
    try:
        d = json.loads(text)
    except json.JSONDecodeError as e:
        raise TrajectoryFileError(
            f"{where(path, e.lineno)}, column {e.colno}: not valid JSON ({e.msg})"
        ) from None
    loc = _Where(path, text)
    if not isinstance(d, dict):
        raise TrajectoryFileError(f"{path}: expected a JSON object with a 'data' list")
    cycles = d.get("data")
    if not isinstance(cycles, list) or not cycles:
        raise TrajectoryFileError(f"{loc(None, 'data')}: missing or empty list of cycles")
    tares = {k: _tare(d, f"{k}_tara", 2, loc) for k in INCLINOMETERS}
    tares["dlen"] = _tare(d, "dlen_tara", 2, loc)
    tares["force"] = _tare(d, "force_tara", 1, loc)
    series: dict[str, tuple[list, list, list]] = {
        k: ([], [], []) for k in (*INCLINOMETERS, "force", "dlen")
    }
    for i, c in enumerate(cycles):
        if not isinstance(c, dict):
            raise TrajectoryFileError(f"{loc(i, 'cycle')}: a cycle must be a JSON object")
        for key, (ts, vs, cs) in series.items():
            r = c.get(key)
            if r is None:
                continue  # a cycle without this sensor (1 of 1857 in halloran_9)
            if not isinstance(r, dict) or "raw" not in r or "timestamp" not in r:
                raise TrajectoryFileError(f"{loc(i, key)}: expected {{'val', 'raw', 'timestamp'}}")
            ts.append(parse_timestamp(r["timestamp"], lambda: loc(i, f"{key}.timestamp")))
            if key == "force":
                vs.append(parse_force(r["raw"], lambda: loc(i, "force.raw")))
            elif key == "dlen":
                m = _DLEN.match(r["raw"]) if isinstance(r["raw"], str) else None
                if m is None:
                    raise TrajectoryFileError(
                        f"{loc(i, 'dlen.raw')}: expected '[n1,n2]', got {r['raw']!r}"
                    )
                vs.append((float(m.group(1)), float(m.group(2))))
            else:
                vs.append(parse_xy(r["raw"], lambda: loc(i, f"{key}.raw")))
            cs.append(i)

    def make(key: str) -> SensorSeries:
        ts, vs, cs = series[key]
        return SensorSeries(np.asarray(ts, float), np.asarray(vs, float), np.asarray(cs, int))

    force = make("force")
    if force.n < 2:
        raise TrajectoryFileError(f"{loc(None, 'data')}: fewer than 2 force readings")
    incl = {k: make(k) for k in INCLINOMETERS if series[k][0]}
    if not incl:
        raise TrajectoryFileError(f"{loc(None, 'data')}: no inclinometer readings")
    for k in incl:
        if tares[k] is None:
            raise TrajectoryFileError(f"{loc(None, f'{k}_tara')}: missing (the tare of {k})")
    name = d.get("name", path.stem)
    return PulFile(
        path=path,
        name=str(name) if name else path.stem,
        n_cycles=len(cycles),
        force=force,
        inclinometers=incl,
        tares={k: v for k, v in tares.items() if v is not None},
        dlen=make("dlen") if series["dlen"][0] else None,
    )
