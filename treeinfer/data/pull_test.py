"""A static tree pulling test as treeinfer uses it: force in the cable and signed inclinations on
one time base, with the set-up of the test (heights, cable angle) from the per-tree metadata.

From a parsed ``.pul`` file (:mod:`treeinfer.data.pul`) and its row of the metadata table
(``trees.csv``, the ``trees`` sheet of Hill et al. 2024's ``static-pulling-trees.xlsx``),
:func:`make_pull_test` makes a :class:`PullTest`:

1. time base: the force readings' timestamps, in s from the first one;
2. force: ``raw`` kN x 1000 = N along the cable, minus its pre-load median (the tare; the file's
   ``force_tara`` is 0 and the load cell rests at about -10 N in some tests);
3. phases: the ramp starts at the last sample at rest (at or below 2% of the peak force, and at
   least 15 N: 1.5 quanta of the load cell) before the force first passes half its peak, and
   ends at the (first) peak; the release starts at the last sample at or above 75% of the peak
   and ends at the first sample after it at rest;
4. signed tilt per inclinometer: ``(X - tare_x, Y - tare_y)`` minus its pre-load mean,
   projected on the direction of the loaded tilt. That direction is the first right singular
   vector of the *uncentred* loaded samples (force > half the peak), i.e. the direction of
   their displacement from rest (centred principal axes would follow the scatter within the
   loaded set instead); its sign makes the loaded mean positive. Degrees to radians;
5. each channel onto the force's time base by linear interpolation on its own timestamps
   (repeated readings with the same timestamp dropped), NaN where the nearest readings on
   either side are more than ``max_gap`` apart (no interpolation across gaps).

:func:`write_pull_test` writes ``<name>.csv`` (``time,force,tilt_<channel>...``) and
``<name>.json`` (set-up, channels, phases, the steps applied); :func:`read_pull_test` reads
them back.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..errors import TrajectoryFileError, where
from ..io.safe_load import read_regular_file
from .pul import PulFile

__all__ = [
    "FORCE_QUANTUM_N",
    "TiltChannel",
    "PullTest",
    "dequantised_force",
    "PullSetup",
    "make_pull_test",
    "read_pull_test",
    "read_test_setups",
    "write_pull_test",
]

REST_FRACTION = 0.02  # force at or below this fraction of the peak (or REST_MIN_N): at rest
REST_MIN_N = 15.0  # N: 1.5 quanta of the load cell (0.01 kN resolution)
LOADED_FRACTION = 0.5  # above this fraction of the peak: loaded (the tilt direction's samples)
RELEASE_FRACTION = 0.75  # the release starts at the last sample at or above this fraction
MAX_GAP_S = 1.0  # s; a channel's readings further apart than this are not interpolated
FORCE_QUANTUM_N = 10.0  # N: the load cell's resolution (its readings are 0.01 kN apart)
KN = 1000.0  # N per kN


@dataclass(frozen=True)
class PullSetup:
    """One test's set-up (heights in m above the ground, angles in degrees)."""

    name: str  # the .pul file's stem
    tree_id: str = ""
    species: str = ""
    site: str = ""
    height: float = math.nan  # tree height
    circumference_cm: tuple[float, ...] = ()  # one per stem
    sling_height: float = math.nan  # cable on the test tree
    anchor_sling_height: float = math.nan
    anchor_distance: float = math.nan
    azimuth_from_anchor_deg: float = math.nan  # anchor -> test tree, from north
    root_clino_height: float = math.nan
    trunk_clino_height: float = math.nan
    crown_centre_height: float = math.nan
    trunk_lean_deg: float = 90.0  # elevation of the trunk (90 = upright)
    trunk_lean_dir: str = ""  # "away" from / "towards" the anchor
    root_clino_channel: str = "inclino2"
    notes: str = ""

    @property
    def cable_angle(self) -> float:
        """rad below horizontal: atan((h_sling - h_anchor) / distance)."""
        return math.atan2(self.sling_height - self.anchor_sling_height, self.anchor_distance)

    @property
    def pull_azimuth_deg(self) -> float:
        return (self.azimuth_from_anchor_deg + 180.0) % 360.0

    @property
    def dbh(self) -> float:
        """m, of the thickest stem (circumference / pi)."""
        return max(self.circumference_cm, default=math.nan) / 100.0 / math.pi

    @property
    def channel_heights(self) -> dict[str, tuple[str, float]]:
        """{'root' | 'trunk': (.pul channel, height)}: the root clino's channel is
        ``root_clino_channel``, the trunk clino is the other one (when its height is known)."""
        other = "inclino" if self.root_clino_channel == "inclino2" else "inclino2"
        out = {"root": (self.root_clino_channel, self.root_clino_height)}
        if math.isfinite(self.trunk_clino_height):
            out["trunk"] = (other, self.trunk_clino_height)
        return out


_NUMBERS = {
    "height": "height",
    "sling_height": "sling_height_test_tree",
    "anchor_sling_height": "sling_height_anchor_tree",
    "anchor_distance": "dist_test_to_anchor",
    "azimuth_from_anchor_deg": "azi_test_from_anchor",
    "root_clino_height": "height_root_clino",
    "trunk_clino_height": "height_trunk_clino",
    "crown_centre_height": "height_crown_centre",
}
_REQUIRED = ("sling_height", "anchor_sling_height", "anchor_distance", "root_clino_height")


def read_test_setups(path: str | os.PathLike) -> dict[str, PullSetup]:
    """The metadata table (``trees.csv``), by ``pul_file``; errors name the file, line, column."""
    path = Path(path)
    text = read_regular_file(path, "tree metadata table", TrajectoryFileError).decode("utf-8-sig")
    rows = csv.DictReader(io.StringIO(text))
    need = {"pul_file", *(_NUMBERS[k] for k in _REQUIRED)}
    missing = need - set(rows.fieldnames or ())
    if missing:
        raise TrajectoryFileError(f"{where(path, 1)}: missing column(s) {sorted(missing)}")
    out = {}
    for line, row in enumerate(rows, start=2):
        name = (row.get("pul_file") or "").strip()
        if not name:
            continue
        vals = {}
        for key, col in _NUMBERS.items():
            s = (row.get(col) or "").strip()
            try:
                vals[key] = float(s) if s else math.nan
            except ValueError:
                raise TrajectoryFileError(
                    f"{where(path, line, col)}: expected a number, got {s!r}"
                ) from None
            if key in _REQUIRED and not (math.isfinite(vals[key]) and vals[key] >= 0):
                raise TrajectoryFileError(
                    f"{where(path, line, col)}: expected a number >= 0, got {s!r}"
                )
        if vals["anchor_distance"] <= 0:
            raise TrajectoryFileError(
                f"{where(path, line, 'dist_test_to_anchor')}: must be > 0 (m)"
            )
        lean = (row.get("trunk_lean_angle") or "").strip().lower()
        try:
            circ = tuple(float(c) for c in (row.get("circ") or "").split(",") if c.strip())
        except ValueError:
            raise TrajectoryFileError(
                f"{where(path, line, 'circ')}: expected numbers (cm) separated by ','"
            ) from None
        try:  # "vertical" or blank: upright; a word such as "variable": unknown (NaN)
            lean_deg = 90.0 if lean in ("", "vertical") else float(lean)
        except ValueError:
            lean_deg = math.nan
        clino_id = (row.get("root_clino_id") or "2").strip()
        out[name] = PullSetup(
            name=name,
            tree_id=(row.get("tree_id") or "").strip(),
            species=(row.get("tree_species") or "").strip(),
            site=(row.get("site") or "").strip(),
            circumference_cm=circ,
            trunk_lean_deg=lean_deg,
            trunk_lean_dir=(row.get("trunk_lean_dir") or "").strip(),
            root_clino_channel="inclino" if clino_id == "1" else "inclino2",
            notes=(row.get("notes") or "").strip(),
            **vals,
        )
    return out


@dataclass(frozen=True)
class TiltChannel:
    """One inclinometer as used: ``axis`` the unit (X, Y) direction of the loaded tilt, ``rest``
    the pre-load mean of (X - tare) in degrees, ``rest_sd`` the sd of the signed tilt before the
    load (rad), ``perp_sd`` the sd of the perpendicular component under load (rad)."""

    name: str  # "root" | "trunk"
    source: str  # the .pul key: "inclino" | "inclino2"
    height: float  # m above the ground
    axis: tuple[float, float]
    rest: tuple[float, float]
    rest_sd: float
    perp_sd: float
    gaps: int  # force samples left NaN (no reading within the gap limit)


@dataclass(frozen=True)
class PullTest:
    """A test on the force's time base: ``time`` [T] s, ``force`` [T] N along the cable (tared),
    ``tilt[channel]`` [T] rad (signed, along the pull, from the pre-load mean; NaN in gaps);
    ``phases`` sample indices ``ramp_start, ramp_end (peak), release_start, release_end``."""

    name: str
    setup: PullSetup
    time: np.ndarray
    force: np.ndarray
    tilt: dict[str, np.ndarray]
    channels: dict[str, TiltChannel]
    phases: dict[str, int]
    steps: list[str] = field(default_factory=list)
    source: str = ""
    source_sha256: str = ""

    @property
    def n(self) -> int:
        return int(self.time.size)


def _first(mask: np.ndarray) -> int:
    """Index of the first True, or the length when there is none (``argmax`` would say 0)."""
    idx = np.flatnonzero(mask)
    return int(idx[0]) if idx.size else int(mask.size)


def rest_threshold(peak: float) -> float:
    """N: a tared force at or below this is at rest."""
    return max(REST_FRACTION * peak, REST_MIN_N)


def find_phases(force: np.ndarray, path) -> dict[str, int]:
    """Ramp and release indices (see the module docstring) of a tared force [T]."""
    peak = float(np.max(force))
    if not peak > REST_MIN_N:
        raise TrajectoryFileError(f"{path}: the force never rises above its rest level")
    rest = force <= rest_threshold(peak)
    first_loaded = int(np.argmax(force > LOADED_FRACTION * peak))
    before = np.nonzero(rest[:first_loaded])[0]
    ramp_start = int(before[-1]) if before.size else 0
    ramp_end = int(np.argmax(force))
    release_start = int(np.nonzero(force >= RELEASE_FRACTION * peak)[0][-1])
    after = np.nonzero(rest[release_start:])[0]
    release_end = release_start + int(after[0]) if after.size else force.size - 1
    return {
        "ramp_start": ramp_start,
        "ramp_end": ramp_end,
        "release_start": release_start,
        "release_end": release_end,
    }


def _onto(t_src: np.ndarray, y: np.ndarray, t: np.ndarray, max_gap: float) -> np.ndarray:
    """``y`` (at ``t_src``) at times ``t``: linear, NaN across gaps and outside the readings."""
    keep = np.concatenate([[True], np.diff(t_src) > 0])  # re-reported readings (same time)
    t_src, y = t_src[keep], y[keep]
    order = np.argsort(t_src, kind="stable")
    t_src, y = t_src[order], y[order]
    out = np.interp(t, t_src, y)
    j = np.clip(np.searchsorted(t_src, t), 1, t_src.size - 1)
    span = t_src[j] - t_src[j - 1]
    exact = np.isclose(t_src[np.clip(np.searchsorted(t_src, t), 0, t_src.size - 1)], t)
    bad = ((span > max_gap) & ~exact) | (t < t_src[0]) | (t > t_src[-1])
    return np.where(bad, np.nan, out)


def make_pull_test(
    pul: PulFile, setup: PullSetup, max_gap: float = MAX_GAP_S, source_sha256: str = ""
) -> PullTest:
    """Force and signed tilts on one time base (the steps of the module docstring)."""
    steps = []
    t0 = float(pul.force.t[0])
    order = np.argsort(pul.force.t, kind="stable")
    t = pul.force.t[order] - t0
    f_raw = pul.force.values[order] * KN
    steps.append(f"time base: {t.size} force readings, s from the first ({t[-1]:.1f} s long)")
    # the pre-load part: before the force first rises a rest threshold above its first value
    # (and before it first passes half its peak)
    pre = f_raw[: max(1, _first(f_raw > LOADED_FRACTION * f_raw.max()))]
    pre = pre[: max(1, _first(pre - pre[0] > rest_threshold(f_raw.max() - pre[0])))]
    tare = float(np.median(pre))
    force = f_raw - tare
    steps.append(f"force: kN x 1000 -> N; tare {tare:+.1f} N (median of the pre-load samples)")
    phases = find_phases(force, pul.path)
    steps.append(
        "phases (s): ramp {:.1f}-{:.1f}, release {:.1f}-{:.1f}".format(
            *(t[phases[k]] for k in ("ramp_start", "ramp_end", "release_start", "release_end"))
        )
    )
    peak = float(force.max())
    tilts, channels = {}, {}
    for name, (src, height) in setup.channel_heights.items():
        s = pul.inclinometers.get(src)
        if s is None:
            raise TrajectoryFileError(
                f"{pul.path}: no '{src}' readings, the {name} inclinometer of test {setup.name}"
            )
        ts = s.t - t0
        xy = s.values - np.asarray(pul.tares[src])
        f_at = np.interp(ts, t, force)  # the force when each angle was read
        rest_mask = ts <= t[phases["ramp_start"]]
        if rest_mask.sum() < 2:
            rest_mask = f_at <= rest_threshold(peak)
        rest = xy[rest_mask].mean(axis=0) if rest_mask.any() else np.zeros(2)
        d = xy - rest
        loaded = d[f_at > LOADED_FRACTION * peak]
        if loaded.shape[0] < 2:
            raise TrajectoryFileError(f"{pul.path}: {src}: no readings under load")
        axis = np.linalg.svd(loaded, full_matrices=False)[2][0]
        axis = axis if loaded.mean(axis=0) @ axis > 0 else -axis
        signed = np.deg2rad(d @ axis)
        perp = np.deg2rad(loaded @ np.array([-axis[1], axis[0]]))
        on_t = _onto(ts, signed, t, max_gap)
        gaps = int(np.isnan(on_t).sum())
        tilts[name] = on_t
        channels[name] = TiltChannel(
            name=name,
            source=src,
            height=float(height),
            axis=(float(axis[0]), float(axis[1])),
            rest=(float(rest[0]), float(rest[1])),
            rest_sd=float(np.std(signed[rest_mask])) if rest_mask.sum() > 1 else math.nan,
            perp_sd=float(np.std(perp)),
            gaps=gaps,
        )
        steps.append(
            f"{name} tilt from {src} at {height:g} m: (X, Y) - tare - pre-load mean "
            f"({rest[0]:+.3f}, {rest[1]:+.3f})°, along ({axis[0]:+.3f}, {axis[1]:+.3f}), "
            f"deg -> rad, onto the force times ({gaps} sample(s) in gaps > {max_gap:g} s: NaN)"
        )
    return PullTest(
        name=setup.name,
        setup=setup,
        time=t,
        force=force,
        tilt=tilts,
        channels=channels,
        phases=phases,
        steps=steps,
        source=str(pul.path),
        source_sha256=source_sha256,
    )


def dequantised_force(time, force, quantum: float = FORCE_QUANTUM_N) -> np.ndarray:
    """The force between the load cell's quanta: ``force`` [T] N (recorded, rounded to
    ``quantum``) at ``time`` [T] s -> [T] N, piecewise linear through the level crossings,
    with the winch's quick steps kept as steps.

    Why: the recorded force is the true one rounded to the cell's 10 N. On a small tree (a
    190 N peak) a level lasts a second or more while the tilts rise smoothly under the true
    force, so a model driven by the staircase sees the tilt climb at a constant force (read
    as lag or creep) and errors of up to half a quantum, a fifth of the force early in the
    ramp. Where the reading changes by one level, from ``a`` to ``b``, between two samples,
    the true force crossed ``(a + b) / 2`` between them: those crossings, at the mid-time of
    the two samples, are knots. A change of two levels or more between two samples (0.1 s)
    is no slow drift through a level but a quick step of the winch (a large tree's pull
    goes in steps of several quanta, and the tilts follow them within a fraction of a
    second): interpolating from the last crossing to it would spread it over the level's
    whole duration before it, i.e. move the load ahead of the tilts (in the mangrove
    records 0.2-4% of the steps between samples, 2-14% of the level changes; none in
    halloran_1's and gladstone_21's fitted windows). Such a step is kept: the knots are the two
    recorded readings on either side of it, so the force holds its level until the step.
    Before the first and after the last knot the reading is kept; the result is never more
    than half a quantum from the reading. Uses only the force record (never the tilts), so
    it is the same for every test and model."""
    time = np.asarray(time, float)
    force = np.asarray(force, float)
    if time.shape != force.shape or time.ndim != 1:
        raise ValueError(f"dequantised_force: time {time.shape} and force {force.shape} differ")
    # the tare shifts the grid off multiples of the quantum: follow the steps themselves
    jump = np.abs(np.diff(force))
    change = np.flatnonzero(jump > quantum / 2)
    if change.size < 2:
        return force.copy()
    single = jump[change] < 1.5 * quantum  # one level: a crossing; more: a quick step
    cross = change[single]
    step = change[~single]
    tk = np.concatenate([0.5 * (time[cross] + time[cross + 1]), time[step], time[step + 1]])
    fk = np.concatenate([0.5 * (force[cross] + force[cross + 1]), force[step], force[step + 1]])
    # consecutive steps share a sample: one knot per time (the same reading)
    tk, first = np.unique(tk, return_index=True)
    fk = fk[first]
    out = np.interp(time, tk, fk)
    out[time < tk[0]] = force[time < tk[0]]
    out[time > tk[-1]] = force[time > tk[-1]]
    return out


def sha256_of(path: str | os.PathLike) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


# ---- files -------------------------------------------------------------------------------------
def csv_text(test: PullTest) -> str:
    cols = ["time", "force", *(f"tilt_{c}" for c in test.tilt)]
    lines = [",".join(cols)]
    for i in range(test.n):
        vals = [test.time[i], test.force[i], *(v[i] for v in test.tilt.values())]
        lines.append(",".join("nan" if not np.isfinite(v) else f"{v:.9g}" for v in vals))
    return "\n".join(lines) + "\n"


def meta_record(test: PullTest) -> dict:
    setup = asdict(test.setup)
    setup["circumference_cm"] = list(test.setup.circumference_cm)
    return {
        "format": "treeinfer pull test 1",
        "name": test.name,
        "source": test.source,
        "source_sha256": test.source_sha256,
        "columns": {"time": "s", "force": "N along the cable"}
        | {f"tilt_{c}": "rad, along the pull" for c in test.tilt},
        "setup": {
            k: (None if isinstance(v, float) and not math.isfinite(v) else v)
            for k, v in setup.items()
        },
        "cable_angle_rad": test.setup.cable_angle,
        "pull_azimuth_deg": test.setup.pull_azimuth_deg,
        "channels": {k: asdict(c) for k, c in test.channels.items()},
        "phases": test.phases,
        "steps": test.steps,
        "citation": "Hill JW, Bennion V, Lovelock CE (2024) Mangrove tree strength estimated "
        "with field experiments. Ecological Engineering 203: 107259. "
        "doi:10.1016/j.ecoleng.2024.107259",
    }


def write_pull_test(test: PullTest, out: str | os.PathLike) -> tuple[Path, Path]:
    """``<out>/<name>.csv`` and ``<out>/<name>.json`` (``out`` created; existing files must
    have been claimed by the caller: :func:`treeinfer.io.ownership.write_output_file` keeps a
    different previous file aside)."""
    from ..io.ownership import write_output_file

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    p_csv = write_output_file(out / f"{test.name}.csv", csv_text(test))
    text = json.dumps(meta_record(test), indent=2, allow_nan=False) + "\n"
    p_json = write_output_file(out / f"{test.name}.json", text)
    return p_csv, p_json


def read_pull_test(path: str | os.PathLike) -> PullTest:
    """A test written by :func:`write_pull_test`: ``path`` is its ``.json`` or ``.csv``."""
    path = Path(path)
    p_json, p_csv = path.with_suffix(".json"), path.with_suffix(".csv")
    meta = json.loads(read_regular_file(p_json, "pull test metadata", TrajectoryFileError))
    if not isinstance(meta, dict) or meta.get("format") != "treeinfer pull test 1":
        raise TrajectoryFileError(f"{p_json}: not a treeinfer pull test (format field)")
    text = read_regular_file(p_csv, "pull test CSV", TrajectoryFileError).decode()
    rows = list(csv.reader(io.StringIO(text)))
    head = rows[0]
    try:
        data = np.array([[float(v) for v in r] for r in rows[1:] if r], float)
    except ValueError as e:
        raise TrajectoryFileError(f"{p_csv}: not numeric ({e})") from None
    setup_d = {k: (math.nan if v is None else v) for k, v in meta["setup"].items()}
    setup_d["circumference_cm"] = tuple(setup_d["circumference_cm"])
    return PullTest(
        name=meta["name"],
        setup=PullSetup(**setup_d),
        time=data[:, 0],
        force=data[:, 1],
        tilt={h[len("tilt_") :]: data[:, i] for i, h in enumerate(head) if h.startswith("tilt_")},
        channels={
            k: TiltChannel(**{**c, "axis": tuple(c["axis"]), "rest": tuple(c["rest"])})
            for k, c in meta["channels"].items()
        },
        phases={k: int(v) for k, v in meta["phases"].items()},
        steps=list(meta["steps"]),
        source=meta["source"],
        source_sha256=meta["source_sha256"],
    )
