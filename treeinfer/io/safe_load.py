"""One safe loader for the YAML and JSON files treeinfer reads (trees, run configs, sidecars).

What it refuses, each with a :class:`~treeinfer.errors.TreeinferError` naming the file (and the
line where the parser knows it):

- anything but a regular file, *before* reading it: a FIFO would block forever, ``/dev/zero``
  would fill memory, a directory is a mistake. The file is opened with ``O_NONBLOCK`` and
  checked with ``fstat`` on the open descriptor, so a FIFO swapped in after a ``stat`` cannot
  block either;
- files larger than ``max_bytes`` (default 16 MiB; a tree file is a few KiB);
- nesting deeper than ``max_depth`` (default 64) instead of a ``RecursionError``;
- YAML alias bombs ("billion laughs"): more than ``max_aliases`` aliases, or a document whose
  aliases would expand to more than ``max_nodes`` nodes (counted on the composed node graph,
  with sharing, so the count itself is cheap);
- duplicate mapping keys (YAML and JSON; silently "last wins" elsewhere);
- YAML tags beyond the safe set (PyYAML's ``SafeLoader`` already refuses Python objects).

Typed fields: YAML 1.1 turns ``yes``/``no``/``on``/``off`` into booleans and ``null``/``~``
into None. The helpers :func:`number`, :func:`string` and :func:`boolean` take the parsed value
and refuse the wrong kind with the field named (``length: yes`` is not 1.0; ``name: null`` is
not the branch ``"None"``).

Why our own subclass of PyYAML's SafeLoader rather than another library: PyYAML is already a
dependency and its composer exposes the node graph, which is where depth, aliases and
duplicate keys can be checked before any Python object is built.
"""

from __future__ import annotations

import errno
import math
import os
import stat
from pathlib import Path
from typing import Any

from ..errors import ConfigError, TreeinferError
from .safe_parse import (  # noqa: F401 -- re-exported: the old import path keeps working
    MAX_ALIASES,
    MAX_BYTES,
    MAX_DEPTH,
    MAX_NODES,
    loads_json,
    loads_yaml,
)

__all__ = [
    "MAX_ALIASES",
    "MAX_BYTES",
    "MAX_DEPTH",
    "MAX_NODES",
    "boolean",
    "list_data_files",
    "load_file",
    "loads_json",
    "loads_yaml",
    "number",
    "read_regular_file",
    "refuse_special_paths",
    "require_regular_file",
    "string",
]


def _kind_of(mode: int) -> str | None:
    """A readable name for a non-regular file type, or None for a regular file."""
    if stat.S_ISREG(mode):
        return None
    if stat.S_ISDIR(mode):
        return "a folder"
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISCHR(mode):
        return "a character device"
    if stat.S_ISBLK(mode):
        return "a block device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def require_regular_file(
    path: str | os.PathLike, what: str = "file", error: type[TreeinferError] = ConfigError
) -> Path:
    """Return ``path`` if it names an existing regular file (symlinks followed).

    Raises ``error`` for a missing file, a broken symlink, a folder, a FIFO, a device or a
    socket; never opens the file (so it cannot block on a FIFO).
    """
    path = Path(path)
    try:
        st = os.stat(path)
    except FileNotFoundError:
        if os.path.islink(path):
            raise error(f"{path}: {what} is a broken symbolic link") from None
        raise error(f"{path}: no such file; cannot read {what}") from None
    except OSError as e:
        raise error(f"{path}: cannot read {what} ({e.strerror or e})") from None
    kind = _kind_of(st.st_mode)
    if kind is not None:
        raise error(f"{path}: {what} is {kind}, not a regular file")
    return path


def read_regular_file(
    path: str | os.PathLike,
    what: str = "file",
    error: type[TreeinferError] = ConfigError,
    max_bytes: int = MAX_BYTES,
) -> bytes:
    """The bytes of a regular file of at most ``max_bytes``; refuses FIFOs and devices without
    blocking (``O_NONBLOCK`` open, then ``fstat`` on the descriptor)."""
    path = Path(path)
    require_regular_file(path, what, error)
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0))
    except OSError as e:
        raise error(f"{path}: cannot open {what} ({e.strerror or e})") from None
    try:
        st = os.fstat(fd)
        kind = _kind_of(st.st_mode)
        if kind is not None:  # swapped after the stat above
            raise error(f"{path}: {what} is {kind}, not a regular file")
        if st.st_size > max_bytes:
            raise error(
                f"{path}: {what} is {st.st_size} bytes; more than the limit of {max_bytes} "
                "bytes for this kind of file"
            )
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
        chunks, total = [], 0
        while True:
            block = os.read(fd, 1 << 20)
            if not block:
                break
            total += len(block)
            if total > max_bytes:  # grew while we read
                raise error(f"{path}: {what} is larger than the limit of {max_bytes} bytes")
            chunks.append(block)
        return b"".join(chunks)
    except OSError as e:
        io = (
            " (I/O error: failing disk or unreadable network file?)" if e.errno == errno.EIO else ""
        )
        raise error(f"{path}: cannot read {what} ({e.strerror or e}){io}") from None
    finally:
        os.close(fd)


def refuse_special_paths(
    path: str | os.PathLike,
    what: str = "input",
    error: type[TreeinferError] = ConfigError,
    max_entries: int = 100_000,
) -> Path:
    """Refuse, without opening anything, an input path that is, or a folder that holds, a FIFO,
    device, socket or symbolic-link loop (a reader would block on it or read forever): the one
    check every reader of a path runs first (bags, model files, data folders, run folders).

    Missing paths are left to the reader (it names them). Folders are walked iteratively,
    symlinks to folders not followed, at most ``max_entries`` entries.
    """
    path = Path(path)
    stack, n = [path], 0
    while stack:
        p = stack.pop()
        try:
            st = os.stat(p)
        except FileNotFoundError:
            if p != path and os.path.islink(p):
                raise error(f"{p}: {what} holds a broken symbolic link") from None
            continue
        except OSError as e:
            why = "a symbolic-link loop" if e.errno == errno.ELOOP else (e.strerror or str(e))
            raise error(f"{p}: cannot read {what} ({why})") from None
        if stat.S_ISDIR(st.st_mode):
            if p != path and os.path.islink(p):
                continue
            try:
                entries = list(os.scandir(p))
            except OSError as e:
                raise error(f"{p}: cannot list {what} ({e.strerror or e})") from None
            n += len(entries)
            if n > max_entries:
                raise error(f"{path}: {what} holds more than {max_entries} files; refused")
            stack.extend(Path(e.path) for e in entries)
            continue
        kind = _kind_of(st.st_mode)
        if kind is not None:
            raise error(f"{p}: {what} is {kind}, not a regular file; refused before reading")
    return path


# ---- files -----------------------------------------------------------------------------------
def load_file(
    path: str | os.PathLike,
    what: str = "file",
    error: type[TreeinferError] = ConfigError,
    fmt: str | None = None,
    max_bytes: int = MAX_BYTES,
    max_depth: int = MAX_DEPTH,
    max_aliases: int = MAX_ALIASES,
    max_nodes: int = MAX_NODES,
) -> Any:
    """Read a YAML or JSON file safely (see the module docstring).

    Args:
      path: the file. what: what it is, for messages ("tree file", "run config").
      error: the TreeinferError subclass to raise. fmt: "yaml" or "json"; None: by suffix
        (``.json`` is JSON, anything else YAML).
    """
    path = Path(path)
    raw = read_regular_file(path, what, error, max_bytes)
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise error(f"{path}: {what} is not UTF-8 text (byte {e.start})") from None
    fmt = fmt or ("json" if path.suffix.lower() == ".json" else "yaml")
    if fmt == "json":
        return loads_json(text, str(path), error, max_depth)
    return loads_yaml(text, str(path), error, max_depth, max_aliases, max_nodes)


# ---- typed fields ----------------------------------------------------------------------------
def _loc(source: str | None, fld: str) -> str:
    return f"{source}: {fld}" if source else fld


def number(
    value: Any,
    fld: str,
    source: str | None = None,
    error: type[TreeinferError] = ConfigError,
    finite: bool = True,
) -> float:
    """``value`` as a float; refuses booleans (YAML ``yes``/``no``), None, strings and NaN/inf."""
    if (
        isinstance(value, bool)
        or value is None
        or isinstance(value, str)
        or not isinstance(value, (int, float))
        and not hasattr(value, "__float__")
    ):
        raise error(
            f"{_loc(source, fld)}: expected a number, got {value!r}"
            + (
                " (YAML reads yes/no/on/off as booleans; write a number)"
                if isinstance(value, bool)
                else ""
            )
        )
    try:
        v = float(value)
    except (TypeError, ValueError, OverflowError):
        raise error(f"{_loc(source, fld)}: expected a number, got {value!r}") from None
    if finite and not math.isfinite(v):
        raise error(f"{_loc(source, fld)}: must be finite, got {value!r}")
    return v


def string(
    value: Any,
    fld: str,
    source: str | None = None,
    error: type[TreeinferError] = ConfigError,
    allow_int: bool = True,
) -> str:
    """``value`` as a str; refuses None (YAML ``null``/``~``), booleans, floats, lists, maps.
    Integers are accepted (and converted) with ``allow_int``."""
    if isinstance(value, str):
        return value
    if allow_int and isinstance(value, int) and not isinstance(value, bool):
        return str(value)
    hint = (
        " (YAML reads null/~ as nothing and yes/no/on/off as booleans: quote it)"
        if (value is None or isinstance(value, bool))
        else ""
    )
    raise error(f"{_loc(source, fld)}: expected a name (text), got {value!r}{hint}")


def boolean(
    value: Any, fld: str, source: str | None = None, error: type[TreeinferError] = ConfigError
) -> bool:
    """``value`` if it is a real boolean (``true``/``false``); refuses 0/1, strings and None."""
    if isinstance(value, bool):
        return value
    raise error(f"{_loc(source, fld)}: expected true or false, got {value!r}")


def list_data_files(
    directory: str | os.PathLike, suffix: str = ".csv", error: type[TreeinferError] = ConfigError
) -> tuple[list[Path], list[str]]:
    """The regular ``*{suffix}`` files of ``directory`` (sorted), and one sentence for every
    entry that looks like data but will not be read, naming it: a FIFO, device, folder or broken
    symbolic link with that suffix, or a file whose suffix differs only in case (``.CSV``).

    Never opens a file (a FIFO cannot block it). ``error`` for a missing folder.
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise error(f"{directory}: no such folder")
    files, skipped = [], []
    for p in sorted(directory.iterdir()):
        name = p.name
        if not name.lower().endswith(suffix.lower()):
            continue
        if not name.endswith(suffix):
            skipped.append(f"{p}: not read: the suffix must be '{suffix}' in lower case; rename it")
            continue
        try:
            st = os.stat(p)
        except FileNotFoundError:
            skipped.append(f"{p}: not read: broken symbolic link")
            continue
        except OSError as e:
            skipped.append(f"{p}: not read: {e.strerror or e}")
            continue
        kind = _kind_of(st.st_mode)
        if kind is not None:
            skipped.append(f"{p}: not read: it is {kind}, not a regular file")
            continue
        files.append(p)
    return files, skipped
