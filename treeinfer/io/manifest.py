"""The manifest of an output folder: the sha256 and size of every file in it.

Every folder treeinfer publishes (:func:`treeinfer.io.atomic.publish_staged`: a run, a data set, an
evaluation, a prediction, a calibration ...) gets ``manifest.json``: the sha256 and size of
every file in it, config.json and summary.json included, written last before the folder is
moved into place. :func:`treeinfer.runs.integrity.verify_run` checks it wherever a run is read
(``predict``, ``evaluate``, ``suggest``, ``infer --prior-from``, :func:`treeinfer.runs.load_run`).

This module sits below :mod:`treeinfer.io.atomic` and :mod:`treeinfer.runs.integrity` (both import
it; it imports neither): the checksum (:func:`file_digest`) and the manifest's format live here.
What a checksum cannot check, a run folder's files holding together, is
:func:`treeinfer.runs.consistency.check_run_consistency`.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Mapping
from pathlib import Path

from ..errors import ConfigError
from .atomic_write import atomic_write_json
from .safe_load import require_regular_file

__all__ = [
    "ALGORITHM",
    "MANIFEST",
    "file_digest",
    "read_manifest",
    "verify_manifest",
    "write_manifest",
]

ALGORITHM = "sha256"
MANIFEST = "manifest.json"  # every file of an output folder


def file_digest(path: str | os.PathLike) -> dict:
    """``{"sha256": hex, "bytes": n}`` of a regular file (ConfigError for FIFOs, devices)."""
    path = require_regular_file(path, "file", ConfigError)
    h = hashlib.sha256()
    n = 0
    try:
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
                n += len(block)
    except OSError as e:
        raise ConfigError(f"{path}: cannot read ({e.strerror or e})") from None
    return {ALGORITHM: h.hexdigest(), "bytes": n}


MANIFEST_FORMAT = 1
# written after the manifest (the publish step's completion flag), so not listed in it
_UNLISTED = (MANIFEST, ".treeinfer-output")
_MARKER = b'{"writer": "treeinfer", "complete": true}\n'  # treeinfer.io.atomic's, once published


def _folder_files(folder: Path) -> list[str]:
    """Relative names (``/``-separated) of the regular files under ``folder``, symlinks not
    followed, the manifest and marker left out."""
    out = []
    for root, dirs, files in os.walk(folder):
        dirs.sort()
        for name in sorted(files):
            p = Path(root) / name
            rel = p.relative_to(folder).as_posix()
            if rel in _UNLISTED or p.is_symlink() or not p.is_file():
                continue
            out.append(rel)
    return out


def write_manifest(folder: str | os.PathLike) -> Path:
    """Write ``folder/manifest.json``: the sha256 and size of every file treeinfer wrote there
    (called on the complete staging folder, just before it is published)."""
    from .. import __version__

    folder = Path(folder)
    files = {rel: file_digest(folder / rel) for rel in _folder_files(folder)}
    return atomic_write_json(
        folder / MANIFEST,
        {
            "format": MANIFEST_FORMAT,
            "writer": f"treeinfer {__version__}",
            "algorithm": ALGORITHM,
            "files": files,
        },
    )


def read_manifest(folder: str | os.PathLike) -> dict | None:
    """The files recorded in ``folder/manifest.json`` (``{name: {sha256, bytes}}``), or None if
    the folder has none (written by a treeinfer from before manifests). ConfigError for a
    manifest that is not one."""
    from .safe_load import load_file

    path = Path(folder) / MANIFEST
    if not (path.exists() or path.is_symlink()):
        return None
    d = load_file(path, "manifest", ConfigError, fmt="json")
    files = d.get("files") if isinstance(d, Mapping) else None
    if (
        not isinstance(files, Mapping)
        or d.get("algorithm") != ALGORITHM
        or not all(
            isinstance(k, str) and isinstance(v, Mapping) and isinstance(v.get(ALGORITHM), str)
            for k, v in files.items()
        )
    ):
        raise ConfigError(f"{path}: not a treeinfer manifest (damaged?)")
    if d.get("format") != MANIFEST_FORMAT:
        raise ConfigError(
            f"{path}: manifest format {d.get('format')!r}, this treeinfer reads format "
            f"{MANIFEST_FORMAT} (written by {d.get('writer', 'another treeinfer')})"
        )
    for k in files:
        if k.startswith("/") or ".." in Path(k).parts:
            raise ConfigError(f"{path}: file name {k!r} points outside the folder")
    # the manifest checks itself: treeinfer writes it in one canonical form, so any other byte
    # (an edit that keeps the JSON valid) is damage too
    canonical = json.dumps(d, indent=2, sort_keys=True) + "\n"
    if path.read_bytes() != canonical.encode("utf-8"):
        raise ConfigError(
            f"{path}: was edited after it was written (not byte-identical to its "
            "content as treeinfer writes it)"
        )
    marker = Path(folder) / ".treeinfer-output"
    if (marker.read_bytes() if marker.is_file() else b"") != _MARKER:
        raise ConfigError(f"{marker}: missing or edited (the folder's completion marker)")
    return dict(files)


def verify_manifest(folder: str | os.PathLike, files: Mapping, source: str = MANIFEST) -> list[str]:
    """Problems (one sentence each) of ``folder`` against its manifest ``files``: a listed file
    missing, not a regular file, or with another sha256."""
    folder = Path(folder)
    problems = []
    for name, rec in files.items():
        p = folder / name
        if not (p.exists() or p.is_symlink()):
            problems.append(f"{name} is missing")
            continue
        try:
            now = file_digest(p)
        except ConfigError as e:
            problems.append(f"{name}: {e}")
            continue
        if now[ALGORITHM] != rec.get(ALGORITHM):
            what = (
                "was edited"
                if name.endswith((".yaml", ".yml", ".json", ".csv"))
                else "is damaged or was replaced"
            )
            problems.append(
                f"{name} {what} after the run (sha256 differs from {source}; "
                f"{rec.get('bytes')} -> {now['bytes']} bytes)"
            )
    return problems
