"""Bounded parsing of YAML and JSON text (for :mod:`treeinfer.io.safe_load`, which re-exports it):
depth, alias and node limits against billion-laughs and deeply nested input, duplicate keys
refused, errors naming the source and line."""

from __future__ import annotations

import json
from typing import Any

from ..errors import ConfigError, TreeinferError

MAX_BYTES = 16 * 1024 * 1024
MAX_DEPTH = 64
MAX_ALIASES = 1000
MAX_NODES = 200_000


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
