"""Work a command runs on a second thread while its main thread goes on: compiling a program
the run will need later (:func:`prefetch`) and drawing the run's figures
(:mod:`treeinfer.runs.figures`).

Why: on a 2-core CPU a cold ``treeinfer infer`` is mostly XLA compiles and rollouts, and both
run on one core (a compile is single-threaded; the rollout program is a loop of scalar steps).
JAX releases Python's lock while XLA compiles and runs, so a program compiled (or a figure
drawn) on a second thread uses the core the main thread leaves idle, and the results are the
same programs and the same numbers as before, only sooner. ``TREEINFER_BACKGROUND=off`` runs
everything on the main thread, in the old order (comparisons, debugging).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

__all__ = ["Job", "enabled", "prefetch"]


def enabled() -> bool:
    """False when ``TREEINFER_BACKGROUND`` is ``off`` (or 0, false, no): the switch of
    :mod:`treeinfer.sim.threads` too."""
    from ..sim.threads import enabled as on

    return on()


class Job:
    """``fn()`` on a second thread, started at once; :meth:`result` waits for it and returns its
    value or raises its exception on the caller's thread. With the background off
    (:func:`enabled`) ``fn`` runs in :meth:`result`, on the caller's thread, when first asked."""

    def __init__(self, fn: Callable[[], Any], name: str = "treeinfer-background"):
        self._fn = fn
        self._value: Any = None
        self._error: BaseException | None = None
        self._done = False
        self._thread = None
        if enabled():
            # not a daemon: the interpreter waits for it at exit. A daemon thread still inside
            # XLA when the main thread ends (an error, exit 2) aborts the process (SIGABRT
            # from XLA's runtime teardown) instead of exiting with the command's code
            self._thread = threading.Thread(target=self._run, name=name, daemon=False)
            self._thread.start()

    def _run(self) -> None:
        try:
            self._value = self._fn()
        except BaseException as e:  # noqa: BLE001 -- handed to the caller by result()
            self._error = e
        self._done = True

    def done(self) -> bool:
        return self._done

    def result(self) -> Any:
        if self._thread is not None:
            self._thread.join()
        elif not self._done:
            self._run()
        if self._error is not None:
            raise self._error
        return self._value


class _Prefetch:
    """A :class:`Job` whose result nobody needs (it fills a cache), or nothing when the
    background is off; :meth:`wait` never raises (the work is done again, and any error met
    again, where it is needed)."""

    def __init__(self, fn: Callable[[], Any], name: str):
        self._job = Job(fn, name) if enabled() else None

    def wait(self) -> None:
        job, self._job = self._job, None
        if job is not None:
            try:
                job.result()
            except Exception:  # noqa: BLE001, S110 -- a cache left unfilled: see the docstring
                pass


def prefetch(fn: Callable[[], Any], name: str = "treeinfer-prefetch") -> _Prefetch:
    """Start ``fn()`` (it compiles, and fills a cache, what the main thread will ask for
    later) on a second thread; call ``.wait()`` on the result before the main thread asks, so
    that the two never trace or compile the same program at once."""
    return _Prefetch(fn, name)
