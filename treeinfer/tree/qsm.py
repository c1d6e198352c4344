"""Reading quantitative structure models (QSMs): the cylinder tables that TreeQSM, SimpleForest
and aRchi reconstruct from a tree's point cloud.

:func:`read_qsm` returns one :class:`Cylinders` table (metres, 0-based parent indices) whatever
the source. Formats (``fmt``), detected from the file when not given:

- ``treeqsm-mat``: TreeQSM's MATLAB file (``QSM.cylinder`` with radius, length, start, axis,
  parent, extension, branch, BranchOrder; any variable holding a struct with a ``cylinder``
  field), read with :func:`scipy.io.loadmat`;
- ``treeqsm-txt``: TreeQSM's text export, either ``cylinder_*.txt`` (2.4 and later: a header
  ``radius (m) length (m) start_point axis_direction parent extension branch branch_order
  position_in_branch mad SurfCov added UnmodRadius (m)``, start and axis 3 columns each) or the
  headerless 15-column ``cyl_data_*.txt`` of 2.3 (see :data:`TREEQSM_V23_COLUMNS`; its
  columns after the axis were written in two orders across versions, told apart by which
  column holds integers);
- ``simpleforest``: SimpleForest's CSV (``ID, parentID, startX, ... endZ, radius, length, ...
  branchOrder``; names after ", ");
- ``archi``: aRchi's ``QSM`` table as CSV (``startX ... endZ, cyl_ID, parent_ID, radius_cyl,
  axis_ID, branching_order``; order 1 is the trunk there, 0 here).

Units: every tool writes metres; ``units`` (``m``, ``cm``, ``mm``) says otherwise. When not
given, a table whose height or thickest radius is implausible in metres is refused with a
request for the unit (no silent guess). Errors name the file, the line (text files; the
cylinder's index for ``.mat``) and the column.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import TreeFileError

FORMATS = ("treeqsm-mat", "treeqsm-txt", "simpleforest", "archi")
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}
# a metre-scale table: trees are below ~120 m and stems below ~5 m radius; beyond, the unit
# is wrong (cm or mm read as m) and the user must say which
MAX_HEIGHT_M = 150.0
# TreeQSM 2.3 ``save_model_text`` (v1.0.0): Rad Len Sta(3) Axe(3) CPar CExt B BO PIB Added Rad0
TREEQSM_V23_COLUMNS = (
    "radius", "length", "start_x", "start_y", "start_z", "axis_x", "axis_y", "axis_z",
    "parent", "extension", "branch", "branch_order", "position_in_branch", "added",
    "unmod_radius",
)  # fmt: skip
# the order of the .mat structure's fields, which some 2.3 exports follow instead
_TREEQSM_V23_ALT = (
    *TREEQSM_V23_COLUMNS[:10], "added", "unmod_radius", "branch", "branch_order",
    "position_in_branch",
)  # fmt: skip
_TREEQSM_V24_HEADER = {
    "radius (m)": ["radius"],
    "length (m)": ["length"],
    "start_point": ["start_x", "start_y", "start_z"],
    "axis_direction": ["axis_x", "axis_y", "axis_z"],
    "parent": ["parent"],
    "extension": ["extension"],
    "branch": ["branch"],
    "branch_order": ["branch_order"],
    "position_in_branch": ["position_in_branch"],
    "mad": ["mad"],
    "surfcov": ["surfcov"],
    "added": ["added"],
    "unmodradius (m)": ["unmod_radius"],
}
# column of each field per CSV format; parent ids: SimpleForest 0-based with -1 = none, aRchi
# 1-based with 0 = none
_SIMPLEFOREST = {
    "id": "ID", "parent": "parentID", "start_x": "startX", "start_y": "startY",
    "start_z": "startZ", "end_x": "endX", "end_y": "endY", "end_z": "endZ", "radius": "radius",
    "branch_order": "branchOrder", "branch": "segmentID",
}  # fmt: skip
_ARCHI = {
    "id": "cyl_ID", "parent": "parent_ID", "start_x": "startX", "start_y": "startY",
    "start_z": "startZ", "end_x": "endX", "end_y": "endY", "end_z": "endZ",
    "radius": "radius_cyl", "branch_order": "branching_order", "branch": "axis_ID",
}  # fmt: skip


@dataclass(frozen=True)
class Cylinders:
    """A QSM's cylinder table, in metres, in the file's coordinates.

    Attributes (n cylinders):
      start, end: [n, 3] m. radius: [n] m.
      parent: [n] index of the parent cylinder in these arrays, -1 for the root.
      ids: [n] the cylinder ids as the file numbers them (what ``grasp_cylinder`` names).
      order: [n] the tool's branch order, 0 = stem. branch: [n] the tool's branch/axis id.
      lines: [n] the file line of each cylinder (1-based; for ``.mat`` the 1-based index).
      source, fmt, units: the file, its format and the unit it was read in.
    """

    start: np.ndarray
    end: np.ndarray
    radius: np.ndarray
    parent: np.ndarray
    ids: np.ndarray
    order: np.ndarray
    branch: np.ndarray
    lines: np.ndarray
    source: str
    fmt: str
    units: str

    @property
    def n(self) -> int:
        return int(self.radius.shape[0])

    @property
    def length(self) -> np.ndarray:
        return np.linalg.norm(self.end - self.start, axis=1)

    def where(self, i: int) -> str:
        """``file, line L (cylinder ID)``: where cylinder ``i`` is, for error messages."""
        what = "cylinder" if self.fmt == "treeqsm-mat" else "line"
        return f"{self.source}, {what} {int(self.lines[i])} (cylinder {int(self.ids[i])})"

    def index_of(self, cylinder_id: int) -> int:
        hit = np.flatnonzero(self.ids == int(cylinder_id))
        if hit.size == 0:
            raise TreeFileError(
                f"{self.source}: no cylinder with id {cylinder_id} (ids run from "
                f"{int(self.ids.min())} to {int(self.ids.max())})"
            )
        return int(hit[0])


# ---- reading --------------------------------------------------------------------------------
def read_qsm(path: str | Path, fmt: str | None = None, units: str | None = None) -> Cylinders:
    """Read a QSM cylinder table (see the module docstring for ``fmt`` and ``units``) and check
    it (:func:`check_cylinders`).

    Raises:
        TreeFileError: unreadable file, unknown layout, malformed value (file, line, column),
            or a table that is not a tree (cycles, missing parents, non-positive radius, a
            cylinder far from its parent).
    """
    path = Path(path)
    if not path.is_file():
        raise TreeFileError(f"{path}: no such QSM file")
    if fmt is not None and fmt not in FORMATS:
        raise TreeFileError(f"QSM format {fmt!r}: expected one of {', '.join(FORMATS)}")
    if units is not None and units not in UNITS:
        raise TreeFileError(f"QSM units {units!r}: expected one of {', '.join(UNITS)}")
    if fmt == "treeqsm-mat" or (fmt is None and path.suffix.lower() == ".mat"):
        cols, lines, fmt = _read_mat(path), None, "treeqsm-mat"
    else:
        rows, header, first_line = _read_text(path)
        cols, fmt = _columns(path, rows, header, first_line, fmt)
        lines = np.arange(len(rows)) + first_line
    cyl = _assemble(path, cols, lines, fmt)
    cyl = _scale(cyl, units)
    check_cylinders(cyl)
    return cyl


def _read_text(path: Path) -> tuple[list[list[str]], list[str] | None, int]:
    """Rows of cells, the header (None if the first line holds numbers) and the file line of
    the first data row. Comma-separated if the first line has a comma, else tabs/whitespace."""
    try:
        text = path.read_text(encoding="utf-8-sig", errors="strict")
    except UnicodeDecodeError as e:
        raise TreeFileError(f"{path}: not a text file ({e.reason} at byte {e.start})") from None
    lines = text.splitlines()
    while lines and not lines[-1].strip():
        lines.pop()
    if not lines:
        raise TreeFileError(f"{path}: empty file")
    if "," in lines[0]:
        rows = [[c.strip() for c in r] for r in csv.reader(lines)]
    elif "\t" in lines[0]:
        rows = [[c.strip() for c in ln.split("\t")] for ln in lines]
    else:
        rows = [ln.split() for ln in lines]
    has_header = not all(_is_number(c) for c in rows[0])  # "nan" is a (bad) number, no name
    header = rows[0] if has_header else None
    return (rows[1:], header, 2) if has_header else (rows, None, 1)


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _columns(path, rows, header, first_line, fmt) -> tuple[dict[str, np.ndarray], str]:
    if header is None:
        if fmt not in (None, "treeqsm-txt"):
            raise TreeFileError(f"{path}: no header line; a {fmt} file starts with one")
        return _treeqsm_v23(path, rows, first_line), "treeqsm-txt"
    names = [h.strip() for h in header]
    lower = [h.lower() for h in names]
    guess = (
        "simpleforest"
        if {"id", "parentid", "radius"} <= set(lower)
        else "archi"
        if {"cyl_id", "parent_id", "radius_cyl"} <= set(lower)
        else "treeqsm-txt"
        if "radius (m)" in lower and "parent" in lower
        else None
    )
    fmt = fmt or guess
    if fmt is None:
        raise TreeFileError(
            f"{path}, line 1: header {names[:6]}... is no QSM layout treeinfer knows (TreeQSM "
            "cylinder_*.txt, SimpleForest CSV, aRchi CSV); name the format if it is one of them"
        )
    if fmt == "treeqsm-txt":
        fields: list[str] = []
        for h in lower:
            if h not in _TREEQSM_V24_HEADER:
                raise TreeFileError(f"{path}, line 1: unknown TreeQSM column {h!r}")
            fields += _TREEQSM_V24_HEADER[h]
        return _numeric(path, rows, fields, first_line), fmt
    spec = _SIMPLEFOREST if fmt == "simpleforest" else _ARCHI
    where = {h: j for j, h in enumerate(names)}
    missing = [col for col in spec.values() if col not in where]
    if missing:
        raise TreeFileError(
            f"{path}, line 1: a {fmt} table needs column(s) {missing}; the header has {names}"
        )
    fields = [None] * len(names)
    for key, col in spec.items():
        fields[where[col]] = key
    return _numeric(path, rows, fields, first_line, names), fmt


def _numeric(path, rows, fields, first_line, names=None) -> dict[str, np.ndarray]:
    """Parse the columns named in ``fields`` (None: skipped) as floats; errors name the line
    and the column."""
    out = {f: np.empty(len(rows)) for f in fields if f is not None}
    for r, row in enumerate(rows):
        line = first_line + r
        if len(row) != len(fields):
            raise TreeFileError(f"{path}, line {line}: {len(row)} columns, expected {len(fields)}")
        for j, f in enumerate(fields):
            if f is None:
                continue
            col = names[j] if names else f
            try:
                v = float(row[j])
            except ValueError:
                raise TreeFileError(
                    f"{path}, line {line}, column '{col}': expected a number, got {row[j]!r}"
                ) from None
            if not math.isfinite(v):
                raise TreeFileError(f"{path}, line {line}, column '{col}': {row[j]} (not finite)")
            out[f][r] = v
    return out


def _treeqsm_v23(path, rows, first_line) -> dict[str, np.ndarray]:
    """The headerless 15-column TreeQSM 2.3 table. The released ``save_model_text`` writes
    branch, order, position, added, unmodified radius after the extension; the field order of
    the .mat structure (added, unmodified radius, branch, order, position) is accepted too:
    column 15 holds a radius (not an integer) in the first, column 12 in the second."""
    if not rows or len(rows[0]) != 15:
        n = len(rows[0]) if rows else 0
        raise TreeFileError(
            f"{path}, line {first_line}: {n} columns; a TreeQSM 2.3 cylinder table without a "
            "header has 15 (radius, length, start xyz, axis xyz, parent, extension, branch, "
            "branch order, position in branch, added, unmodified radius)"
        )
    cols = _numeric(path, rows, list(TREEQSM_V23_COLUMNS), first_line)
    integral = {
        k: bool(np.all(cols[k] == np.round(cols[k])))
        for k in ("branch", "branch_order", "position_in_branch", "unmod_radius")
    }
    if integral["branch"] and integral["branch_order"] and integral["position_in_branch"]:
        return cols  # save_model_text's order (an all-integer radius column cannot be radii)
    alt = dict(zip(_TREEQSM_V23_ALT, (cols[k] for k in TREEQSM_V23_COLUMNS)))
    if all(np.all(alt[k] == np.round(alt[k])) for k in ("branch", "branch_order")):
        return alt
    raise TreeFileError(
        f"{path}: a 15-column table whose columns 11-15 are neither TreeQSM 2.3 order (branch, "
        "order, position, added, unmodified radius) nor the .mat order (added, unmodified "
        "radius, branch, order, position)"
    )


def _read_mat(path: Path) -> dict[str, np.ndarray]:
    import scipy.io

    try:
        m = scipy.io.loadmat(path, squeeze_me=True, struct_as_record=False)
    except (ValueError, TypeError, OSError, NotImplementedError) as e:
        raise TreeFileError(
            f"{path}: not a MATLAB file scipy can read ({e}); a v7.3 (HDF5) file must be saved "
            "again with save(..., '-v7')"
        ) from None
    qsm = None
    for name, v in m.items():
        if name.startswith("__"):
            continue
        v = np.atleast_1d(v).ravel()[0] if isinstance(v, np.ndarray) and v.dtype == object else v
        if hasattr(v, "_fieldnames") and "cylinder" in v._fieldnames:
            qsm = v
            break
    if qsm is None:
        raise TreeFileError(
            f"{path}: no variable holds a TreeQSM structure (a struct with a 'cylinder' field); "
            f"variables: {[k for k in m if not k.startswith('__')]}"
        )
    c = qsm.cylinder
    need = ("radius", "length", "start", "axis", "parent")
    missing = [f for f in need if f not in c._fieldnames]
    if missing:
        raise TreeFileError(f"{path}: QSM.cylinder lacks field(s) {missing}")
    n = np.atleast_1d(c.radius).shape[0]
    out: dict[str, np.ndarray] = {}
    for f, key in (("radius", "radius"), ("length", "length"), ("parent", "parent"),
                   ("branch", "branch"), ("BranchOrder", "branch_order")):  # fmt: skip
        if f in c._fieldnames:
            out[key] = np.atleast_1d(np.asarray(getattr(c, f), float)).reshape(-1)
    for f in ("start", "axis"):
        a = np.asarray(getattr(c, f), float).reshape(n, 3)
        for k, ax in enumerate("xyz"):
            out[f"{f}_{ax}"] = a[:, k]
    for key, a in out.items():
        if a.shape[0] != n:
            raise TreeFileError(f"{path}: QSM.cylinder.{key} has {a.shape[0]} rows, radius {n}")
        bad = np.flatnonzero(~np.isfinite(a))
        if bad.size:
            raise TreeFileError(f"{path}, cylinder {bad[0] + 1}, field '{key}': not finite")
    return out


def _assemble(path: Path, cols: dict[str, np.ndarray], lines, fmt: str) -> Cylinders:
    """One :class:`Cylinders` from the parsed columns (TreeQSM: start + axis * length; CSVs:
    start and end)."""
    n = cols["radius"].shape[0]
    if n == 0:
        raise TreeFileError(f"{path}: no cylinders")
    lines = np.arange(1, n + 1) if lines is None else np.asarray(lines)
    start = np.stack([cols["start_x"], cols["start_y"], cols["start_z"]], axis=1)
    if fmt.startswith("treeqsm"):
        axis = np.stack([cols["axis_x"], cols["axis_y"], cols["axis_z"]], axis=1)
        norm = np.linalg.norm(axis, axis=1)
        bad = np.flatnonzero(np.abs(norm - 1.0) > 0.01)
        if bad.size:
            i = int(bad[0])
            raise TreeFileError(
                f"{path}, {'cylinder' if fmt == 'treeqsm-mat' else 'line'} {int(lines[i])}: "
                f"axis direction has length {norm[i]:.4g}, not 1"
            )
        end = start + axis / norm[:, None] * cols["length"][:, None]
        ids = np.arange(1, n + 1)
        parent_ids = cols["parent"]  # 1-based, 0 = none
        none = 0
    else:
        end = np.stack([cols["end_x"], cols["end_y"], cols["end_z"]], axis=1)
        ids = cols["id"].astype(np.int64)
        parent_ids = cols["parent"]
        none = -1 if fmt == "simpleforest" else 0
    pos = {int(v): i for i, v in enumerate(ids)}
    if len(pos) != n:
        dup = next(int(v) for v in ids if np.sum(ids == v) > 1)
        raise TreeFileError(f"{path}: cylinder id {dup} appears more than once")
    parent = np.full(n, -1, dtype=np.int64)
    for i, p in enumerate(parent_ids):
        if p == none:
            continue
        if int(p) not in pos:
            raise TreeFileError(
                f"{path}, {'cylinder' if fmt == 'treeqsm-mat' else 'line'} {int(lines[i])} "
                f"(cylinder {int(ids[i])}): parent {int(p)} is no cylinder of the table"
            )
        parent[i] = pos[int(p)]
    order = cols.get("branch_order", np.zeros(n)).astype(np.int64)
    if fmt == "archi":
        order = order - 1  # aRchi counts the trunk as order 1
    branch = cols.get("branch", np.zeros(n)).astype(np.int64)
    return Cylinders(
        start=start,
        end=end,
        radius=np.asarray(cols["radius"], float),
        parent=parent,
        ids=ids,
        order=order,
        branch=branch,
        lines=lines,
        source=str(path),
        fmt=fmt,
        units="m",
    )


def _scale(cyl: Cylinders, units: str | None) -> Cylinders:
    if units is None:
        lo, hi = cyl.start.min(axis=0), cyl.end.max(axis=0)
        height = float(max(hi[2], cyl.start[:, 2].max()) - min(lo[2], cyl.end[:, 2].min()))
        if height > MAX_HEIGHT_M or float(cyl.radius.max()) > 5.0:
            raise TreeFileError(
                f"{cyl.source}: the tree is {height:.4g} units tall with a thickest radius of "
                f"{float(cyl.radius.max()):.4g}: not metres; give the unit (cm or mm)"
            )
        units = "m"
    f = UNITS[units]
    return Cylinders(
        **{
            **cyl.__dict__,
            "start": cyl.start * f,
            "end": cyl.end * f,
            "radius": cyl.radius * f,
            "units": units,
        }
    )


# ---- checks ---------------------------------------------------------------------------------
def check_cylinders(cyl: Cylinders, gap_factor: float = 3.0, gap_floor: float = 0.05) -> None:
    """Refuse a table that is not a tree of cylinders: non-positive radius or length, not one
    root, a parent cycle, or a cylinder that starts farther than ``gap_factor`` parent radii
    plus ``gap_floor`` m from its parent's axis segment (TreeQSM starts a branch on its
    parent's surface, part-way along it, and leaves small gaps; a larger gap is a broken
    table). Errors name the row."""
    bad = np.flatnonzero(~(cyl.radius > 0))
    if bad.size:
        i = int(bad[0])
        raise TreeFileError(f"{cyl.where(i)}: radius {cyl.radius[i]:g} must be positive")
    length = cyl.length
    bad = np.flatnonzero(~(length > 0))
    if bad.size:
        raise TreeFileError(f"{cyl.where(int(bad[0]))}: zero length (start equals end)")
    roots = np.flatnonzero(cyl.parent < 0)
    if roots.size != 1:
        which = ", ".join(cyl.where(int(i)) for i in roots[:3])
        raise TreeFileError(
            f"{cyl.source}: {roots.size} cylinders without a parent, expected one root"
            + (f" ({which})" if roots.size else " (every cylinder has a parent: a cycle)")
        )
    reached = np.zeros(cyl.n, bool)
    for i in topological_order(cyl):
        reached[i] = True
    if not reached.all():
        i = int(np.flatnonzero(~reached)[0])
        raise TreeFileError(
            f"{cyl.where(i)}: not connected to the root (its chain of parents is a cycle)"
        )
    for i in np.flatnonzero(cyl.parent >= 0):
        p = int(cyl.parent[i])
        d = _point_segment_distance(cyl.start[i], cyl.start[p], cyl.end[p])
        limit = gap_factor * cyl.radius[p] + gap_floor
        if d > limit:
            raise TreeFileError(
                f"{cyl.where(int(i))}: starts {d:.3g} m from its parent (cylinder "
                f"{int(cyl.ids[p])}), more than {limit:.3g} m: a broken table or wrong parent id"
            )


def topological_order(cyl: Cylinders) -> list[int]:
    """Cylinder indices from the root, parents before children (breadth first); cylinders
    outside the root's tree are left out."""
    children = children_of(cyl)
    roots = [int(i) for i in np.flatnonzero(cyl.parent < 0)]
    out, queue = [], roots[:1]
    while queue:
        i = queue.pop()
        out.append(i)
        queue.extend(children[i])
    return out


def children_of(cyl: Cylinders) -> list[list[int]]:
    children: list[list[int]] = [[] for _ in range(cyl.n)]
    for i, p in enumerate(cyl.parent):
        if p >= 0:
            children[int(p)].append(i)
    return children


def _point_segment_distance(x, a, b) -> float:
    ab = b - a
    t = float(np.clip(np.dot(x - a, ab) / max(float(np.dot(ab, ab)), 1e-300), 0.0, 1.0))
    return float(np.linalg.norm(x - (a + t * ab)))
