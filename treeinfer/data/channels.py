"""Observation channels besides the grasp point: positions of named points on the tree
(markers, keypoints) and angles at named points (inclinometers, IMUs), read from a data
folder's ``channels.yaml`` and the channel files it names (issue 30, section 2).

A data folder with channels::

    data/
      pull_a.csv               # the pulls (force and grasp-point displacement), as always
      pulls.yaml               # optional: where each pull acted
      channels.yaml            # the channels below
      channels/marker_a.csv    # one file per channel: time + one column per component

``channels.yaml``::

    channels:
      - name: marker_child           # unique; labels its noise column sigma[marker_child]
        recording: pull_a.csv        # the pull this channel observed (a CSV of the folder)
        file: channels/marker_a.csv  # relative to the data folder (not at its top level:
                                     # every top-level CSV is a pull)
        kind: position               # position (3-D displacement) | angle (rotation) |
                                     # image (pixel displacement in a camera: needs camera:)
        point: {link: child, fraction: 0.5}  # or {link: child, distance: 0.3} (m from its joint)
        components: [x, z]           # world axes measured (position: displacement along them;
                                     # angle: rotation about them, right-handed), 1-3 of x, y, z
        units: {time: s, value: mm}  # time s|ms; position m|cm|mm|in; angle rad|mrad|deg
        time_offset: 0.0             # s added to the file's time to put it on the pull's clock
        noise: auto                  # auto (inferred, like the displacement's) or a std in the
                                     # value unit
        sensor: camera_marker_1      # optional: channels of one sensor (on several pulls)
                                     # share one inferred noise scale, sigma[sensor]

Values are measured from the tree's rest pose at the start of the pull: a position channel is
the point's displacement from its rest position, an angle channel the rotation of the link's
frame from its rest orientation (the rotation vector of ``R(t) R(0)^T``, world axes). Each channel
keeps its own rate; the likelihood compares it with the simulation interpolated (linearly) at
its own sample times. Samples outside the pull's time span are dropped (and counted); a channel
with none inside is an error. Every error names the file and the field (exit code 2).
"""

from __future__ import annotations

import csv
import math
import os
from pathlib import Path
from typing import Any, NamedTuple, Sequence

import numpy as np

from ..errors import ConfigError, TrajectoryFileError, where
from .csv_format import DISPLACEMENT_UNITS, TIME_UNITS

CHANNELS_FILE = "channels.yaml"
KINDS = ("position", "angle", "image")
AXES = ("x", "y", "z")
IMAGE_AXES = ("u", "v")  # pixel columns (right) and rows (down) of an image channel
ANGLE_UNITS = {"rad": 1.0, "mrad": 1e-3, "deg": math.pi / 180.0}
VALUE_UNITS = {"position": DISPLACEMENT_UNITS, "angle": ANGLE_UNITS, "image": {"px": 1.0}}
SI_UNIT = {"position": "m", "angle": "rad", "image": "px"}
# largest plausible |value| in SI: past it the declared unit is almost surely wrong
PLAUSIBLE = {"position": 5.0, "angle": math.pi, "image": 1e5}
_FIELDS = {
    "name",
    "recording",
    "file",
    "kind",
    "point",
    "components",
    "units",
    "time_offset",
    "noise",
    "camera",
    "sensor",
}


class NamedPoint(NamedTuple):
    """A point on the tree: ``link`` (a branch name) and where along its axis, either
    ``distance`` m from its joint or ``fraction`` of its length (exactly one is set)."""

    link: str
    distance: float | None = None
    fraction: float | None = None

    def fraction_of(self, length: float) -> float:
        """The point as a fraction of a link of ``length`` m."""
        return float(self.fraction) if self.fraction is not None else self.distance / length

    def label(self) -> str:
        at = f"{self.fraction:g}" if self.fraction is not None else f"{self.distance:g} m"
        return f"{self.link}@{at}"


class Channel(NamedTuple):
    """One observation channel, in SI units on its pull's clock.

    Attributes:
      name: unique channel name. kind: ``"position"`` or ``"angle"``.
      recording: the pull's file name (``Trajectory.source``). point: :class:`NamedPoint`.
      components: world axes measured, e.g. ``("x", "z")``.
      time: [S] s on the pull's clock (the file's time + ``time_offset``), inside the pull.
      values: [S, C] m (position: displacement from rest) or rad (angle: rotation from rest).
      noise: std in SI units, or None (inferred).
      source: the channel file (messages). units: the file's units as declared.
      time_offset: s. dropped: samples outside the pull's span left out.
      camera: an image channel's pinhole camera (:func:`parse_camera`), else ().
      sensor: the sensor's name (channels of one sensor share a noise scale), or "" (its own).
    """

    name: str
    kind: str
    recording: str
    point: NamedPoint
    components: tuple[str, ...]
    time: np.ndarray
    values: np.ndarray
    noise: float | None = None
    source: str = ""
    units: dict = {}
    time_offset: float = 0.0
    dropped: int = 0
    camera: tuple = ()
    sensor: str = ""

    @property
    def rate(self) -> float:
        """Hz, from the median sample interval."""
        return 1.0 / float(np.median(np.diff(self.time))) if len(self.time) > 1 else 0.0

    @property
    def axes(self) -> np.ndarray:
        """[C] indices (0, 1, 2) of ``components``."""
        names = IMAGE_AXES if self.kind == "image" else AXES
        return np.array([names.index(c) for c in self.components], dtype=np.int32)

    def value_range(self) -> float:
        """Largest peak-to-peak of a component (SI), the noise prior's upper end."""
        return float(np.max(np.ptp(self.values, axis=0))) if self.values.size else 0.0


# ----------------------------------------------------------------------------- parsing
def _number(v: Any, loc: str) -> float:
    if isinstance(v, bool):
        raise ConfigError(f"{loc}: expected a number, got {v!r}")
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise ConfigError(f"{loc}: expected a number, got {v!r}") from None
    if not math.isfinite(x):
        raise ConfigError(f"{loc}: must be finite, got {x}")
    return x


def parse_point(entry: Any, loc: str, tree=None) -> NamedPoint:
    """A :class:`NamedPoint` from ``{link, fraction}`` or ``{link, distance}``, checked against
    ``tree`` (an unknown link, or a point past the link's end, is an error naming ``loc``)."""
    if not isinstance(entry, dict):
        raise ConfigError(f"{loc}: expected a mapping {{link, fraction | distance}}, got {entry!r}")
    unknown = set(entry) - {"link", "fraction", "distance"}
    if unknown:
        raise ConfigError(
            f"{loc}: unknown field(s) {sorted(unknown)}; use link, fraction, distance"
        )
    link = entry.get("link")
    if not isinstance(link, str) or not link:
        raise ConfigError(f"{loc}.link: expected a branch name, got {link!r}")
    if ("fraction" in entry) == ("distance" in entry):
        raise ConfigError(f"{loc}: give exactly one of 'fraction' and 'distance'")
    fraction = distance = None
    if "fraction" in entry:
        fraction = _number(entry["fraction"], f"{loc}.fraction")
        if not 0.0 <= fraction <= 1.0:
            raise ConfigError(f"{loc}.fraction: must be in [0, 1], got {fraction:g}")
    else:
        distance = _number(entry["distance"], f"{loc}.distance")
        if distance < 0:
            raise ConfigError(f"{loc}.distance: must be >= 0 m, got {distance:g}")
    if tree is not None:
        if link not in tree.names:
            raise ConfigError(
                f"{loc}.link: unknown point '{link}': the tree has no link of that name "
                f"(links: {', '.join(tree.names)})"
            )
        length = tree.branch(link).length
        if distance is not None and distance > length * (1 + 1e-9):
            raise ConfigError(
                f"{loc}.distance: {distance:g} m is past the end of link '{link}' "
                f"({length:g} m long)"
            )
    return NamedPoint(link, distance, fraction)


def _components(v: Any, loc: str, axes=AXES) -> tuple[str, ...]:
    names = ", ".join(axes)
    if isinstance(v, str):
        v = list(v) if set(v) <= set(axes) else [v]
    if not isinstance(v, (list, tuple)) or not v:
        raise ConfigError(f"{loc}: expected a list of axes among {names}, got {v!r}")
    out = tuple(str(c).lower() for c in v)
    bad = [c for c in out if c not in axes]
    if bad or len(set(out)) != len(out):
        raise ConfigError(f"{loc}: expected distinct axes among {names}, got {list(v)}")
    return out


def parse_camera(v: Any, loc: str) -> tuple:
    """A pinhole camera ``{focal: [fx, fy], center: [cx, cy], rotation: 3x3 (rows: the
    camera's x right, y down, z forward in world axes), position: [x, y, z] m}`` as the 16 floats
    ``(fx, fy, cx, cy, R (9, row-major), position (3))``."""
    if not isinstance(v, dict):
        raise ConfigError(f"{loc}: an image channel needs a camera mapping {{focal, center, "
                          f"rotation, position}}, got {v!r}")  # fmt: skip
    unknown = set(v) - {"focal", "center", "rotation", "position"}
    if unknown:
        raise ConfigError(f"{loc}: unknown field(s) {sorted(unknown)}")

    def arr(key, shape):
        try:
            a = np.asarray(v.get(key), float)
        except (TypeError, ValueError):
            raise ConfigError(f"{loc}.{key}: expected numbers of shape {shape}") from None
        if a.shape != shape or not np.all(np.isfinite(a)):
            raise ConfigError(f"{loc}.{key}: expected finite numbers of shape {shape}")
        return a

    f, c, r, p = (
        arr("focal", (2,)),
        arr("center", (2,)),
        arr("rotation", (3, 3)),
        arr("position", (3,)),
    )
    if np.any(f <= 0):
        raise ConfigError(f"{loc}.focal: must be positive (pixels)")
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
        raise ConfigError(f"{loc}.rotation: must be a rotation matrix (orthonormal, det +1)")
    return tuple(float(x) for x in np.concatenate([f, c, r.ravel(), p]))


def _units(v: Any, kind: str, loc: str) -> dict:
    v = {} if v is None else v
    if not isinstance(v, dict):
        raise ConfigError(f"{loc}: expected a mapping {{time: s, value: ...}}, got {v!r}")
    unknown = set(v) - {"time", "value"}
    if unknown:
        raise ConfigError(f"{loc}: unknown field(s) {sorted(unknown)}; use time, value")
    time_u = str(v.get("time", "s"))
    value_u = str(v.get("value", SI_UNIT[kind]))
    if time_u not in TIME_UNITS:
        raise ConfigError(f"{loc}.time: unknown time unit {time_u!r}; use {', '.join(TIME_UNITS)}")
    if value_u not in VALUE_UNITS[kind]:
        other = [k for k in KINDS if k != kind and value_u in VALUE_UNITS[k]]
        hint = f" ({value_u!r} is a unit of {other[0]} channels)" if other else ""
        raise ConfigError(
            f"{loc}.value: inconsistent units: a {kind} channel takes "
            f"{', '.join(VALUE_UNITS[kind])}, got {value_u!r}{hint}"
        )
    return {"time": time_u, "value": value_u}


def read_channel_file(path: Path, components: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """``time [S]`` and ``values [S, C]`` (file units) of a channel CSV whose header is ``time``
    and the component names (``x, z``; any order, other columns ignored). Errors name the file,
    line and column."""
    try:
        with open(path, newline="") as f:
            rows = [
                (i + 1, r) for i, r in enumerate(csv.reader(f)) if r and not r[0].startswith("#")
            ]
    except OSError as e:
        raise TrajectoryFileError(f"{path}: cannot read the channel file ({e.strerror})") from None
    if not rows:
        raise TrajectoryFileError(f"{path}: empty channel file")
    header = [c.strip().lower() for c in rows[0][1]]
    need = ["time", *components]
    missing = [c for c in need if c not in header]
    if missing:
        raise TrajectoryFileError(
            f"{where(path, rows[0][0])}: missing column(s) {missing} (header: {header}); a "
            f"channel file holds 'time' and one column per component"
        )
    cols = [header.index(c) for c in need]
    data = np.empty((len(rows) - 1, len(need)))
    for k, (line, r) in enumerate(rows[1:]):
        for j, c in enumerate(cols):
            try:
                data[k, j] = float(r[c])
            except (ValueError, IndexError):
                cell = r[c] if c < len(r) else ""
                raise TrajectoryFileError(
                    f"{path}, line {line}, column '{need[j]}': expected a number, got {cell!r}"
                ) from None
            if not math.isfinite(data[k, j]):
                raise TrajectoryFileError(
                    f"{path}, line {line}, column '{need[j]}': not finite ({data[k, j]})"
                )
    if data.shape[0] < 2:
        raise TrajectoryFileError(
            f"{path}: a channel needs at least 2 samples, got {data.shape[0]}"
        )
    if np.any(np.diff(data[:, 0]) <= 0):
        bad = int(np.argmax(np.diff(data[:, 0]) <= 0)) + 1
        raise TrajectoryFileError(
            f"{path}, line {rows[bad + 1][0]}, column 'time': time must increase strictly"
        )
    return data[:, 0], data[:, 1:]


def parse_channel(
    entry: Any,
    index: int,
    folder: Path,
    tree=None,
    recordings: dict[str, tuple[float, float]] | None = None,
    source: str = CHANNELS_FILE,
) -> Channel:
    """One ``channels.yaml`` entry, its file read and converted to SI; ``recordings`` maps each
    pull's file name to its time span (s), for the overlap check."""
    loc0 = f"{source}: channels[{index}]"
    if not isinstance(entry, dict):
        raise ConfigError(f"{loc0}: expected a mapping, got {entry!r}")
    unknown = set(entry) - _FIELDS
    if unknown:
        raise ConfigError(f"{loc0}: unknown field(s) {sorted(unknown)}; known: {sorted(_FIELDS)}")
    name = entry.get("name")
    if not isinstance(name, str) or not name.strip() or any(c in name for c in "[],\n"):
        raise ConfigError(f"{loc0}: field 'name': expected a plain name, got {name!r}")
    loc = f"{source}: channel '{name}'"
    kind = entry.get("kind")
    if kind not in KINDS:
        raise ConfigError(f"{loc}: field 'kind': expected one of {', '.join(KINDS)}, got {kind!r}")
    point = parse_point(entry.get("point"), f"{loc}: field 'point'", tree)
    axes = IMAGE_AXES if kind == "image" else AXES
    comps = _components(entry.get("components", list(axes)), f"{loc}: field 'components'", axes)
    camera = ()
    if kind == "image":
        camera = parse_camera(entry.get("camera"), f"{loc}: field 'camera'")
    elif "camera" in entry:
        raise ConfigError(f"{loc}: field 'camera': only image channels have a camera")
    units = _units(entry.get("units"), kind, f"{loc}: field 'units'")
    sensor = entry.get("sensor", "")
    if not isinstance(sensor, str) or any(c in sensor for c in "[],\n"):
        raise ConfigError(f"{loc}: field 'sensor': expected a plain name, got {sensor!r}")
    offset = _number(entry.get("time_offset", 0.0), f"{loc}: field 'time_offset'")
    rec = entry.get("recording")
    if not isinstance(rec, str):
        raise ConfigError(f"{loc}: field 'recording': expected a pull's CSV file name, got {rec!r}")
    if recordings is not None and rec not in recordings:
        raise ConfigError(
            f"{loc}: field 'recording': no pull '{rec}' in the data folder "
            f"(pulls: {', '.join(recordings) or 'none'})"
        )
    file = entry.get("file")
    if not isinstance(file, str) or not file:
        raise ConfigError(f"{loc}: field 'file': expected a path, got {file!r}")
    path = folder / file
    if path.parent.resolve() == folder.resolve() and path.suffix.lower() == ".csv":
        raise ConfigError(
            f"{loc}: field 'file': {file} sits at the data folder's top level, where every CSV "
            "is read as a pull; put channel files in a subfolder (channels/)"
        )
    t, raw = read_channel_file(path, comps)
    scale = VALUE_UNITS[kind][units["value"]]
    values = raw * scale
    t = t * TIME_UNITS[units["time"]] + offset
    peak = float(np.max(np.abs(values)))
    if peak > PLAUSIBLE[kind]:
        raise ConfigError(
            f"{path}: values up to {peak:.3g} {SI_UNIT[kind]} after converting from "
            f"{units['value']} ({loc}: field 'units'): inconsistent units? (a {kind} channel "
            f"above {PLAUSIBLE[kind]:g} {SI_UNIT[kind]} is implausible)"
        )
    noise = entry.get("noise", "auto")
    if noise == "auto" or noise is None:
        sigma = None
    else:
        sigma = _number(noise, f"{loc}: field 'noise'") * scale
        if sigma <= 0:
            raise ConfigError(f"{loc}: field 'noise': must be > 0 or 'auto', got {noise!r}")
    dropped = 0
    if recordings is not None:
        t0, t1 = recordings[rec]
        inside = (t >= t0 - 1e-9) & (t <= t1 + 1e-9)
        if not inside.any():
            raise ConfigError(
                f"{path} ({loc}: fields 'time_offset', 'units.time'): no overlap in time with "
                f"the pull {rec} ({t0:g}-{t1:g} s): the channel spans {t[0]:g}-{t[-1]:g} s "
                "on the pull's clock"
            )
        dropped = int((~inside).sum())
        t, values = t[inside], values[inside]
    return Channel(
        name, kind, rec, point, comps, t, values, sigma, str(path), units, offset, dropped, camera,
        sensor,
    )  # fmt: skip


def read_channels(
    folder: str | os.PathLike, tree=None, trajectories=None, only_these_pulls: bool = False
) -> tuple[Channel, ...]:
    """The channels of a data folder (``()`` without a ``channels.yaml``), checked against the
    ``tree`` (point names) and the ``trajectories`` (recordings and time overlap) when given.
    ``only_these_pulls``: keep only the channels of those trajectories (a k-fold split of the
    folder's pulls) instead of refusing the others."""
    import yaml

    folder = Path(folder)
    path = folder / CHANNELS_FILE
    if not path.exists():
        return ()
    try:
        raw = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise ConfigError(f"{path}: not valid YAML ({e})") from None
    return channels_from_dict(raw, folder, tree, trajectories, str(path), only_these_pulls)


def channels_from_dict(
    raw: Any,
    folder,
    tree=None,
    trajectories=None,
    source: str = CHANNELS_FILE,
    only_these_pulls: bool = False,
) -> tuple[Channel, ...]:
    """:func:`read_channels` from the parsed YAML ``raw``."""
    if not isinstance(raw, dict) or not isinstance(raw.get("channels"), list):
        raise ConfigError(f"{source}: expected a mapping with a list 'channels'")
    unknown = set(raw) - {"channels"}
    if unknown:
        raise ConfigError(f"{source}: unknown field(s) {sorted(unknown)}")
    recordings = None
    if trajectories is not None:
        recordings = {
            Path(tr.source).name: (float(tr.time[0]), float(tr.time[-1])) for tr in trajectories
        }
    entries = list(enumerate(raw["channels"]))
    if only_these_pulls and recordings is not None:
        entries = [
            (i, e)
            for i, e in entries
            if not isinstance(e, dict) or e.get("recording") in recordings
        ]
    out = [parse_channel(e, i, Path(folder), tree, recordings, source) for i, e in entries]
    names = [c.name for c in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ConfigError(f"{source}: field 'name': channel names must be unique, repeated: {dup}")
    return tuple(out)


def sample_weights(time: np.ndarray, t0: float, dt: float, n_steps: int):
    """Linear interpolation of a pull's grid ``t0 + k dt`` (k < n_steps) at ``time`` [S]:
    ``(index [S] int32, weight [S])`` with value = ``(1 - w) x[i] + w x[i + 1]``."""
    u = np.clip((np.asarray(time, float) - t0) / dt, 0.0, n_steps - 1.0)
    i = np.minimum(np.floor(u).astype(np.int32), max(n_steps - 2, 0))
    return i, u - i
