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
import json
import math
import os
import stat
from pathlib import Path
from typing import Any

from .errors import ConfigError, TreeinferError

MAX_BYTES = 16 * 1024 * 1024
MAX_DEPTH = 64
MAX_ALIASES = 1000
MAX_NODES = 200_000

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


# ---- YAML ------------------------------------------------------------------------------------
def _yaml_loader_class():
    import yaml

    class _Loader(yaml.SafeLoader):
        """SafeLoader that bounds depth, alias use and expanded size, and refuses duplicate keys."""

        max_depth = MAX_DEPTH
        max_aliases = MAX_ALIASES
        max_nodes = MAX_NODES

        def __init__(self, stream):
            super().__init__(stream)
            self._depth = 0
            self._aliases = 0

        def compose_node(self, parent, index):
            if self.check_event(yaml.AliasEvent):
                self._aliases += 1
                if self._aliases > self.max_aliases:
                    ev = self.peek_event()
                    raise yaml.composer.ComposerError(
                        None,
                        None,
                        f"more than {self.max_aliases} aliases (alias bomb?)",
                        ev.start_mark,
                    )
                return super().compose_node(parent, index)
            self._depth += 1
            if self._depth > self.max_depth:
                ev = self.peek_event()
                raise yaml.composer.ComposerError(
                    None, None, f"nested deeper than {self.max_depth} levels", ev.start_mark
                )
            try:
                return super().compose_node(parent, index)
            finally:
                self._depth -= 1

        def construct_mapping(self, node, deep=False):
            if isinstance(node, yaml.MappingNode):
                seen: dict[Any, Any] = {}
                for key_node, _ in node.value:
                    if key_node.tag == "tag:yaml.org,2002:merge":
                        continue
                    key = self.construct_object(key_node, deep=True)
                    try:
                        hash(key)
                    except TypeError:
                        continue  # the base class reports unhashable keys
                    if key in seen:
                        raise yaml.constructor.ConstructorError(
                            None,
                            None,
                            f"duplicate key {key!r} (first at line {seen[key].line + 1})",
                            key_node.start_mark,
                        )
                    seen[key] = key_node.start_mark
            return super().construct_mapping(node, deep=deep)

    return _Loader


def _expanded_size(node, limit: int) -> int:
    """Nodes the document would have with every alias expanded (memoised on shared nodes,
    iterative, stops counting past ``limit``); -1 for a recursive (self-containing) document."""
    import yaml

    memo: dict[int, int] = {}
    active: set[int] = set()
    stack: list[tuple[Any, bool]] = [(node, False)]
    while stack:
        n, done = stack.pop()
        if id(n) in memo:
            continue
        if isinstance(n, yaml.ScalarNode):
            memo[id(n)] = 1
            continue
        kids = (
            [c for kv in n.value for c in kv] if isinstance(n, yaml.MappingNode) else list(n.value)
        )
        if done:
            active.discard(id(n))
            total = 1
            for c in kids:
                total += memo[id(c)]
                if total > limit:
                    return total
            memo[id(n)] = total
        else:
            if id(n) in active:
                return -1
            active.add(id(n))
            stack.append((n, True))
            for c in kids:
                if id(c) in active:
                    return -1
                if id(c) not in memo:
                    stack.append((c, False))
    return memo[id(node)]


def loads_yaml(
    text: str,
    source: str = "<yaml>",
    error: type[TreeinferError] = ConfigError,
    max_depth: int = MAX_DEPTH,
    max_aliases: int = MAX_ALIASES,
    max_nodes: int = MAX_NODES,
) -> Any:
    """Parse one YAML document with the limits of this module; errors name ``source`` and line."""
    import yaml

    cls = _yaml_loader_class()
    cls.max_depth, cls.max_aliases, cls.max_nodes = max_depth, max_aliases, max_nodes
    try:
        loader = cls(text)
    except yaml.YAMLError as e:  # a character YAML does not allow (ReaderError)
        raise error(f"{source}: invalid YAML: {e}") from None
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        size = _expanded_size(node, max_nodes)
        if size < 0:
            raise error(
                f"{source}: the document contains itself through an alias (recursive "
                "structure); refusing to load it"
            )
        if size > max_nodes:
            raise error(
                f"{source}: the document expands to more than {max_nodes} nodes "
                "(aliases repeated many times: an alias bomb?); refusing to load it"
            )
        return loader.construct_document(node)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None) or getattr(e, "context_mark", None)
        line = f", line {mark.line + 1}" if mark is not None else ""
        problem = getattr(e, "problem", None) or str(e)
        raise error(f"{source}{line}: invalid YAML: {problem}") from None
    except RecursionError:
        raise error(f"{source}: nested too deeply to read") from None
    finally:
        loader.dispose()


# ---- JSON ------------------------------------------------------------------------------------
def _json_depth(text: str, limit: int) -> tuple[int, int]:
    """(deepest bracket nesting, line where ``limit`` was first exceeded or 0), strings skipped.

    Linear scan before ``json.loads``, whose recursive decoder would hit RecursionError."""
    depth = deepest = 0
    in_str = esc = False
    line = 1
    for ch in text:
        if ch == "\n":
            line += 1
        if in_str:
            if esc:
                esc = False
            elif ch == "\\":
                esc = True
            elif ch == '"':
                in_str = False
            continue
        if ch == '"':
            in_str = True
        elif ch in "[{":
            depth += 1
            if depth > deepest:
                deepest = depth
                if deepest > limit:
                    return deepest, line
        elif ch in "]}":
            depth -= 1
    return deepest, 0


def _key_line(text: str, key: str, nth: int) -> int | None:
    """Line of the ``nth`` (0-based) occurrence of ``"key":`` in ``text`` (for messages only)."""
    import re

    pat = re.compile(re.escape(json.dumps(key)) + r"\s*:")
    hits = [m.start() for m in pat.finditer(text)]
    if len(hits) > nth:
        return text.count("\n", 0, hits[nth]) + 1
    return None


def loads_json(
    text: str,
    source: str = "<json>",
    error: type[TreeinferError] = ConfigError,
    max_depth: int = MAX_DEPTH,
) -> Any:
    """Parse JSON refusing duplicate keys, NaN/Infinity literals and deep nesting."""
    deepest, line = _json_depth(text, max_depth)
    if deepest > max_depth:
        raise error(f"{source}, line {line}: nested deeper than {max_depth} levels")
    counts: dict[str, int] = {}

    def pairs(items):
        out: dict[str, Any] = {}
        for k, v in items:
            if k in out:
                n = counts.get(k, 0) + 1
                ln = _key_line(text, k, n)
                where = f", line {ln}" if ln else ""
                raise error(f"{source}{where}: duplicate key {k!r}")
            out[k] = v
        for k in out:
            counts[k] = counts.get(k, 0) + 1
        return out

    def no_constant(name):
        raise error(f"{source}: {name} is not a valid JSON number")

    try:
        return json.loads(text, object_pairs_hook=pairs, parse_constant=no_constant)
    except json.JSONDecodeError as e:
        raise error(f"{source}, line {e.lineno}: invalid JSON: {e.msg}") from None
    except RecursionError:
        raise error(f"{source}: nested too deeply to read") from None


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
