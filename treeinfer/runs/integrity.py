"""Run-folder integrity: checksums recorded at the end of ``infer``, verified before a run is
used again (``predict``, ``evaluate``, ``--resume``), and validation of the run's own files
(config.json, summary.json, checkpoint.npz) so a damaged folder gives a clean error naming the
file and field instead of a crash or, worse, a silent answer from the wrong tree.

Recording: :func:`record_checksums` over the finished folder's files (tree.yaml, posterior.nc,
particles.csv, trace.npz) gives ``{"algorithm": "sha256", "files": {name: {sha256, bytes}}}``,
stored as ``config["integrity"]``; config.json itself is written after them. The data files'
hashes are already in ``config["data"]["files"]`` (see :func:`verify_data`).

Verifying: :func:`verify_run` refuses a run whose recorded files are missing or changed (an
edited tree.yaml, a truncated posterior) unless ``allow_modified``; then it returns notes that
the caller records in its output (``--allow-modified``).
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from ..errors import ConfigError
from ..io.manifest import (  # file_digest, in __all__, keeps its old import path
    ALGORITHM,
    MANIFEST,
    file_digest,
    read_manifest,
    verify_manifest,
)
from ..io.safe_load import require_regular_file

__all__ = [
    "CHECKSUM_FILES",
    "check_partial",
    "file_digest",
    "load_npz",
    "record_checksums",
    "validate_checkpoint_file",
    "validate_run_config",
    "validate_summary",
    "verify_data",
    "verify_run",
]

CHECKSUM_FILES = ("tree.yaml", "posterior.nc", "particles.csv", "trace.npz")


def record_checksums(run_dir: str | os.PathLike, names: Iterable[str] = CHECKSUM_FILES) -> dict:
    """Checksums of the run folder's files that exist, for ``config["integrity"]``."""
    run_dir = Path(run_dir)
    files = {n: file_digest(run_dir / n) for n in names if (run_dir / n).is_file()}
    return {"algorithm": ALGORITHM, "files": files}


def _recorded_files(recorded: Mapping | None) -> dict | None:
    if recorded is None:
        return None
    if "integrity" in recorded and isinstance(recorded["integrity"], Mapping):  # the whole config
        recorded = recorded["integrity"]
    elif "integrity" not in recorded and "files" not in recorded:
        return None
    files = recorded.get("files") if isinstance(recorded, Mapping) else None
    if not isinstance(files, Mapping) or recorded.get("algorithm", ALGORITHM) != ALGORITHM:
        raise ConfigError(f"config.json, field 'integrity': malformed checksum record {recorded!r}")
    return dict(files)


def verify_run(
    run_dir: str | os.PathLike,
    recorded: Mapping | None,
    allow_modified: bool = False,
    names: Iterable[str] | None = None,
) -> list[str]:
    """Check the run folder's files against their recorded checksums.

    The folder's ``manifest.json`` (every file, config.json and summary.json included) is
    checked when there is one. Without one: a config (``recorded``) that says a manifest was
    written makes its absence a problem; a run from before manifests is checked against
    ``config["integrity"]`` (tree.yaml, posterior.nc, particles.csv, trace.npz) and a note says
    config.json and summary.json could not be verified.

    Args:
      run_dir: the run folder. recorded: ``config`` (or ``config["integrity"]``); None: not read
        yet (only a manifest can be checked).
      allow_modified: accept changed or missing files, returning notes instead of raising.
      names: check only these files (default: every recorded one).

    Returns:
      Notes to record in the output (empty when everything matches).

    Raises:
      ConfigError: a recorded file is missing or changed and ``allow_modified`` is False.
    """
    run_dir = Path(run_dir)
    try:
        manifest = read_manifest(run_dir)
    except ConfigError as e:
        if not allow_modified:
            raise
        return [f"{run_dir}: used with --allow-modified although {e}"]
    notes: list[str] = []
    if manifest is not None:
        if names is not None:
            manifest = {n: r for n, r in manifest.items() if n in set(names)}
        problems = verify_manifest(run_dir, manifest)
    else:
        if recorded is None:
            return []
        integ = recorded.get("integrity") if isinstance(recorded, Mapping) else None
        expects = isinstance(integ, Mapping) and integ.get("manifest") == MANIFEST
        files = _recorded_files(recorded)
        if files is None:
            return [
                (
                    f"{run_dir}: no checksums recorded (a run from an older treeinfer); its files "
                    "were not verified"
                )
            ]
        problems = [f"{MANIFEST} is missing"] if expects else []
        if not expects:
            notes.append(
                f"{run_dir}: a run from a treeinfer before manifests: tree.yaml, posterior.nc, "
                "particles.csv and trace.npz were verified, config.json and summary.json could "
                "not be"
            )
        wanted = list(files) if names is None else [n for n in names if n in files]
        problems += verify_manifest(
            run_dir, {n: files[n] for n in wanted if isinstance(files[n], Mapping)}, "config.json"
        )
        problems += [
            f"{n}: malformed checksum record" for n in wanted if not isinstance(files[n], Mapping)
        ]
    if not problems:
        return notes
    if not allow_modified:
        raise ConfigError(
            f"{run_dir}: the run folder changed since it was written: {'; '.join(problems)}. "
            "Results from it would not come from the posterior that was inferred; run infer "
            "again, or pass --allow-modified to use it anyway (recorded in the output)"
        )
    return notes + [f"{run_dir}: used with --allow-modified although {p}" for p in problems]


def verify_data(config: Mapping, data_dir: str | os.PathLike | None = None) -> list[str]:
    """Names of training files whose sha256 differs from ``config["data"]["files"]`` (or that
    are missing); empty if all match."""
    d = Path(data_dir if data_dir is not None else config["data"]["dir"])
    bad = []
    for rec in config["data"]["files"]:
        p = d / rec["name"]
        if not p.is_file() or file_digest(p)[ALGORITHM] != rec.get(ALGORITHM):
            bad.append(rec["name"])
    return bad


# ---- validation of a run's own files ---------------------------------------------------------
_MISSING = object()


def _get(d: Any, dotted: str) -> Any:
    cur = d
    for k in dotted.split("."):
        if not isinstance(cur, Mapping) or k not in cur:
            return _MISSING
        cur = cur[k]
    return cur


def _check(d: Mapping, path: Path, dotted: str, kind: str, optional: bool = False) -> Any:
    v = _get(d, dotted)
    loc = f"{path}, field '{dotted}'"
    if v is _MISSING:
        if optional:
            return None
        raise ConfigError(f"{loc}: missing; the run folder is damaged or not from this treeinfer")
    if v is None and optional:
        return None
    bad = False
    if kind in ("number", "positive", "nonneg"):
        bad = isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v))
        if not bad and kind == "positive":
            bad = float(v) <= 0
        if not bad and kind == "nonneg":
            bad = float(v) < 0
    elif kind in ("int", "count", "posint"):
        bad = isinstance(v, bool) or not isinstance(v, int)
        if not bad and kind == "count":
            bad = v < 0
        if not bad and kind == "posint":
            bad = v < 1
    elif kind == "str":
        bad = not isinstance(v, str)
    elif kind == "bool":
        bad = not isinstance(v, bool)
    elif kind == "dict":
        bad = not isinstance(v, Mapping)
    elif kind == "list":
        bad = not isinstance(v, list)
    else:  # pragma: no cover -- programming error
        raise ValueError(kind)
    if bad:
        expected = {
            "positive": "a positive number",
            "nonneg": "a number >= 0",
            "number": "a number",
            "int": "an integer",
            "count": "an integer >= 0",
            "posint": "an integer >= 1",
            "str": "text",
            "bool": "true or false",
            "dict": "an object",
            "list": "a list",
        }[kind]
        raise ConfigError(f"{loc}: expected {expected}, got {v!r}")
    return v


def validate_run_config(config: Any, path: str | os.PathLike, resumable: bool = False) -> dict:
    """Check the fields of a run's config.json that predict/evaluate/--resume read.

    ``resumable``: also the fields only ``--resume`` needs (config_hash, data files, sampler).
    Returns ``config``; raises ConfigError naming the file and field.
    """
    path = Path(path)
    if not isinstance(config, Mapping):
        raise ConfigError(f"{path}: expected a JSON object, got {type(config).__name__}")
    _check(config, path, "format", "int")
    _check(config, path, "command", "str")
    _check(config, path, "options", "dict")
    for k, kind in (
        ("sampler", "str"),
        ("particles", "posint"),
        ("iterations", "count"),
        ("seed", "int"),
        ("kT", "positive"),
        ("max_unstable_share", "nonneg"),
        ("checkpoint_every", "count"),
    ):
        _check(config, path, f"options.{k}", kind)
    _check(config, path, "options.grasp_fraction", "positive", optional=True)
    _check(config, path, "problem", "dict")
    _check(config, path, "problem.kT", "positive")
    _check(config, path, "problem.obs_dt", "positive")
    _check(config, path, "problem.substeps", "posint")
    _check(config, path, "problem.backend", "str", optional=True)
    _check(config, path, "tree_dict", "dict")
    if resumable:
        _check(config, path, "config_hash", "str")
        _check(config, path, "sampler", "dict")
        _check(config, path, "data.dir", "str")
        files = _check(config, path, "data.files", "list")
        for i, f in enumerate(files):
            if (
                not isinstance(f, Mapping)
                or not isinstance(f.get("name"), str)
                or not isinstance(f.get(ALGORITHM), str)
            ):
                raise ConfigError(
                    f"{path}, field 'data.files[{i}]': expected {{name, sha256}}, got {f!r}"
                )
    if "integrity" in config:
        _recorded_files(config)
    return dict(config)


def validate_summary(summary: Any, path: str | os.PathLike, n_particles: int) -> dict:
    """Check the summary.json fields the run layer reads (``unstable_particles`` indices in
    ``[0, n_particles)``; counts; the posterior table) and return it."""
    path = Path(path)
    if not isinstance(summary, Mapping):
        raise ConfigError(f"{path}: expected a JSON object, got {type(summary).__name__}")
    idx = _check(summary, path, "unstable_particles", "list", optional=True) or []
    for i, v in enumerate(idx):
        if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v < n_particles:
            raise ConfigError(
                f"{path}, field 'unstable_particles[{i}]': {v!r} is not a particle index in "
                f"[0, {n_particles}) (the run has {n_particles} particles)"
            )
    _check(summary, path, "n_unstable", "count", optional=True)
    _check(summary, path, "posterior", "dict", optional=True)
    status = _get(summary, "fit.status")
    if status is not _MISSING and status not in ("ok", "warning", "poor_fit"):
        raise ConfigError(
            f"{path}, field 'fit.status': expected ok, warning or poor_fit, got {status!r}"
        )
    return dict(summary)


def validate_checkpoint_file(path: str | os.PathLike) -> Path:
    """A checkpoint that can be opened: a regular, non-empty zip (``.npz``) file."""
    path = require_regular_file(path, "checkpoint", ConfigError)
    size = path.stat().st_size
    if size == 0:
        raise ConfigError(
            f"{path}: checkpoint is empty (0 bytes; a write cut short?); the run "
            "cannot continue from it: delete it to restart from iteration 0"
        )
    with open(path, "rb") as f:
        magic = f.read(4)
    if magic[:2] != b"PK":
        raise ConfigError(f"{path}: not a checkpoint (.npz) file (starts with {magic!r})")
    return path


def load_npz(path: str | os.PathLike, what: str = "file") -> dict:
    """All arrays of an ``.npz`` (no pickles) as a dict; ConfigError naming the file for a
    missing, empty, truncated or foreign file (np.load raises EOFError, BadZipFile, ...)."""
    import zipfile

    import numpy as np

    path = Path(path)
    require_regular_file(path, what, ConfigError)
    if path.stat().st_size == 0:
        raise ConfigError(f"{path}: {what} is empty (0 bytes)")
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as e:
        raise ConfigError(f"{path}: unreadable {what} ({type(e).__name__}: {e})") from None


def check_partial(partial: str | os.PathLike) -> str | None:
    """Why ``RUN.partial`` cannot be resumed (a sentence), or None if it can be.

    The run layer calls this where it finds a ``RUN.partial`` (a new ``infer`` refusing to
    start, or ``--resume``) so both say the same thing: a folder whose config.json was never
    written (a full disk at the start) is not resumable and may be removed.
    """
    partial = Path(partial)
    if not partial.is_dir():
        return f"{partial} does not exist"
    cfg = partial / "config.json"
    if not cfg.is_file():
        return (
            f"{partial} has no config.json (the run stopped before it was written, e.g. on a "
            "full disk); it cannot be resumed: delete it, or pass --force to start over"
        )
    if cfg.stat().st_size == 0:
        return f"{cfg} is empty; it cannot be resumed: delete {partial} or pass --force"
    from ..io.safe_load import load_file

    try:
        config = load_file(cfg, "run config", ConfigError, fmt="json")
        validate_run_config_for_resume(config, cfg)
    except ConfigError as e:
        return f"{e}; it cannot be resumed: delete {partial} or pass --force"
    ck = partial / "checkpoint.npz"
    if ck.exists():
        try:
            validate_checkpoint_file(ck)
        except ConfigError as e:
            return f"{e}"
    return None


def validate_run_config_for_resume(config: Any, path: str | os.PathLike) -> dict:
    """:func:`validate_run_config` for a ``RUN.partial/config.json`` (no posterior yet)."""
    path = Path(path)
    if not isinstance(config, Mapping):
        raise ConfigError(f"{path}: expected a JSON object, got {type(config).__name__}")
    return validate_run_config(config, path, resumable=True)
