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

from ..errors import ConfigError, TreeFileError

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


def _opt(rest: list[str], flag: str, default: float) -> float:
    """The value of ``flag`` among infer options passed through (``warmup -- ...``)."""
    for i, a in enumerate(rest):
        if a == flag and i + 1 < len(rest):
            v = rest[i + 1]
        elif a.startswith(flag + "="):
            v = a.split("=", 1)[1]
        else:
            continue
        try:
            return float(v)
        except ValueError:
            return default  # infer itself names the bad value
    return default


def _n(v, default: float = 1.0) -> float:
    if v is None:
        return default
    if isinstance(v, (list, tuple)):
        return float(len(v))
    try:
        return float(v)
    except (TypeError, ValueError):
        return default


def check_command_size(command: str, args) -> None:
    """:func:`check_work` for ``calibrate``, ``warmup`` and ``suggest`` from their parsed
    options, before anything is read or compiled (``args.allow_large`` goes past)."""
    g = lambda name, d=1.0: _n(getattr(args, name, None), d)  # noqa: E731
    allow = bool(getattr(args, "allow_large", False))
    if command == "calibrate":
        samples = g("duration", 1.0) / max(g("dt", 0.01), 1e-9)
        factors = [
            ("--datasets", g("datasets")),
            ("--n-traj", g("n_traj")),
            ("samples (--duration / --dt)", samples),
            ("max(--smc-particles, --particles)", max(g("smc_particles"), g("particles"))),
            ("max(--smc-levels, --iterations)", max(g("smc_levels"), g("iterations"))),
        ]
        check_work(factors, allow, limit=MAX_WORK * 1e3)  # samples x pulls weigh less
    elif command == "warmup":
        rest = list(getattr(args, "infer_options", []) or [])
        factors = [
            ("--n-traj", g("trajectories")),
            ("--steps", g("steps")),
            ("infer --particles", _opt(rest, "--particles", 32)),
            ("infer --iterations", _opt(rest, "--iterations", 300)),
        ]
        check_work(factors, allow, limit=MAX_WORK * 1e3)
    elif command == "simulate":
        if isinstance(getattr(args, "seed", 0), int) and args.seed < 0:
            raise ConfigError(f"--seed: must be an integer >= 0, got {args.seed}")
        samples = g("duration", 1.0) / max(g("dt", 0.01), 1e-9)
        n = len(args.profile) if getattr(args, "profile", None) else g("n_traj", 8)
        factors = [("--n-traj", n), ("samples (--duration / --dt)", samples)]
        check_work(factors, allow, limit=1e8)  # 1e8 samples of 3 floats: 2.4 GB of output
    elif command == "suggest":
        factors = [
            ("--particles", g("particles", 32)),
            ("--grasp-fractions", g("grasp_fractions", 4)),
            ("--peak-forces", g("peak_forces", 4)),
            ("--profile-kinds", g("profile_kinds", 2)),
            ("--directions", g("directions", 1)),
        ]
        check_work(factors, allow, limit=1e6)
