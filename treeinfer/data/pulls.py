"""Where and in which direction each recorded pull acted: the data folder's ``pulls.yaml``.

A data set may hold pulls at several grasp points and in several directions (a branch probed
at three heights, pushed sideways while driving along a row). Each trajectory CSV says only
what was measured (time, force, displacement along the pull); this small sidecar file beside
the CSVs says where the force acted and in which direction::

    # pulls.yaml (written by import-csv / import-bag; edit freely)
    default:                       # optional: for CSV files not listed below
      branch: stem                 # grasped branch (default: the tree file's grasp.branch)
      fraction: 1.0                # along the branch from its joint, in (0, 1]
      direction: down              # down | horizontal | [x, y, z]
    pulls:
      push_low.csv:  {branch: stem, distance: 0.10, direction: horizontal}
      push_mid.csv:  {branch: stem, fraction: 0.6}
      push_high.csv: {branch: tip, fraction: 1.0, direction: [1, 0, 0]}

Per entry (every field optional, missing ones come from ``default``, then from the tree file):

* ``branch``: the grasped branch's name.
* ``fraction`` (0 < f <= 1, of the branch's length from its joint) **or** ``distance``
  (metres from the branch's joint, 0 < d <= length). Not both.
* ``trimmed`` (by ``import-csv --trim``): what was cut, for the record (``ends_with``).
* ``direction`` of the force the robot applies on the branch, in world coordinates:
  ``down`` (along gravity, the paper's pulls), ``horizontal`` (horizontal and perpendicular to
  the grasped branch at its rest geometry: ``up x axis``; for a vertical branch, its bending
  direction, the base's heading) or a vector ``[x, y, z]`` (any length but zero). The
  recorded displacement is the grasp point's motion along this direction, and force is
  positive when it pushes the branch along it.

The tree file may set the data set's default direction with ``pull: {direction: ...}``
(:func:`parse_tree_pull`); without it the default is ``down``.

Errors raise :class:`~treeinfer.errors.ConfigError` naming the file, the entry and the field.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from ..errors import ConfigError
from ..io.atomic import atomic_write_text
from ..tree.description import DIRECTION_WORDS, parse_direction, parse_tree_pull
from .pull_checks import check_pull_moves, check_same_pull, pull_leverage

__all__ = [
    "DIRECTION_WORDS",
    "PULLS_FILE",
    "PullSpec",
    "PullsFile",
    "ResolvedPull",
    "check_pull_moves",
    "check_same_pull",
    "data_grasp_fractions",
    "load_data_pulls",
    "parse_direction",
    "parse_tree_pull",
    "pull_direction",
    "pull_leverage",
    "pull_spec",
    "pulls_from_dict",
    "read_pulls",
    "resolve_pull",
    "resolve_pulls",
    "spec_to_dict",
    "stack_resolved",
    "write_pulls",
]

PULLS_FILE = "pulls.yaml"
_ENTRY_KEYS = {"branch", "fraction", "distance", "direction", "trimmed"}
_TOP_KEYS = {"default", "pulls"}
VERTICAL_COS = 1.0 - 1e-9  # |axis . up| above this: the branch counts as vertical


class PullSpec(NamedTuple):
    """One pull as written in the sidecar (``None``: not given, inherit).

    Attributes:
        branch: grasped branch name.
        fraction: grasp point as a fraction of the branch length from its joint, (0, 1].
        distance: grasp point in metres from the branch's joint (exclusive with ``fraction``).
        direction: ``"down"``, ``"horizontal"`` or a tuple of 3 floats (world, any length > 0).
        trimmed: what ``import-csv --trim`` removed (a record; never inherited).
    """

    branch: str | None = None
    fraction: float | None = None
    distance: float | None = None
    direction: str | tuple[float, float, float] | None = None
    trimmed: dict | None = None


class PullsFile(NamedTuple):
    """A parsed sidecar: ``default`` entry and per-file entries (keys: CSV file names)."""

    default: PullSpec
    pulls: dict[str, PullSpec]
    source: str = PULLS_FILE


class ResolvedPull(NamedTuple):
    """A pull ready for the simulator.

    Attributes:
        branch: grasped branch name. fraction: (0, 1] of its length from its joint.
        direction: [3] unit world vector of the applied force.
        label: human-readable direction as given (``down``, ``horizontal``, ``[x, y, z]``).
    """

    branch: str
    fraction: float
    direction: np.ndarray
    label: str = "down"


# ----------------------------------------------------------------------------- parsing


def _where(source: str, entry: str, fld: str) -> str:
    return f"{source}: {entry}: field '{fld}'"


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool):
        raise ConfigError(f"{where}: expected a number, got {value!r}")
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: expected a number, got {value!r}") from None
    if not math.isfinite(v):
        raise ConfigError(f"{where}: must be finite, got {v}")
    return v


def pull_spec(entry: Any, source: str = PULLS_FILE, name: str = "entry") -> PullSpec:
    """Parse one sidecar entry (a mapping) into a :class:`PullSpec` (tree-free checks only)."""
    if entry is None:
        return PullSpec()
    if not isinstance(entry, Mapping):
        raise ConfigError(
            f"{source}: {name}: expected a mapping with {sorted(_ENTRY_KEYS)}, got {entry!r}"
        )
    bad = set(entry) - _ENTRY_KEYS
    if bad:
        raise ConfigError(
            f"{source}: {name}: unknown field(s) {sorted(map(str, bad))}; "
            f"allowed: {sorted(_ENTRY_KEYS)}"
        )
    if "fraction" in entry and "distance" in entry:
        raise ConfigError(
            f"{source}: {name}: give either 'fraction' or 'distance' of the grasp point, not both"
        )
    branch = entry.get("branch")
    if branch is not None and (not isinstance(branch, str) or not branch):
        raise ConfigError(
            f"{_where(source, name, 'branch')}: expected a branch name, got {branch!r}"
        )
    fraction = distance = None
    if entry.get("fraction") is not None:
        fraction = _number(entry["fraction"], _where(source, name, "fraction"))
        if not 0.0 < fraction <= 1.0:
            raise ConfigError(
                f"{_where(source, name, 'fraction')}: must be in (0, 1] (a fraction of the "
                f"branch length from its joint), got {fraction:g}"
            )
    if entry.get("distance") is not None:
        distance = _number(entry["distance"], _where(source, name, "distance"))
        if distance <= 0.0:
            raise ConfigError(
                f"{_where(source, name, 'distance')}: must be > 0 m from the branch's joint, "
                f"got {distance:g}"
            )
    direction = None
    if entry.get("direction") is not None:
        direction = parse_direction(entry["direction"], _where(source, name, "direction"))
    trimmed = entry.get("trimmed")
    if trimmed is not None and not (
        isinstance(trimmed, Mapping)
        and all(isinstance(v, (str, int, float)) for v in trimmed.values())
    ):
        raise ConfigError(f"{_where(source, name, 'trimmed')}: expected a mapping, got {trimmed!r}")
    return PullSpec(
        branch, fraction, distance, direction, None if trimmed is None else dict(trimmed)
    )


def _check_against_tree(spec: PullSpec, tree, source: str, name: str) -> None:
    if spec.branch is not None and spec.branch not in tree.names:
        raise ConfigError(
            f"{_where(source, name, 'branch')}: unknown branch '{spec.branch}'; "
            f"the tree has: {', '.join(tree.names)}"
        )
    if spec.distance is not None:
        branch = spec.branch or tree.grasp_branch
        length = tree.branch(branch).length
        if spec.distance > length * (1.0 + 1e-9):
            raise ConfigError(
                f"{_where(source, name, 'distance')}: {spec.distance:g} m is beyond the end of "
                f"branch '{branch}' ({length:g} m long)"
            )


def read_pulls(path: str | os.PathLike, tree=None) -> PullsFile:
    """Read and validate a ``pulls.yaml`` (against ``tree`` when given).

    Raises:
        ConfigError: unreadable file, invalid YAML (with its line), unknown fields, unknown
            branch, fraction out of (0, 1], distance beyond the branch, bad or zero direction.
    """
    import yaml

    from ..io.safe_load import read_regular_file

    path = Path(path)
    try:  # a FIFO or device is refused unopened
        text = read_regular_file(path, "pulls file", ConfigError).decode("utf-8")
    except UnicodeDecodeError as e:
        raise ConfigError(f"{path}: cannot read the pulls file ({e})") from None
    try:
        d = yaml.safe_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        line = f", line {mark.line + 1}" if mark is not None else ""
        raise ConfigError(f"{path}{line}: invalid YAML: {getattr(e, 'problem', e)}") from None
    return pulls_from_dict(d, tree, str(path))


def pulls_from_dict(d: Any, tree=None, source: str = PULLS_FILE) -> PullsFile:
    """Validate the parsed content of a pulls file (see :func:`read_pulls`)."""
    if d is None:
        d = {}
    if not isinstance(d, Mapping):
        raise ConfigError(
            f"{source}: expected a mapping with 'default' and 'pulls' at the top level"
        )
    bad = set(d) - _TOP_KEYS
    if bad:
        raise ConfigError(
            f"{source}: unknown top-level field(s) {sorted(map(str, bad))}; allowed: default, pulls"
        )
    default = pull_spec(d.get("default"), source, "default")
    raw = d.get("pulls") or {}
    if not isinstance(raw, Mapping):
        raise ConfigError(f"{source}: pulls: expected a mapping {{file.csv: {{...}}}}, got {raw!r}")
    pulls = {}
    for name, entry in raw.items():
        if not isinstance(name, str) or not name or "/" in name or "\\" in name:
            raise ConfigError(f"{source}: pulls: entry names must be CSV file names, got {name!r}")
        pulls[name] = pull_spec(entry, source, f"pulls.{name}")
    if tree is not None:
        _check_against_tree(default, tree, source, "default")
        for name, spec in pulls.items():
            merged = _merge(spec, default)
            _check_against_tree(merged, tree, source, f"pulls.{name}")
    return PullsFile(default, pulls, source)


def spec_to_dict(spec: PullSpec) -> dict:
    out: dict[str, Any] = {}
    if spec.branch is not None:
        out["branch"] = spec.branch
    if spec.fraction is not None:
        out["fraction"] = float(spec.fraction)
    if spec.distance is not None:
        out["distance"] = float(spec.distance)
    if spec.direction is not None:
        d = spec.direction
        out["direction"] = d if isinstance(d, str) else [float(x) for x in d]
    if spec.trimmed:
        out["trimmed"] = dict(spec.trimmed)
    return out


def write_pulls(
    path: str | os.PathLike,
    pulls: Mapping[str, PullSpec],
    default: PullSpec | None = None,
    header: str = "",
) -> Path:
    """Write a sidecar atomically (entries validated as :func:`read_pulls` would, tree-free).

    Args:
        path: destination, normally ``<data folder>/pulls.yaml``.
        pulls: CSV file name -> :class:`PullSpec`.
        default: the ``default`` entry, if any.
        header: comment written at the top (one ``#`` per line).
    """
    import yaml

    d: dict[str, Any] = {}
    if default is not None and spec_to_dict(default):
        d["default"] = spec_to_dict(default)
    d["pulls"] = {name: spec_to_dict(spec) for name, spec in pulls.items()}
    pulls_from_dict(d, None, str(path))  # same checks as reading
    lines = [f"# {h}".rstrip() for h in header.split("\n")] if header else []
    text = "\n".join(lines + [yaml.safe_dump(d, sort_keys=False, default_flow_style=None)])
    return atomic_write_text(path, text if text.endswith("\n") else text + "\n")


# ----------------------------------------------------------------------------- resolution


def _merge(spec: PullSpec, default: PullSpec) -> PullSpec:
    """``spec``'s fields, else ``default``'s; a grasp point is taken as a whole (fraction or
    distance from the same entry), and a default grasp point naming a branch applies only to
    that branch."""
    branch = spec.branch if spec.branch is not None else default.branch
    if spec.fraction is not None or spec.distance is not None:
        fraction, distance = spec.fraction, spec.distance
    elif spec.branch is None or default.branch is None or spec.branch == default.branch:
        fraction, distance = default.fraction, default.distance
    else:
        fraction = distance = None
    direction = spec.direction if spec.direction is not None else default.direction
    return PullSpec(branch, fraction, distance, direction, spec.trimmed)


def pull_direction(tree, branch: str, direction: str | Sequence[float]) -> np.ndarray:
    """Unit world vector [3] of ``direction`` for a pull on ``branch`` of ``tree``.

    ``down`` is along the tree's gravity; ``horizontal`` is ``up x axis`` normalised, with
    ``axis`` the branch's direction at its geometric rest pose (from its joint towards its
    tip); for a vertical branch, where that vanishes, the base's heading ``(cos yaw, sin yaw,
    0)``, which lies in a vertical stem's bending plane. A vector is normalised. The same
    convention as the simulator's :func:`treeinfer.data.direction.pull_direction` (this calls
    it), so data, sidecar and simulation agree on the sign.
    """
    from .direction import pull_direction as _sim_direction

    g = np.asarray(tree.gravity, float)
    if np.linalg.norm(g) == 0:
        raise ConfigError("tree gravity is zero: 'down' and 'horizontal' are undefined")
    if isinstance(direction, str):
        word = direction.strip().lower()
        if word not in DIRECTION_WORDS:
            raise ConfigError(f"direction: unknown word {direction!r}; expected down or horizontal")
        return _sim_direction(tree, word, branch)
    v = np.asarray(parse_direction(direction), float)
    return v / np.linalg.norm(v)


def _direction_label(direction) -> str:
    if direction is None:
        return "down"
    if isinstance(direction, str):
        return direction
    return "[" + ", ".join(f"{float(x):g}" for x in direction) + "]"


def resolve_pull(
    spec: PullSpec | None,
    tree,
    default: PullSpec | None = None,
    default_direction: str | Sequence[float] | None = None,
    source: str = PULLS_FILE,
    name: str = "entry",
) -> ResolvedPull:
    """Fill in a pull from ``default``, then from the tree (grasp and ``pull.direction``).

    Args:
        spec: the file's entry (``None``: not listed).
        tree: :class:`treeinfer.tree.description.Tree`.
        default: the sidecar's ``default`` entry.
        default_direction: the tree file's ``pull.direction``; ``None``: ``getattr(tree,
            "pull_direction",
    "pull_leverage", "down")``.

    Raises:
        ConfigError: unknown branch, grasp point outside the branch, bad direction.
    """
    merged = _merge(spec or PullSpec(), default or PullSpec())
    _check_against_tree(merged, tree, source, name)
    branch = merged.branch or tree.grasp_branch
    if merged.distance is not None:
        fraction = merged.distance / tree.branch(branch).length
        fraction = min(fraction, 1.0)
    elif merged.fraction is not None:
        fraction = merged.fraction
    elif branch == tree.grasp_branch:
        fraction = tree.grasp_fraction
    else:
        fraction = 1.0
    if merged.direction is not None:
        direction = merged.direction
    elif default_direction is not None:
        direction = default_direction
    else:
        direction = getattr(tree, "pull_direction", "down")
    try:
        vec = pull_direction(tree, branch, direction)
    except ConfigError as e:
        raise ConfigError(f"{_where(source, name, 'direction')}: {e}") from None
    return ResolvedPull(branch, float(fraction), vec, _direction_label(direction))


def resolve_pulls(
    files: Iterable[str | os.PathLike],
    tree,
    sidecar: PullsFile | None = None,
    default_direction: str | Sequence[float] | None = None,
) -> list[ResolvedPull]:
    """One :class:`ResolvedPull` per trajectory file (matched by file name) in order.

    Entries of ``sidecar`` that match none of ``files`` are ignored (a subset of a data
    folder may be used, e.g. leave-one-out).
    """
    sidecar = sidecar or PullsFile(PullSpec(), {})
    out = []
    for f in files:
        name = Path(f).name
        out.append(
            resolve_pull(
                sidecar.pulls.get(name),
                tree,
                sidecar.default,
                default_direction,
                sidecar.source,
                f"pulls.{name}" if name in sidecar.pulls else "default",
            )
        )
    return out


def load_data_pulls(
    data_dir: str | os.PathLike,
    tree,
    files: Iterable[str | os.PathLike] | None = None,
    default_direction: str | Sequence[float] | None = None,
) -> list[ResolvedPull]:
    """Resolve the pulls of a data folder: reads ``<data_dir>/pulls.yaml`` if it exists.

    ``files`` defaults to the folder's ``*.csv`` sorted by name (the order of
    :func:`treeinfer.data.trajectories.read_trajectory_dir`).
    """
    data_dir = Path(data_dir)
    side = data_dir / PULLS_FILE
    sidecar = read_pulls(side, tree) if side.is_file() else None
    if files is None:
        files = sorted(p.name for p in data_dir.glob("*.csv") if p.is_file())
    return resolve_pulls(files, tree, sidecar, default_direction)


def data_grasp_fractions(
    data_dir: str | os.PathLike,
    tree,
    sources: Sequence[str],
    any_branch: bool = False,
    any_direction: bool = False,
) -> np.ndarray | None:
    """Per-trajectory grasp fractions [B] from a data folder's ``pulls.yaml`` (``None`` if the
    folder has none), for a simulator that takes one fraction per profile.

    Args:
        sources: the trajectories' file names, in the order they are stacked.
        any_branch, any_direction: whether the caller's simulator supports grasp branches other
            than the tree's and directions other than ``down``; if not, such pulls are refused.

    Raises:
        ConfigError: naming the file and what the simulator cannot do.
    """
    side = Path(data_dir) / PULLS_FILE
    if not side.is_file():
        return None
    resolved = load_data_pulls(data_dir, tree, [Path(s).name for s in sources])
    down = pull_direction(tree, tree.grasp_branch, "down")
    for name, r in zip(sources, resolved):
        if not any_branch and r.branch != tree.grasp_branch:
            raise ConfigError(
                f"{side}: {Path(name).name} was grasped on branch '{r.branch}', but this model "
                f"pulls only on the tree's grasp branch '{tree.grasp_branch}'"
            )
        if not any_direction and float(r.direction @ down) < 1.0 - 1e-9:
            raise ConfigError(
                f"{side}: {Path(name).name} was pulled {r.label}, but this model pulls only "
                "down (along gravity)"
            )
        stuck = check_pull_moves(tree, r, f"{side}: {Path(name).name}")
        if stuck is not None:
            raise ConfigError(stuck)
    return np.asarray([r.fraction for r in resolved], float)


def stack_resolved(resolved: Sequence[ResolvedPull], tree=None):
    """Batch arrays for the simulator: (branches [B] names, fractions [B], directions [B, 3]).

    With ``tree``, also checks every branch exists."""
    if tree is not None:
        for r in resolved:
            tree.branch(r.branch)
    branches = tuple(r.branch for r in resolved)
    fractions = np.asarray([r.fraction for r in resolved], float)
    directions = np.asarray([r.direction for r in resolved], float).reshape(len(resolved), 3)
    return branches, fractions, directions
