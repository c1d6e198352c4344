"""The manifest of an output folder, and the checks of a run folder a checksum cannot make.

Every folder treeinfer publishes (:func:`treeinfer._io.publish_staged`: a run, a data set, an
evaluation, a prediction, a calibration ...) gets ``manifest.json``: the sha256 and size of
every file in it, config.json and summary.json included, written last before the folder is
moved into place. :func:`treeinfer.integrity.verify_run` checks it wherever a run is read
(``predict``, ``evaluate``, ``suggest``, ``infer --prior-from``, :func:`treeinfer.runs.load_run`).

:func:`check_run_consistency` covers what a checksum cannot: an old run without a manifest, or
one let through with ``--allow-modified``, whose tree.yaml is not the tree config.json recorded,
whose particles do not fit their labels, or whose summary.json contradicts its particles.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterable, Mapping
from pathlib import Path

from .errors import ConfigError
from .integrity import ALGORITHM, MANIFEST, file_digest

__all__ = [
    "MANIFEST",
    "check_run_consistency",
    "read_manifest",
    "verify_manifest",
    "write_manifest",
]

MANIFEST_FORMAT = 1
# written after the manifest (the publish step's completion flag), so not listed in it
_UNLISTED = (MANIFEST, ".treeinfer-output")
_MARKER = b'{"writer": "treeinfer", "complete": true}\n'  # treeinfer._io's, once published


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
    from . import __version__
    from ._io import atomic_write_json

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


def check_run_consistency(
    run_dir: str | os.PathLike,
    config: Mapping,
    tree,
    theta,
    labels: Iterable[str],
    summary: Mapping,
    allow_modified: bool = False,
) -> list[str]:
    """Checks a checksum cannot make (a run from before manifests, or one let through with
    ``--allow-modified``): tree.yaml is the tree config.json recorded; the particles have one
    column per label; summary.json's posterior table is the particles' (same labels, the same
    mean of each gain over the stable particles). Raises ConfigError naming the file, or with
    ``allow_modified`` returns notes."""
    import numpy as np

    from .runs.provenance import tree_to_dict_json
    from .tree import tree_to_dict

    run_dir = Path(run_dir)
    labels = list(labels)
    problems = []
    if tree_to_dict_json(tree_to_dict(tree)) != tree_to_dict_json(config["tree_dict"]):
        problems.append(
            f"{run_dir / 'tree.yaml'}: is not the tree recorded in config.json (swapped or edited)"
        )
    theta = np.asarray(theta, float)
    if theta.ndim != 2 or theta.shape[1] != len(labels):
        problems.append(
            f"{run_dir / 'trace.npz'}: particles of shape {theta.shape} for {len(labels)} "
            f"labels {labels}"
        )
    table = summary.get("posterior") if isinstance(summary, Mapping) else None
    if isinstance(table, Mapping) and table and not problems:
        if sorted(table) != sorted(labels):
            problems.append(
                f"{run_dir / 'summary.json'}, field 'posterior': labels {list(table)} are not "
                f"the particles' {labels}"
            )
        else:
            bad = set(summary.get("unstable_particles") or [])
            ok = np.all(np.isfinite(theta), axis=1)
            ok &= np.array([i not in bad for i in range(len(theta))], bool)
            for j, lab in enumerate(labels):
                rec = table[lab]
                if not (lab.startswith(("Kp[", "Kd[")) and isinstance(rec, Mapping)):
                    continue
                mean = rec.get("mean")
                if not isinstance(mean, (int, float)) or ok.sum() < 2:
                    continue
                now = float(np.mean(np.exp(theta[ok, j])))
                if not math.isclose(now, float(mean), rel_tol=1e-3, abs_tol=1e-12):
                    problems.append(
                        f"{run_dir / 'summary.json'}, field 'posterior.{lab}.mean': {mean!r} "
                        f"contradicts the particles (their mean is {now:.6g})"
                    )
    if not problems:
        return []
    if not allow_modified:
        raise ConfigError(
            f"{problems[0]}{'; ' + '; '.join(problems[1:]) if problems[1:] else ''}; the run "
            "folder does not hold together: run infer again, or pass --allow-modified to use it "
            "anyway (recorded in the output)"
        )
    return [f"{run_dir}: used with --allow-modified although {p}" for p in problems]
