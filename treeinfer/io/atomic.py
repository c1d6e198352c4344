"""Atomic file output, and the rules that keep output from ever destroying data.

Results are written to a temporary name beside their destination and renamed
into place, so an interrupted run never leaves a half-written file, and an
earlier run's results are never overwritten unless the caller asks.

Output folders (:func:`staged_output_dir`):

- are built in a staging folder ``.NAME.PID.XXXX.staging`` next to the destination and carry
  a marker file ``.treeinfer-output`` and a ``manifest.json`` of every file with its sha256
  (:func:`treeinfer.io.manifest.write_manifest`); the atomic writes of single files live in
  :mod:`treeinfer.io.atomic_write` (below :mod:`treeinfer.io.ownership` and
  :mod:`treeinfer.io.manifest`);
- never overwrite or delete what was there (:mod:`treeinfer.io.ownership`): ``--force``
  (``force=True``) moves the previous folder aside to ``NAME.old-<UTC time>`` (reported), and
  only for a folder with the marker (or from a treeinfer before the marker: a ``config.json`` or
  ``results.json`` recording treeinfer's version) or an empty one; an output that is, holds or
  lies inside an input of the same command (``inputs=``), a mount point, the root, home or
  current folder are refused before any work;
- are never lost once complete: if the final rename fails (a mount point, a permission, a full
  disk) the finished folder is kept at ``NAME.complete-PID`` and the error names that path;
- leave nothing behind on error, and a staging folder left by a killed process is cleaned by
  the next write to the same destination (:func:`clean_stale_staging`, which the run layer also
  calls on ``--resume``): an unfinished one (our marker, no mount point inside) is removed, a
  finished one whose rename was cut short is moved into place, a displaced previous result is
  put back (or kept aside as ``NAME.old-<time>``).

Disk-full and I/O errors while writing become :class:`OutputWriteError` naming the file.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

from ..errors import OutputExistsError
from . import interrupt
from .atomic_write import (  # noqa: F401 -- re-exported: the old import path
    _DISK_ERRNOS,
    _ERRNO_HINT,
    OutputWriteError,
    _publish_mode,
    atomic_save,
    atomic_write_bytes,
    atomic_write_json,
    atomic_write_text,
    output_error,
)

OUTPUT_MARKER = ".treeinfer-output"
STAGING_SUFFIX = ".staging"
OLD_SUFFIX = ".old"
COMPLETE_INFIX = ".complete-"


def _read_json_quietly(path: Path) -> Any:
    try:
        if path.is_file() and path.stat().st_size < (1 << 22):
            return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        pass
    return None


def is_treeinfer_output(path: str | os.PathLike) -> bool:
    """True if ``path`` is a folder treeinfer wrote: it has the ``.treeinfer-output`` marker, or
    (folders from before the marker) a ``config.json``/``results.json`` recording treeinfer's
    version under ``versions``."""
    path = Path(path)
    if (path / OUTPUT_MARKER).is_file():
        return True
    for name in ("config.json", "results.json"):
        d = _read_json_quietly(path / name)
        if (
            isinstance(d, dict)
            and isinstance(d.get("versions"), dict)
            and "treeinfer" in d["versions"]
        ):
            return True
    return False


def check_output_dir(
    path: str | os.PathLike,
    force: bool = False,
    what: str = "output",
    inputs: Iterable[str | os.PathLike] = (),
    allow_inside: Iterable[str | os.PathLike] = (),
) -> Path:
    """Refuse an output folder that must not be (re)written; never delete anything here.

    Refused (:mod:`treeinfer.io.ownership`): a folder that is, holds, or lies inside one of
    ``inputs`` (the command's own input files or folders); a path that exists and is not a
    folder; the root, home or current folder, or a mount point; a non-empty folder without
    ``force``; with ``force``, a non-empty folder that treeinfer did not write (see
    :func:`is_treeinfer_output`). ``force`` never deletes: the old folder is moved aside when the
    new one is published (:func:`publish_staged`), so the marker decides nothing destructive.
    """
    from .ownership import refuse_overlap, refuse_unmovable

    path = Path(path)
    refuse_overlap(path, inputs, f"{what} folder", allow=allow_inside)
    if path.is_symlink() and not path.exists():
        raise OutputExistsError(f"{path}: {what} path is a broken symbolic link")
    if path.exists() and not path.is_dir():
        raise OutputExistsError(f"{path}: {what} path exists and is not a folder")
    if path.exists():
        refuse_unmovable(path, what)
    if path.is_dir() and any(path.iterdir()):
        if not force:
            raise OutputExistsError(
                f"{path}: {what} folder already holds results; choose another --out or pass "
                "--force (the old folder is then kept as NAME.old-<time>)"
            )
        if not is_treeinfer_output(path):
            raise OutputExistsError(
                f"{path}: --force replaces only folders treeinfer wrote (with a {OUTPUT_MARKER} "
                "marker) or empty ones, and this one is neither; move it yourself if you "
                "mean to, or choose another --out"
            )
    return path


# ---- staging folders ---------------------------------------------------------------------------
def _marker_text(complete: bool) -> str:
    return json.dumps({"writer": "treeinfer", "complete": bool(complete)}) + "\n"


def _stage_complete(stage: Path) -> bool:
    d = _read_json_quietly(stage / OUTPUT_MARKER)
    return isinstance(d, dict) and d.get("complete") is True


def _pid_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _sibling_pid(entry: str, name: str) -> int | None:
    """PID in ``.NAME.PID.XXXX.staging`` / ``.NAME.PID.old`` (None: not ours or no PID)."""
    rest = entry[len(name) + 2 :]
    head = rest.split(".", 1)[0]
    return int(head) if head.isdigit() else None


def _removable_stage(stage: Path) -> bool:
    """An unfinished staging folder that only treeinfer can have filled: our marker says
    unfinished, and nothing in it is a mount point (rmtree would descend into it)."""
    d = _read_json_quietly(stage / OUTPUT_MARKER)
    if not (isinstance(d, dict) and d.get("writer") == "treeinfer" and d.get("complete") is False):
        return False
    for root, dirs, _files in os.walk(stage):
        for name in dirs:
            if os.path.ismount(os.path.join(root, name)):
                return False
    return True


def find_staging(path: str | os.PathLike) -> list[Path]:
    """Staging (``.NAME.*.staging``) and displaced (``.NAME.*.old``, ``.NAME.old-*``) siblings of
    the output folder ``path``, left by a write in progress or by a killed process."""
    path = Path(path)
    parent, name = path.parent, path.name
    if not parent.is_dir():
        return []
    out = []
    for p in parent.iterdir():
        n = p.name
        if not n.startswith(f".{name}.") or not p.is_dir():
            continue
        if n.endswith((STAGING_SUFFIX, OLD_SUFFIX)) or n.startswith(f".{name}.old-"):
            out.append(p)
    return sorted(out)


def clean_stale_staging(
    path: str | os.PathLike, log: Callable[[str], None] | None = None
) -> list[str]:
    """Tidy what killed writers of the output folder ``path`` left beside it; return messages.

    A staging folder of a live process is left alone (reported). Of a dead one: a *complete*
    staging folder (its marker says so) is moved into place if the destination is missing (the
    kill fell between the two renames of the publish step), else kept at ``NAME.complete-PID``;
    a displaced previous result (``.old``) is put back if the destination is missing; an
    unfinished staging folder is removed.
    """
    from .ownership import old_name

    path = Path(path)
    msgs: list[str] = []
    entries = find_staging(path)
    # complete stages first, then displaced old results, then the rest
    entries.sort(
        key=lambda p: (
            not (p.name.endswith(STAGING_SUFFIX) and _stage_complete(p)),
            not p.name.endswith(OLD_SUFFIX),
        )
    )
    for p in entries:
        pid = _sibling_pid(p.name, path.name)
        if pid is not None and pid != os.getpid() and _pid_alive(pid):
            msgs.append(f"{p}: staging folder of running process {pid}; left alone")
            continue
        if pid == os.getpid():
            continue
        try:
            if not path.exists() and p.name.endswith(STAGING_SUFFIX) and _stage_complete(p):
                os.replace(p, path)
                msgs.append(
                    f"{path}: recovered the finished result a killed process left in {p.name}"
                )
            elif p.name.endswith(STAGING_SUFFIX) and _stage_complete(p):
                kept = path.with_name(f"{path.name}{COMPLETE_INFIX}{pid}")
                os.replace(p, kept)
                msgs.append(
                    f"{path}: a killed process finished a newer result than this one; it is "
                    f"kept, complete, in {kept}"
                )
            elif not path.exists() and (p.name.endswith(OLD_SUFFIX) or ".old-" in p.name):
                os.replace(p, path)
                msgs.append(
                    f"{path}: put back the previous result a killed process had moved to {p.name}"
                )
            elif p.name.endswith(STAGING_SUFFIX) and _removable_stage(p):
                shutil.rmtree(p)
                msgs.append(f"{p}: removed a staging folder left by an interrupted process")
            else:  # not provably an unfinished staging folder of ours: keep it, visibly
                kept = old_name(path)
                os.replace(p, kept)
                msgs.append(f"{p}: left by an interrupted process; kept as {kept}")
        except OSError as e:
            msgs.append(
                f"{p}: stale staging folder could not be tidied ({e.strerror or e}); remove it "
                "yourself"
            )
    if log is not None:
        for m in msgs:
            log(m)
    return msgs


def _rescue(stage: Path, path: Path, e: OSError, what: str) -> OutputWriteError:
    """The final rename failed: keep the finished folder at a visible name and say where."""
    kept = path.with_name(f"{path.name}{COMPLETE_INFIX}{os.getpid()}")
    try:
        os.replace(stage, kept)
    except OSError:
        kept = stage
    hint = _ERRNO_HINT.get(e.errno or -1, "")
    return OutputWriteError(
        f"{path}: cannot move the finished {what} into place ({e.strerror or e}"
        f"{'; ' + hint if hint and hint.lower() != (e.strerror or '').lower() else ''}); "
        f"nothing is lost: it is complete in {kept}; move or rename it yourself"
    )


def publish_staged(
    stage: Path, path: Path, what: str = "output", log: Callable[[str], None] | None = None
) -> Path:
    """Move the complete folder ``stage`` to ``path``, never losing either: a previous ``path``
    is moved aside to ``NAME.old-<time>`` (reported; :func:`treeinfer.io.ownership.move_aside`),
    never deleted; on failure the previous result is put back and the new one kept (_rescue).
    The folder's ``manifest.json`` (every file with its sha256) is written first."""
    from .manifest import write_manifest
    from .ownership import old_name, report

    try:
        write_manifest(stage)
    except OSError as e:
        shutil.rmtree(stage, ignore_errors=True)  # our own staging folder, never published
        raise output_error(stage, e) from None
    with contextlib.suppress(OSError):
        (stage / OUTPUT_MARKER).write_text(_marker_text(True), encoding="utf-8")
    if path.is_dir() and not path.is_symlink():
        with contextlib.suppress(OSError):
            os.rmdir(path)  # an empty folder: nothing to keep (fails on anything else)
    if path.exists() or path.is_symlink():
        old = old_name(path)
        try:
            os.replace(path, old)
        except OSError as e:
            raise _rescue(stage, path, e, what) from None
        try:
            os.replace(stage, path)
        except OSError as e:
            with contextlib.suppress(OSError):
                os.replace(old, path)
            raise _rescue(stage, path, e, what) from None
        report(
            f"the previous {what} {path} was moved to {old} (nothing was deleted; remove it "
            "yourself when you no longer need it)",
            log,
        )
    else:
        try:
            os.replace(stage, path)
        except OSError as e:
            raise _rescue(stage, path, e, what) from None
    return path


@contextlib.contextmanager
def staged_output_dir(
    path: str | os.PathLike,
    force: bool = False,
    what: str = "output",
    inputs: Iterable[str | os.PathLike] = (),
    log: Callable[[str], None] | None = None,
    allow_inside: Iterable[str | os.PathLike] = (),
) -> Iterator[Path]:
    """Build a whole output folder under a temporary sibling and move it into place at the end.

    On error the staging folder is removed and ``path`` is left exactly as it was.
    With ``force`` an existing ``path`` is replaced only after the new one is complete, and only
    if treeinfer wrote it (see :func:`check_output_dir`; ``inputs`` are never replaced). Stale
    staging folders of the same destination are tidied first (``log`` gets what was done).
    """
    path = Path(path)
    inputs = tuple(inputs)
    check_output_dir(path, force, what, inputs, allow_inside)
    clean_stale_staging(path, log)
    # a recovered result counts as existing output
    check_output_dir(path, force, what, inputs, allow_inside)
    stage: Path | None = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        stage = Path(
            tempfile.mkdtemp(
                prefix=f".{path.name}.{os.getpid()}.", suffix=STAGING_SUFFIX, dir=path.parent
            )
        )
        interrupt.register(stage)  # removed even if a second Ctrl-C ends the process at once
        _publish_mode(stage, directory=True)
        (stage / OUTPUT_MARKER).write_text(_marker_text(False), encoding="utf-8")
    except OSError as e:
        if stage is not None:
            shutil.rmtree(stage, ignore_errors=True)
        raise output_error(path.parent, e, "create a staging folder in") from None
    try:
        yield stage
    except BaseException as e:
        shutil.rmtree(stage, ignore_errors=True)
        interrupt.unregister(stage)
        if isinstance(e, OSError) and e.errno in _DISK_ERRNOS:
            raise output_error(getattr(e, "filename", None) or stage, e) from None
        raise
    try:
        publish_staged(stage, path, what, log)
    finally:
        interrupt.unregister(stage)


def mark_output_dir(path: str | os.PathLike) -> Path:
    """Put the ``.treeinfer-output`` marker into a folder treeinfer writes in place (not staged),
    so that a later ``--force`` may replace it."""
    return atomic_write_text(Path(path) / OUTPUT_MARKER, _marker_text(True))
