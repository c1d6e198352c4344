"""The ``model:`` section of a tree description (a user's own URDF/MJCF): its fields and their
validation. Apart from :mod:`treeinfer.tree.usermodel` (which loads the model, and needs
:mod:`treeinfer.tree.description`) so that :mod:`treeinfer.tree.description` can validate tree files
without a cycle.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from ..errors import TreeFileError

MODEL_KEYS = {
    "file",
    "sha256",
    "joints",
    "bodies",
    "grasp_position",
    "repair_inertia",
    "limits",
    "gains",
}
REPAIRS = ("geometry", "floor")
LIMIT_POLICIES = ("refuse", "ignore")
GAIN_POLICIES = ("tree", "model")
MODEL_SUFFIXES = {".urdf": "URDF", ".xml": "MJCF", ".mjcf": "MJCF"}


def file_sha256(path: str | Path) -> str:
    """Hex sha256 of a file's bytes (a regular file: a FIFO or device is refused unopened)."""
    from ..io.manifest import file_digest

    return file_digest(path)["sha256"]


def _name_map(v: Any, fld: str, pre: str) -> dict[str, str]:
    if v is None:
        return {}
    if not isinstance(v, dict) or not all(
        isinstance(k, str) and isinstance(x, str) for k, x in v.items()
    ):
        raise TreeFileError(f"{pre}model.{fld}: expected a mapping {{branch name: model name}}")
    return dict(v)


def parse_model_section(
    raw: Any, source: str = "<dict>", base_dir: str | Path | None = None
) -> dict[str, Any]:
    """The validated ``model:`` section (``file`` made absolute against ``base_dir``)."""
    pre = f"{source}: "
    if isinstance(raw, str):
        raw = {"file": raw}
    if not isinstance(raw, dict) or "file" not in raw:
        raise TreeFileError(
            f"{pre}model: expected a mapping with 'file' (and optional "
            f"{sorted(MODEL_KEYS - {'file'})})"
        )
    bad = set(raw) - MODEL_KEYS
    if bad:
        raise TreeFileError(
            f"{pre}model: unknown field(s) {sorted(bad)}; allowed: {sorted(MODEL_KEYS)}"
        )
    path = Path(str(raw["file"]))
    if not path.is_absolute() and base_dir is not None:
        path = Path(base_dir) / path
    if path.suffix.lower() not in MODEL_SUFFIXES:
        raise TreeFileError(
            f"{pre}model.file: unknown model file type '{path.suffix}'; "
            "expected .urdf or .xml/.mjcf (MJCF)"
        )
    out: dict[str, Any] = {"file": str(path.resolve()) if base_dir is not None else str(path)}
    if raw.get("sha256") is not None:
        out["sha256"] = str(raw["sha256"])
    for k in ("joints", "bodies"):
        m = _name_map(raw.get(k), k, pre)
        if m:
            out[k] = m
    gp = raw.get("grasp_position")
    if gp is not None:
        try:
            gp = [float(x) for x in gp]
        except (TypeError, ValueError):
            gp = None
        if gp is None or len(gp) != 3 or not all(math.isfinite(x) for x in gp):
            raise TreeFileError(
                f"{pre}model.grasp_position: expected [x, y, z] in metres, got "
                f"{raw.get('grasp_position')!r}"
            )
        out["grasp_position"] = gp
    for k, choices, default in (
        ("repair_inertia", REPAIRS, None),
        ("limits", LIMIT_POLICIES, "refuse"),
        ("gains", GAIN_POLICIES, "tree"),
    ):
        v = raw.get(k, default)
        if v is not None and v not in choices:
            raise TreeFileError(f"{pre}model.{k}: must be one of {', '.join(choices)}, got {v!r}")
        if v != default:
            out[k] = v
    return out
