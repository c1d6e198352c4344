"""The explicit cache of compiled programs: whoever runs several samplers or studies in one
process owns a :class:`ProgramCache` and hands it to :func:`treeinfer.inference.samplers.run`,
:func:`treeinfer.inference.problem.infer` or :mod:`treeinfer.inference.batch` (``cache=``). No
module keeps one: without a cache each call builds (and compiles) its program afresh, so what a
process keeps compiled is always visible, and dropped with the object that owns it.

The application layer's :class:`treeinfer.runs.SimulatorCache` carries one
(``SimulatorCache.programs``), so a command's runs and folds share compiled programs the way
they share simulators.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable
from typing import Any

__all__ = ["ProgramCache"]


class ProgramCache:
    """At most ``max_size`` programs (jitted functions or compiled executables) by hashable
    key, the oldest dropped first. Keys hold what identifies a program: the traced functions
    themselves (so an entry keeps them alive while it is cached), static settings and the
    argument shapes. ``builds`` counts the programs built through :meth:`get` (cache misses)."""

    def __init__(self, max_size: int = 8):
        if isinstance(max_size, bool) or not isinstance(max_size, int) or max_size < 1:
            from ..errors import ConfigError

            raise ConfigError(f"ProgramCache: max_size must be an integer >= 1, got {max_size!r}")
        self.max_size = max_size
        self.builds = 0
        self._programs: dict[Hashable, Any] = {}

    def __len__(self) -> int:
        return len(self._programs)

    def __contains__(self, key: Hashable) -> bool:
        return key in self._programs

    def get(self, key: Hashable, build: Callable[[], Any]) -> Any:
        """The program under ``key``; ``build()`` makes (and stores) it on a miss."""
        if key in self._programs:
            return self._programs[key]
        program = build()
        self.builds += 1
        while len(self._programs) >= self.max_size:
            self._programs.pop(next(iter(self._programs)))
        self._programs[key] = program
        return program

    def clear(self) -> None:
        self._programs.clear()
