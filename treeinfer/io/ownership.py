"""Who owns an output path: the one helper every command asks before it writes (issue 28).

Two rules, for every command (``infer``, ``simulate``, ``import-*``, ``tree``, ``calibrate``,
``suggest``, ``predict``, ``evaluate``, ``demo``, ``warmup``) and for the library calls behind
them:

1. **An output never overlaps an input.** :func:`refuse_overlap` refuses an output path that is,
   contains, or lies inside any of the command's inputs (data folder, tree file, model, run,
   prior, source file), comparing resolved paths (symlinks followed), before any work is done;
   the message names both paths.
2. **Nothing treeinfer did not write is ever deleted.** ``--force`` does not delete the previous
   output: :func:`move_aside` renames it to a visible sibling ``NAME.old-<UTC time>`` and says
   where (a folder, or a single file such as ``tree.yaml``). Only an *empty* folder is removed
   (``os.rmdir`` fails on anything else, so that removal cannot lose a file). A marker file
   (``.treeinfer-output``) or a ``config.json`` look-alike therefore decides nothing
   destructive: at most it lets ``--force`` move a folder aside instead of refusing. Folders that
   must never be moved as a whole (the file-system root, the home folder, the current folder or
   one above it, a mount point) are refused even with ``--force``.

Why a rename and not a checksum-guarded delete: a rename is atomic, loses nothing whatever the
folder holds (a user's file, a mount point, a symlink out of the folder), and needs no
trust in a manifest a user could have copied. The cost is disk space, and the report says which
folder to delete once the user no longer needs it.
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
from collections.abc import Callable, Iterable
from pathlib import Path

from ..errors import OutputExistsError
from .atomic_write import atomic_write_bytes, output_error

__all__ = [
    "OLD_INFIX",
    "claim_output_file",
    "move_aside",
    "old_name",
    "refuse_overlap",
    "refuse_unmovable",
    "report",
]

OLD_INFIX = ".old-"


def report(msg: str, log: Callable[[str], None] | None = None) -> None:
    """Tell the user (``log``, else stderr): moving a user's output aside is never silent."""
    if log is not None:
        log(msg)
    else:
        print(f"note: {msg}", file=sys.stderr)


def _real(p: str | os.PathLike) -> Path:
    return Path(os.path.realpath(os.path.expanduser(os.fspath(p))))


def _inside(child: Path, parent: Path) -> bool:
    return child == parent or parent in child.parents


def refuse_overlap(
    out: str | os.PathLike,
    inputs: Iterable[str | os.PathLike | None],
    what: str = "output",
    allow: Iterable[str | os.PathLike] = (),
) -> None:
    """Raise :class:`OutputExistsError` if ``out`` is, contains, or lies inside an input.

    ``inputs``: the command's input files and folders (None entries are skipped). ``allow``:
    output paths that may lie inside an input by design (``suggest``'s default ``RUN/suggest``).
    Paths are compared resolved (symlinks, ``..``, ``~``), so a link to the data folder is the
    data folder.
    """
    real_out = _real(out)
    allowed = {_real(a) for a in allow}
    for inp in inputs:
        if inp is None or os.fspath(inp) == "":
            continue
        rin = _real(inp)
        if real_out == rin:
            rel = "is"
        elif _inside(rin, real_out):
            rel = "contains"
        elif _inside(real_out, rin):
            if real_out in allowed:
                continue
            rel = "lies inside"
        else:
            continue
        raise OutputExistsError(
            f"{out}: the {what} {rel} an input of this command ({inp}); writing there could "
            "destroy or change what it reads: choose another output path"
        )


def refuse_unmovable(path: str | os.PathLike, what: str = "output") -> None:
    """Refuse an existing folder that ``--force`` must never move or replace as a whole."""
    path = Path(path)
    real = _real(path)
    if real == Path(real.anchor):
        raise OutputExistsError(f"{path}: the {what} is the file-system root; choose a new folder")
    home = os.environ.get("HOME")
    if home and real == _real(home):
        raise OutputExistsError(
            f"{path}: the {what} is your home folder; give a new folder inside it, e.g. --out "
            f"{path / 'treeinfer-out'}"
        )
    with contextlib.suppress(OSError):
        if _inside(_real(os.getcwd()), real):
            raise OutputExistsError(
                f"{path}: the {what} is the current folder or holds it; give a new folder"
            )
    if path.is_dir() and not path.is_symlink() and os.path.ismount(path):
        raise OutputExistsError(
            f"{path}: the {what} folder is a mount point, which treeinfer cannot replace as a "
            f"whole; give a folder inside it, e.g. --out {path / 'run'}"
        )


def old_name(path: str | os.PathLike) -> Path:
    """A free sibling ``NAME.old-<UTC time>[-k]`` of ``path``."""
    path = Path(path)
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    cand = path.with_name(f"{path.name}{OLD_INFIX}{stamp}")
    k = 1
    while cand.exists() or cand.is_symlink():
        cand = path.with_name(f"{path.name}{OLD_INFIX}{stamp}-{k}")
        k += 1
    return cand


def move_aside(
    path: str | os.PathLike, log: Callable[[str], None] | None = None, what: str = "output"
) -> Path | None:
    """Move the existing ``path`` (file, folder or symlink) to :func:`old_name` and report it.

    Returns the new name, or None when there was nothing to keep: ``path`` did not exist or was
    an empty folder (removed with ``os.rmdir``, which cannot remove anything else). Raises
    OSError from the rename (callers turn it into a message naming the path).
    """
    path = Path(path)
    if not (path.exists() or path.is_symlink()):
        return None
    if path.is_dir() and not path.is_symlink():
        with contextlib.suppress(OSError):
            os.rmdir(path)  # only succeeds on an empty folder
            return None
    dest = old_name(path)
    os.replace(path, dest)
    report(
        f"the previous {what} {path} was moved to {dest} (nothing was deleted; remove it "
        "yourself when you no longer need it)",
        log,
    )
    return dest


def claim_output_file(
    path: str | os.PathLike,
    force: bool,
    inputs: Iterable[str | os.PathLike | None] = (),
    what: str = "output file",
) -> Path:
    """Check that a single output file may be written, before any work: not an input (nor an
    input's folder), not a folder or special file, and absent unless ``force`` (then the old
    file is moved aside by :func:`replace_file_aside` when the new one is written)."""
    path = Path(path)
    refuse_overlap(path, inputs, what)
    if path.is_dir():
        raise OutputExistsError(f"{path}: is a folder, expected a file name for the {what}")
    if path.exists() and not path.is_file():
        raise OutputExistsError(f"{path}: the {what} exists and is not a regular file")
    if (path.exists() or path.is_symlink()) and not force:
        raise OutputExistsError(
            f"{path}: file exists; choose another name or pass --force to replace it (the old "
            "file is then kept as NAME.old-<time>)"
        )
    return path


def keep_previous_file(
    path: str | os.PathLike, new: bytes, log: Callable[[str], None] | None = None
) -> Path | None:
    """Before ``path`` is overwritten with ``new``: move the old file aside unless it already
    holds exactly ``new`` (then nothing is lost by overwriting it). Returns where it went."""
    path = Path(path)
    if path.is_symlink() or not path.exists():
        return move_aside(path, log, "file") if path.is_symlink() else None
    if path.is_file():
        try:
            if path.stat().st_size == len(new) and path.read_bytes() == new:
                return None
        except OSError:
            pass
    return move_aside(path, log, "file")


def write_output_file(
    path: str | os.PathLike, text: str | bytes, log: Callable[[str], None] | None = None
) -> Path:
    """Write a command's output file atomically, keeping a different previous file aside."""
    data = text.encode("utf-8") if isinstance(text, str) else text
    try:
        keep_previous_file(path, data, log)
    except OSError as e:
        raise output_error(path, e, "move the previous file aside") from None
    return atomic_write_bytes(path, data)


def claim_output_files(
    paths: Iterable[str | os.PathLike | None],
    force: bool,
    inputs: Iterable[str | os.PathLike | None] = (),
    what: str = "output file",
) -> list[Path]:
    """:func:`claim_output_file` for each of ``paths`` (None skipped), which must differ."""
    inputs = list(inputs)
    out = [claim_output_file(p, force, inputs, what) for p in paths if p is not None]
    if len({_real(p) for p in out}) != len(out):
        raise OutputExistsError(f"{', '.join(map(str, out))}: the output files must differ")
    return out


def retire_output_files(
    paths: Iterable[str | os.PathLike | None],
    force: bool,
    inputs: Iterable[str | os.PathLike | None] = (),
    log: Callable[[str], None] | None = None,
) -> list[Path]:
    """Just before single output files are written (everything already built in memory): check
    them again (:func:`claim_output_files`) and move each existing one aside, so that ``--force``
    never loses the file it replaces."""
    out = claim_output_files(paths, force, inputs)
    for p in out:
        try:
            move_aside(p, log, "file")
        except OSError as e:
            raise output_error(p, e, "move the previous file aside") from None
    return out
