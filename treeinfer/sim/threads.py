"""Independent calls of one compiled program run on the machine's idle cores.

Why: XLA:CPU runs the rollout program (a loop of scalar steps over a batch of parameter sets)
on one thread, and JAX's asynchronous dispatch does not run two calls at once, so on a 2-core
CPU the start pipeline's rollouts (screen, LM central differences, importance rounds: most of
a warm ``treeinfer infer``) used one core. JAX releases Python's lock while a program runs, so
calls handed to a second thread run beside the first one: the same program on the same inputs,
the same numbers to the bit, sooner where a core is free (one chunk of 104 rollouts: 8 chunks
in 6.2-7.4 s wall one after another, 4.2 s on two threads, a 2-core box shared with other
jobs). ``TREEINFER_BACKGROUND=off`` (as :mod:`treeinfer.runs.background`) keeps every call on
the caller's thread.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Sequence
from typing import Any

__all__ = ["enabled", "map_calls"]

_OFF = ("0", "off", "false", "no", "none")
_POOL = None
_LOCK = threading.Lock()


def enabled() -> bool:
    """False when ``TREEINFER_BACKGROUND`` is ``off`` (or 0, false, no, none)."""
    return os.environ.get("TREEINFER_BACKGROUND", "on").strip().lower() not in _OFF


def _workers() -> int:
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        cores = os.cpu_count() or 1
    return max(1, min(cores, 8))


def _pool():
    global _POOL
    with _LOCK:
        if _POOL is None:
            from concurrent.futures import ThreadPoolExecutor

            _POOL = ThreadPoolExecutor(_workers(), thread_name_prefix="treeinfer-calls")
        return _POOL


def map_calls(fn: Callable[[Any], Any], items: Sequence) -> list:
    """``[fn(x) for x in items]``, in order. The first call runs on the caller's thread (it
    traces and compiles what the rest then share: two threads never build one program at
    once); on a CPU with several cores the others are spread over a thread pool. ``fn`` must be
    safe to call from several threads at once once the first call returned (a compiled JAX
    program is); an exception of any call is raised here."""
    items = list(items)
    if not items:
        return []
    first = fn(items[0])
    if len(items) == 1 or not enabled() or _workers() < 2 or not _on_cpu():
        return [first, *(fn(x) for x in items[1:])]
    futures = [_pool().submit(fn, x) for x in items[1:]]
    return [first, *(f.result() for f in futures)]


def _on_cpu() -> bool:
    """Only the CPU backend runs one call per thread; a GPU's calls are queued asynchronously
    already."""
    import jax

    return jax.default_backend() == "cpu"
