"""Which XLA programs a process compiled, and which it loaded from the persistent cache.

JAX logs "Finished XLA compilation of F in S sec" for persistent-cache hits as well (the log
wraps the cache lookup), so counting that line overstates the work. This module listens to
``jax.monitoring`` instead: every backend compile request ends with the duration event
``/jax/core/compile/backend_compile_duration`` (with the function's name), and a request
served from the persistent cache records ``/jax/compilation_cache/cache_hits`` before it. A
request without a hit is an XLA compilation. Used by ``treeinfer warmup`` (what it compiled),
the time-to-posterior benchmark's child processes and the cold-start tests.
"""

from __future__ import annotations

import dataclasses
import threading

__all__ = ["CompileStats", "compile_stats"]

_BACKEND_COMPILE = "/jax/core/compile/backend_compile_duration"
_HIT = "/jax/compilation_cache/cache_hits"


@dataclasses.dataclass
class CompileStats:
    """Running totals since :func:`compile_stats` first installed the listeners."""

    compiled: list = dataclasses.field(default_factory=list)  # (name, seconds) per compilation
    cache_hits: list = dataclasses.field(default_factory=list)  # (name, seconds) per load
    _hit_pending: dict = dataclasses.field(default_factory=dict)  # thread id -> a hit was seen

    def mark(self) -> tuple[int, int]:
        """The counts now, to pass to :meth:`since`."""
        return len(self.compiled), len(self.cache_hits)

    def since(self, mark: tuple[int, int] = (0, 0)) -> dict:
        """``{"xla_compiles", "compile_s", "compiled": [[name, s], ...], "cache_hits"}`` since
        ``mark`` (JSON-ready; ``compiled`` slowest first)."""
        comp, hits = self.compiled[mark[0] :], self.cache_hits[mark[1] :]
        return {
            "xla_compiles": len(comp),
            "compile_s": round(sum(s for _, s in comp), 3),
            "compiled": [[n, round(s, 3)] for n, s in sorted(comp, key=lambda e: -e[1])],
            "cache_hits": len(hits),
        }

    # the listeners: JAX may compile in several threads at once (treeinfer's compile threads),
    # and a hit and its duration event come from the same thread
    def _on_event(self, event: str, **_kw) -> None:
        if event == _HIT:
            self._hit_pending[threading.get_ident()] = True

    def _on_duration(self, event: str, secs: float, **kw) -> None:
        if event != _BACKEND_COMPILE:
            return
        name = str(kw.get("fun_name", "?"))
        if self._hit_pending.pop(threading.get_ident(), False):
            self.cache_hits.append((name, float(secs)))
        else:
            self.compiled.append((name, float(secs)))


_STATS: CompileStats | None = None
_LOCK = threading.Lock()


def compile_stats() -> CompileStats:
    """The process's :class:`CompileStats`, its listeners installed on the first call (they
    stay for the life of the process: counting costs a dictionary update per compile)."""
    global _STATS
    with _LOCK:
        if _STATS is None:
            from jax import monitoring

            _STATS = CompileStats()
            monitoring.register_event_listener(_STATS._on_event)
            monitoring.register_event_duration_secs_listener(_STATS._on_duration)
        return _STATS
