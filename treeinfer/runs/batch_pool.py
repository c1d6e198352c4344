"""Where the items of ``treeinfer batch`` run on this machine: in this process
(:func:`run_here`) or in worker processes (:func:`run_pool`), each with one
:class:`~.cache.SimulatorCache` for all its items."""

from __future__ import annotations

import contextlib
import os
import queue
import signal
import time
from collections.abc import Sequence

from .batch_item import Report, Task, failed_row, run_item
from .cache import SimulatorCache

STOP_GRACE_S = 2.0  # s a worker gets to stop by itself after Ctrl-C before it is signalled


def run_here(jobs: Sequence[tuple[int, Task]], report: Report) -> None:
    """Every job in this process, one after another, with one cache."""
    cache = SimulatorCache()
    for i, task in jobs:
        try:
            row = run_item(task, cache)
        except KeyboardInterrupt:
            report(i, failed_row(task, "interrupted (Ctrl-C); resumed next time", "interrupted"))
            raise
        report(i, row)


def _pool_worker(tasks, results) -> None:
    """A worker process of :func:`run_pool`: items from ``tasks`` until None, one cache."""
    from ..io import interrupt

    interrupt.install()  # Ctrl-C in compiled code still ends it, its staging folders removed
    import treeinfer

    treeinfer.configure_runtime()
    cache = SimulatorCache()
    pid = os.getpid()
    i = None
    try:
        while True:
            job = tasks.get()
            if job is None:
                return
            i, task = job
            results.put(("start", i, pid, None))
            row = run_item(task, cache)
            results.put(("done", i, pid, row))
            i = None
    except KeyboardInterrupt:  # the terminal's Ctrl-C reaches every worker: stop quietly
        if i is not None:
            results.put(("interrupted", i, pid, None))


def _exit_text(code: int | None) -> str:
    if code is not None and code < 0:
        with contextlib.suppress(ValueError):
            return f"killed by signal {signal.Signals(-code).name}"
    return f"exit code {code}"


def run_pool(jobs: Sequence[tuple[int, Task]], workers: int, report: Report) -> None:
    """The jobs in ``workers`` processes of this machine.

    Why not ``concurrent.futures.ProcessPoolExecutor``: its workers keep nothing between tasks
    except through module globals (which this package does not keep), so each item would build
    its simulators and programs anew; and a worker that dies breaks the whole pool. Here each
    worker loops over a shared queue with one cache, says which item it starts, and a worker that
    dies (killed, out of memory) fails only the item it was running and is replaced."""
    import multiprocessing as mp

    ctx = mp.get_context("spawn")  # JAX's threads make fork unsafe
    tasks, results = ctx.Queue(), ctx.Queue()
    for job in jobs:
        tasks.put(job)
    n = min(workers, len(jobs))
    for _ in range(n):
        tasks.put(None)
    by_index = dict(jobs)
    procs: dict[int, object] = {}

    def start() -> None:
        p = ctx.Process(target=_pool_worker, args=(tasks, results), daemon=True)
        p.start()
        procs[p.pid] = p

    for _ in range(n):
        start()
    running: dict[int, int] = {}  # pid -> index
    done: set[int] = set()
    left = len(jobs)
    spare = 2 * n  # replacements for workers that die (not forever, if they die at start)
    try:
        while left:
            try:
                kind, i, pid, row = results.get(timeout=0.5)
            except queue.Empty:
                for pid, p in list(procs.items()):
                    if p.is_alive():
                        continue
                    del procs[pid]
                    if pid in running:
                        j = running.pop(pid)
                        left -= 1
                        done.add(j)
                        why = f"worker process {pid} died ({_exit_text(p.exitcode)})"
                        report(j, failed_row(by_index[j], f"{why}; run the batch again to resume"))
                    # one that died (not one that took its sentinel) is replaced while items wait
                    if p.exitcode != 0 and left > len(running) and spare > 0:
                        spare -= 1
                        start()
                if not procs and left:  # an item whose start was never heard of, or no spare
                    for j, task in jobs:
                        if j not in done:
                            why = "its worker process died before it reported; run again"
                            report(j, failed_row(task, why))
                    return
                continue
            if kind == "start":
                running[pid] = i
                continue
            running.pop(pid, None)
            if kind == "interrupted":
                report(i, failed_row(by_index[i], "interrupted (Ctrl-C)", "interrupted"))
                raise KeyboardInterrupt
            left -= 1
            done.add(i)
            report(i, row)
    except BaseException:
        _stop_pool(tasks, results, procs, running, by_index, report)
        raise
    finally:
        for p in procs.values():
            p.join(timeout=5)
        for q in (tasks, results):
            q.cancel_join_thread()
            q.close()


def _stop_pool(tasks, results, procs, running, by_index, report: Report) -> None:
    """Stop the workers (Ctrl-C, or an error here): no new items; each gets STOP_GRACE_S to
    finish or stop by itself (a terminal's Ctrl-C reached them too), then SIGINT (the run keeps
    its checkpoint, its staging folder is removed), then SIGTERM. Within the command line's
    Ctrl-C grace (:data:`treeinfer.io.interrupt.GRACE_S`)."""
    with contextlib.suppress(Exception):
        while True:
            tasks.get_nowait()
    for _ in procs:
        with contextlib.suppress(Exception):
            tasks.put(None)

    def drain(until: float) -> None:
        while time.monotonic() < until and any(p.is_alive() for p in procs.values()):
            try:
                kind, i, pid, row = results.get(timeout=0.1)
            except (queue.Empty, OSError, EOFError, ValueError):
                continue
            if kind == "start":
                running[pid] = i
            elif kind in ("done", "interrupted"):
                running.pop(pid, None)
                if kind == "done":
                    report(i, row)

    drain(time.monotonic() + STOP_GRACE_S)
    for sig in (signal.SIGINT, signal.SIGTERM):
        alive = [p for p in procs.values() if p.is_alive()]
        if not alive:
            break
        for p in alive:
            with contextlib.suppress(OSError):
                os.kill(p.pid, sig)
        drain(time.monotonic() + 1.0)
    for p in procs.values():
        if p.is_alive():
            p.kill()
    for i in running.values():
        report(i, failed_row(by_index[i], "interrupted; resumed next time", "interrupted"))
