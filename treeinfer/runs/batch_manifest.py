"""The manifest of ``treeinfer batch``: one row per item (a tree, its recordings, optionally
held-out pulls, a grasp point and a few infer options), read from CSV or YAML and validated as
a whole before any work (:func:`read_manifest`).

CSV: a header line with ``id``, ``tree``, ``recordings`` and any of ``test``,
``grasp_fraction`` and the option names of :data:`ITEM_OPTIONS` as further columns; an empty
cell takes the default; lines starting with ``#`` and blank lines are skipped. YAML: a list of
items, or ``{defaults: {OPTION: value}, items: [...]}``, each item a mapping with ``id``,
``tree``, ``recordings`` and optionally ``test``, ``grasp_fraction`` and ``options: {...}``.
Relative paths are taken from the manifest's folder.

What makes the whole manifest unusable (unreadable, no items, an unknown column, a malformed
YAML layout) raises :class:`~treeinfer.errors.ConfigError` at once. What concerns one row (a
missing file, a duplicate id, an unknown or out-of-range option) is collected on the item
(:attr:`Item.error`, naming file, line and field): ``batch`` reports every one before it starts
and records those rows as ``invalid`` in the results table while the others run.
"""

from __future__ import annotations

import csv
import dataclasses
import difflib
import hashlib
import io
import json
import math
import re
from dataclasses import MISSING, dataclass, fields
from pathlib import Path
from typing import Any

from ..errors import ConfigError, TreeinferError, where
from ..io.provenance import data_manifest, file_sha256
from ..io.safe_load import list_data_files, load_file, read_regular_file
from .config import OPTION_FIELDS, RunConfig

# The infer options a manifest may set per item (a small, validated set: the ones that change
# what is inferred or how long it takes; paths and --force belong to the batch). name -> kind
ITEM_OPTIONS: dict[str, str] = {
    "sampler": "str",
    "particles": "int",
    "iterations": "int",
    "seed": "int",
    "likelihood": "str",
    "init": "str",
    "backend": "str",
    "model_kind": "str",
    "gradients": "str",
    "kT": "float_or_auto",
    "noise_displacement": "float",
    "noise_force": "noise_force",
    "noise_velocity": "float",
    "eta": "float",
    "prior_tail": "float",
    "stop_when_converged": "bool",
    "reinit_stragglers": "int",
    "max_unstable_share": "float",
    "checkpoint_every": "int",
    "force_interp": "str",
    "max_sim_dt": "float",
    "sim_tolerance": "float",
    "shape_buckets": "str",
}
ITEM_FIELDS = ("id", "tree", "recordings", "test", "grasp_fraction")
# The run options of an item that the manifest does not set: `treeinfer infer`'s defaults (the
# run configuration's), as cli.infer_options.INFER_DEFAULTS has them.
RUN_DEFAULTS: dict[str, Any] = {
    f.name: f.default
    for f in fields(RunConfig)
    if f.default is not MISSING
    and f.name in OPTION_FIELDS
    and f.name not in ("grasp_fraction", "force", "model", "repair_inertia")
}
# An id names a folder: letters, digits, '.', '_', '-'; not the names treeinfer gives the
# siblings of a run folder (RUN.partial, RUN.old-<time>, RUN.complete-<pid>)
_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$")
_RESERVED = re.compile(r"(\.partial$|\.old-|\.complete-|\.staging$)")
_TRUE = {"true", "yes", "on", "1"}
_FALSE = {"false", "no", "off", "0"}


@dataclass(frozen=True)
class Item:
    """One manifest row, its paths resolved (absolute) and its options validated.

    ``options``: the item's explicit options (defaults and the manifest's ``defaults:``
    merged in by :meth:`run_options`). ``error``: why the row cannot run (None: valid).
    ``digests``: sha256 of the tree file and of every recording / test CSV (for the item's
    :meth:`spec_hash` and for matching a finished run folder). ``group``: items with equal
    groups have the same tree and number of recordings (compiled programs are shared best when
    they run one after another in the same worker)."""

    id: str
    line: int
    source: str
    tree: str | None = None
    recordings: str | None = None
    test: str | None = None
    grasp_fraction: float | None = None
    options: dict = dataclasses.field(default_factory=dict)
    error: str | None = None
    digests: dict = dataclasses.field(default_factory=dict)
    group: str = ""

    def run_options(self) -> dict:
        """Every run option of :func:`treeinfer.runs.infer_config` for this item."""
        return {**RUN_DEFAULTS, **self.options}

    def spec_hash(self) -> str:
        """sha256 of what the item's row depends on: its inputs' contents and its options."""
        spec = {
            "digests": self.digests,
            "grasp_fraction": self.grasp_fraction,
            "options": self.run_options(),
        }
        return hashlib.sha256(json.dumps(spec, sort_keys=True).encode()).hexdigest()


def _suggest(name: str, known) -> str:
    close = difflib.get_close_matches(name, list(known), n=1)
    return f" (did you mean '{close[0]}'?)" if close else ""


def _convert(kind: str, value: Any, loc: str) -> Any:
    """A manifest value as the option's type; CSV cells arrive as text, YAML ones typed."""
    text = value.strip() if isinstance(value, str) else None
    try:
        if kind == "int":
            if isinstance(value, bool):
                raise ValueError
            v = int(text) if text is not None else value
            if not isinstance(v, int):
                raise ValueError
            return v
        if kind == "float" or (kind in ("float_or_auto", "noise_force") and text != "auto"):
            if kind == "noise_force" and text is not None and text.endswith("%"):
                return text  # "P%": checked by the run configuration
            if isinstance(value, bool):
                raise ValueError
            v = float(text) if text is not None else float(value)
            if not math.isfinite(v):
                raise ValueError
            return v
        if kind in ("float_or_auto", "noise_force"):
            return "auto"
        if kind == "bool":
            if isinstance(value, bool):
                return value
            if text is not None and text.lower() in _TRUE | _FALSE:
                return text.lower() in _TRUE
            raise ValueError
        if isinstance(value, bool) or not isinstance(value, (str, int)):
            raise ValueError
        return str(value).strip()
    except (TypeError, ValueError):
        want = {
            "int": "an integer",
            "float": "a finite number",
            "float_or_auto": "a number or 'auto'",
            "noise_force": "newtons, 'P%' or 'auto'",
            "bool": "true or false",
            "str": "a name",
        }[kind]
        raise ConfigError(f"{loc}: expected {want}, got {value!r}") from None


def _options(raw: dict, loc_of) -> dict:
    """Typed and checked options of one item (ConfigError naming the field)."""
    out = {}
    for k, v in raw.items():
        if k not in ITEM_OPTIONS:
            raise ConfigError(
                f"{loc_of(k)}: unknown option{_suggest(str(k), ITEM_OPTIONS)}; a manifest may "
                f"set {', '.join(ITEM_OPTIONS)}"
            )
        if v is None or (isinstance(v, str) and not v.strip()):
            continue  # empty: the default
        out[k] = _convert(ITEM_OPTIONS[k], v, loc_of(k))
    for k, v in out.items():  # each option's own range check, naming its field
        try:
            RunConfig(tree="", data="", out="", **{**RUN_DEFAULTS, k: v})
        except ConfigError as e:
            raise ConfigError(f"{loc_of(k)}: {e}") from None
    try:  # and together (e.g. --noise-force with a non-Gaussian likelihood)
        RunConfig(tree="", data="", out="", **{**RUN_DEFAULTS, **out})
    except ConfigError as e:
        raise ConfigError(f"{loc_of('options')}: {e}") from None
    return out


def _folder_digests(folder: Path, loc: str) -> dict:
    if not folder.is_dir():
        raise ConfigError(f"{loc}: {folder}: no such folder")
    files, skipped = list_data_files(folder, error=ConfigError)
    if skipped:
        raise ConfigError(f"{loc}: {skipped[0]}")
    if not files:
        raise ConfigError(f"{loc}: {folder} holds no trajectory CSV (*.csv)")
    return {f["name"]: f["sha256"] for f in data_manifest(folder)}


def _item(raw: dict, line: int, source: str, base: Path, defaults: dict) -> Item:
    """One row as an :class:`Item`; a row-level problem is kept in ``error``."""
    loc = lambda fld: where(source, line, fld)
    ident = raw.get("id")
    ident = "" if ident is None else str(ident).strip()
    item = Item(id=ident, line=line, source=source)
    try:
        if not ident:
            raise ConfigError(f"{loc('id')}: missing; every item needs an id")
        if not _ID.match(ident) or _RESERVED.search(ident):
            raise ConfigError(
                f"{loc('id')}: {ident!r} cannot name a run folder: use letters, digits, '.', "
                "'_' and '-' (at most 100, starting with a letter or digit; not ending in "
                "'.partial')"
            )
        paths: dict[str, Path | None] = {}
        for fld in ("tree", "recordings", "test"):
            v = raw.get(fld)
            if v is None or (isinstance(v, str) and not v.strip()):
                if fld != "test":
                    raise ConfigError(f"{loc(fld)}: missing; give a path")
                paths[fld] = None
                continue
            if not isinstance(v, str):
                raise ConfigError(f"{loc(fld)}: expected a path, got {v!r}")
            p = Path(v.strip()).expanduser()
            paths[fld] = (p if p.is_absolute() else base / p).resolve()
        digests: dict[str, Any] = {}
        tree_path = paths["tree"]
        if not tree_path.is_file():
            raise ConfigError(f"{loc('tree')}: {tree_path}: no such file")
        from ..tree.description import load_tree, tree_to_dict

        try:
            tree = load_tree(tree_path)
        except TreeinferError as e:
            raise ConfigError(f"{loc('tree')}: {e}") from None
        digests["tree"] = file_sha256(tree_path)
        digests["recordings"] = _folder_digests(paths["recordings"], loc("recordings"))
        if paths["test"] is not None:
            if paths["test"] == paths["recordings"]:
                raise ConfigError(
                    f"{loc('test')}: is the recordings folder; coverage must come from held-out "
                    "pulls the posterior was not fitted to"
                )
            digests["test"] = _folder_digests(paths["test"], loc("test"))
        g = raw.get("grasp_fraction")
        grasp = None
        if g is not None and not (isinstance(g, str) and not g.strip()):
            grasp = _convert("float", g, loc("grasp_fraction"))
            if not 0.0 < grasp <= 1.0:
                raise ConfigError(
                    f"{loc('grasp_fraction')}: must be in (0, 1] (a fraction of the grasped "
                    f"branch's length), got {g!r}"
                )
        opts = _options(raw.get("options") or {}, loc)
        shape = json.dumps(tree_to_dict(tree), sort_keys=True, default=str)
        group = hashlib.sha256(shape.encode()).hexdigest()[:12] + f"/{len(digests['recordings'])}"
        return dataclasses.replace(
            item,
            tree=str(tree_path),
            recordings=str(paths["recordings"]),
            test=None if paths["test"] is None else str(paths["test"]),
            grasp_fraction=grasp,
            options={**defaults, **opts},
            digests=digests,
            group=group,
        )
    except ConfigError as e:
        return dataclasses.replace(item, error=str(e))


def _csv_rows(text: str, source: str) -> list[tuple[int, dict]]:
    reader = csv.reader(io.StringIO(text))
    header, rows = None, []
    for cells in reader:
        line = reader.line_num
        if not any(c.strip() for c in cells) or cells[0].lstrip().startswith("#"):
            continue
        if header is None:
            header = [c.strip() for c in cells]
            known = ITEM_FIELDS + tuple(ITEM_OPTIONS)
            for i, h in enumerate(header):
                if h not in known:
                    raise ConfigError(
                        f"{where(source, line, h)}: unknown column{_suggest(h, known)}; "
                        f"columns are {', '.join(ITEM_FIELDS)} and the options "
                        f"{', '.join(ITEM_OPTIONS)}"
                    )
                if h in header[:i]:
                    raise ConfigError(f"{where(source, line, h)}: column given twice")
            missing = [c for c in ("id", "tree", "recordings") if c not in header]
            if missing:
                raise ConfigError(
                    f"{where(source, line)}: the header lacks column(s) {', '.join(missing)} "
                    "(the first line that is not a comment is the header)"
                )
            continue
        if len(cells) > len(header):
            raise ConfigError(
                f"{where(source, line)}: {len(cells)} cells but the header has {len(header)} "
                "columns (a comma inside a path? quote the cell)"
            )
        row = dict(zip(header, cells))
        opts = {k: row.pop(k) for k in list(row) if k in ITEM_OPTIONS}
        rows.append((line, {**row, "options": opts}))
    if header is None:
        raise ConfigError(f"{source}: empty manifest (no header line)")
    return rows


def _yaml_rows(text: str, data: Any, source: str) -> tuple[list[tuple[int, dict]], dict]:
    import yaml

    node = yaml.compose(text, Loader=yaml.SafeLoader)  # for line numbers; load_file checked it
    defaults: dict = {}
    items_node = node
    if isinstance(data, dict):
        unknown = sorted(set(data) - {"items", "defaults"})
        if unknown or "items" not in data:
            raise ConfigError(
                f"{source}: a YAML manifest is a list of items or a mapping with 'items' (and "
                f"optionally 'defaults'); got keys {sorted(map(str, data))}"
            )
        items_node = next(v for k, v in node.value if k.value == "items")
        d_line = next((k.start_mark.line + 1 for k, _ in node.value if k.value == "defaults"), 0)
        if data.get("defaults") is not None:
            if not isinstance(data["defaults"], dict):
                raise ConfigError(f"{where(source, d_line, 'defaults')}: expected a mapping")
            defaults = _options(data["defaults"], lambda k: where(source, d_line, f"defaults.{k}"))
        data = data["items"]
    if not isinstance(data, list):
        raise ConfigError(f"{source}: expected a list of items, got {type(data).__name__}")
    rows = []
    for raw, n in zip(data, items_node.value):
        line = n.start_mark.line + 1
        if not isinstance(raw, dict):
            raise ConfigError(f"{where(source, line)}: an item must be a mapping, got {raw!r}")
        bad = sorted(set(map(str, raw)) - set(ITEM_FIELDS) - {"options"})
        if bad:
            known = ITEM_FIELDS + ("options",)
            hint = " (infer options go under 'options:')" if set(bad) & set(ITEM_OPTIONS) else ""
            raw = {**raw, "_error": f"{where(source, line, bad[0])}: unknown key"
                   f"{_suggest(bad[0], known)}{hint}; an item has {', '.join(known)}"}  # fmt: skip
        elif raw.get("options") is not None and not isinstance(raw["options"], dict):
            raw = {**raw, "_error": f"{where(source, line, 'options')}: expected a mapping"}
        rows.append((line, raw))
    return rows, defaults


def read_manifest(path: str) -> list[Item]:
    """Every item of the manifest ``path`` (CSV by its ``.csv`` suffix, else YAML), validated.

    Raises ConfigError for a manifest that cannot be used at all; row-level problems are
    kept in :attr:`Item.error` (including duplicate ids: every row sharing an id fails)."""
    path = Path(path)
    source = str(path)
    base = path.resolve().parent
    if path.suffix.lower() == ".csv":
        raw = read_regular_file(path, "manifest", ConfigError)
        try:
            text = raw.decode("utf-8-sig")
        except UnicodeDecodeError as e:
            raise ConfigError(f"{path}: the manifest is not UTF-8 text (byte {e.start})") from None
        rows, defaults = _csv_rows(text, source), {}
    elif path.suffix.lower() in (".yaml", ".yml"):
        data = load_file(path, "manifest", ConfigError, fmt="yaml")
        text = path.read_text(encoding="utf-8-sig")
        rows, defaults = _yaml_rows(text, data, source)
    else:
        raise ConfigError(f"{path}: a manifest is a .csv, .yaml or .yml file")
    if not rows:
        raise ConfigError(f"{source}: no items")
    items = []
    for line, raw in rows:
        if "_error" in raw:
            items.append(Item(id=str(raw.get("id") or ""), line=line, source=source,
                              error=raw["_error"]))  # fmt: skip
        else:
            items.append(_item(raw, line, source, base, defaults))
    lines: dict[str, list[int]] = {}
    for it in items:  # an id names a folder: compared case-blind (macOS, Windows file systems)
        if it.id:
            lines.setdefault(it.id.lower(), []).append(it.line)
    out = []
    for it in items:
        same = lines.get(it.id.lower(), [])
        if len(same) > 1 and it.error is None:
            others = ", ".join(str(n) for n in same if n != it.line)
            it = dataclasses.replace(
                it,
                error=f"{where(source, it.line, 'id')}: {it.id!r} is also the id on line(s) "
                f"{others}; ids name the run folders and must differ",
            )
        out.append(it)
    return out
