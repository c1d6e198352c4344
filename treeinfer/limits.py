"""Size limits checked before any work, so that an absurd size is a clear error in a second
instead of minutes of computing or an exhausted memory (issue 28, section 4).

- a tree: at most :data:`MAX_BRANCHES` branches and :data:`MAX_TREE_DEPTH` joints from the root
  to a tip (orchard trees have a few to a few dozen; a 1,000-branch model is almost surely a
  mistake, e.g. a fractal of depth 25 has 2^26 - 1 branches and would never finish);
- the work of ``calibrate``/``warmup``/``suggest``: particles x iterations x data sets (or
  rollouts) at most :data:`MAX_WORK`.

Going past: ``--allow-large`` where a command has it, or ``TREEINFER_ALLOW_LARGE=1`` for every
command (trees are read in many places; one switch reaches them all). Deep trees that are let
through are walked iteratively; the XML writers of the standard library recurse, so they run
under :func:`deep_recursion`.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterable, Iterator, Mapping

from .errors import ConfigError, TreeFileError

__all__ = [
    "ENV",
    "MAX_BRANCHES",
    "MAX_TREE_DEPTH",
    "MAX_WORK",
    "allow_large",
    "check_tree_size",
    "check_work",
    "deep_recursion",
    "tree_depth",
]

ENV = "TREEINFER_ALLOW_LARGE"
MAX_BRANCHES = 256
MAX_TREE_DEPTH = 128
MAX_WORK = 10**8  # particle-iterations x data sets: about a day of CPU at the default sizes
HOW = f"pass --allow-large where the command has it, or set {ENV}=1"


def allow_large() -> bool:
    return os.environ.get(ENV, "").strip().lower() in ("1", "true", "yes", "on")


def tree_depth(parents: Mapping[str, str | None]) -> int:
    """Joints on the longest root-to-tip path of ``{branch: parent}`` (iterative, memoised;
    a cycle counts as infinitely deep)."""
    depth: dict[str, int] = {}
    for start in parents:
        path, n = [], start
        while n is not None and n not in depth:
            if n in path or len(path) > len(parents):
                return sys.maxsize  # a cycle; the tree checks name it
            path.append(n)
            n = parents.get(n)
        d = 0 if n is None else depth[n]
        for m in reversed(path):
            d += 1
            depth[m] = d
    return max(depth.values(), default=0)


def check_tree_size(n_branches: int, depth: int, where: str = "branches") -> None:
    """TreeFileError for a tree beyond :data:`MAX_BRANCHES` / :data:`MAX_TREE_DEPTH`."""
    if allow_large():
        return
    if n_branches > MAX_BRANCHES:
        raise TreeFileError(
            f"{where}: {n_branches} branches, more than the limit of {MAX_BRANCHES} (inference "
            f"cost grows with every joint; is this the tree you meant?); to go past it, {HOW}"
        )
    if depth > MAX_TREE_DEPTH:
        raise TreeFileError(
            f"{where}: {depth} joints from the root to a tip, more than the limit of "
            f"{MAX_TREE_DEPTH}; to go past it, {HOW}"
        )


def check_work(
    factors: Iterable[tuple[str, float]], allow: bool = False, limit: float = MAX_WORK
) -> None:
    """ConfigError naming the options when the product of ``(flag, value)`` exceeds ``limit``."""
    factors = list(factors)
    total = 1.0
    for _, v in factors:
        total *= max(float(v), 1.0)
    if total > limit and not (allow or allow_large()):
        named = " x ".join(f"{flag} {v:g}" for flag, v in factors)
        raise ConfigError(
            f"{named} = {total:.3g} units of work, more than the limit of {limit:.3g} (it would "
            f"run for days or exhaust memory); choose smaller sizes, or {HOW}"
        )


@contextlib.contextmanager
def deep_recursion(depth: int) -> Iterator[None]:
    """Let the standard library's recursive walks (``xml.etree`` indent/serialise: about two
    frames per level) through a tree ``depth`` levels deep; restores the limit after."""
    old = sys.getrecursionlimit()
    need = 200 + 4 * int(depth)
    if need > old:
        sys.setrecursionlimit(need)
    try:
        yield
    finally:
        sys.setrecursionlimit(old)
