"""``treeinfer batch --ray``: the items as Ray tasks, on a cluster or on a Ray started here.

Each Ray worker is an actor holding one :class:`~.cache.SimulatorCache` (as a local worker
process does: items of the same shapes reuse its compiled programs) and JAX's persistent compile
cache (shared by the workers of one machine; on a cluster, set ``TREEINFER_JAX_CACHE`` to a
shared folder). An item is one actor call asking for ``cpus_per_item`` CPUs or
``gpus_per_item`` GPUs. The manifest's paths and the batch folder must be visible at the same
paths on every node (a shared file system): the workers write the run folders, the driver
writes the table. A worker that dies fails only its item (run the batch again to resume it)
and is replaced.

Ray is optional (``pip install 'treeinfer[ray]'``); without it ``--ray`` fails at once with
that advice.
"""

from __future__ import annotations

import socket
import time
from collections.abc import Callable, Sequence

from ..errors import ConfigError
from .batch_item import Report, Task, failed_row, run_item
from .cache import SimulatorCache

CONNECT_TIMEOUT_S = 5.0  # a cluster address that does not answer within this fails at once


class ItemRunner:
    """The body of a Ray worker (an actor): one cache for every item it runs."""

    def __init__(self):
        import treeinfer

        treeinfer.configure_runtime()
        self.cache = SimulatorCache()

    def run(self, task: Task) -> dict:
        return run_item(task, self.cache)


def _import_ray():
    try:
        import ray
    except ImportError:
        raise ConfigError(
            "--ray: Ray is not installed; install it with `pip install 'treeinfer[ray]'` (or "
            "`pip install ray`), or leave --ray out to run on this machine"
        ) from None
    return ray


def check_reachable(address: str, timeout: float = CONNECT_TIMEOUT_S) -> None:
    """ConfigError at once for a ``HOST:PORT`` (or ``ray://HOST:PORT``) nothing answers on (Ray's
    own connect waits about a minute before it gives up). ``auto`` is left to Ray."""
    if address == "auto":
        return
    hostport = address.split("://", 1)[-1]
    host, sep, port = hostport.rpartition(":")
    if not sep or not port.isdigit():
        raise ConfigError(
            f"--ray {address}: expected 'local', 'auto' or a cluster address HOST:PORT (e.g. "
            "10.0.0.5:6379, or ray://10.0.0.5:10001 for Ray Client)"
        )
    try:
        with socket.create_connection((host, int(port)), timeout=timeout):
            pass
    except OSError as e:
        raise ConfigError(
            f"--ray {address}: cannot reach a Ray cluster there ({e.strerror or e}); start one "
            "with `ray start --head` on that machine, or use --ray local"
        ) from None


def run_on_ray(
    jobs: Sequence[tuple[int, Task]],
    report: Report,
    address: str,
    workers: int | None,
    cpus_per_item: int,
    gpus_per_item: float,
    log: Callable[[str], None],
) -> None:
    """The jobs as calls on ``workers`` Ray actors (None: as many as the cluster's CPUs (or
    GPUs) allow, at most one per job). ``address`` "local" starts a Ray cluster in this process
    with ``workers * cpus_per_item`` CPUs and stops it at the end."""
    ray = _import_ray()
    if cpus_per_item < 1 or gpus_per_item < 0:
        raise ConfigError("--cpus-per-item must be >= 1 and --gpus-per-item >= 0")
    if not jobs:
        return
    started_here = address == "local"
    if started_here:
        n = workers or 1
        ray.init(
            num_cpus=n * cpus_per_item,
            num_gpus=None if not gpus_per_item else max(1, int(n * gpus_per_item + 0.999)),
            include_dashboard=False,
            log_to_driver=False,
            configure_logging=False,
        )
    else:
        check_reachable(address)
        ray.init(address=address, log_to_driver=False, configure_logging=False)
    try:
        res = ray.cluster_resources()
        if workers is None:
            fit = int(res.get("CPU", 1) // cpus_per_item)
            if gpus_per_item:
                fit = min(fit, int(res.get("GPU", 0) // gpus_per_item))
            workers = max(1, fit)
        n = min(int(workers), len(jobs))
        log(f"Ray at {address}: {res.get('CPU', 0):g} CPUs, {res.get('GPU', 0):g} GPUs; "
            f"{n} workers of {cpus_per_item} CPU(s)"
            + (f" and {gpus_per_item:g} GPU(s)" if gpus_per_item else ""))  # fmt: skip
        actor = ray.remote(num_cpus=cpus_per_item, num_gpus=gpus_per_item, max_restarts=0)(
            ItemRunner
        )
        queue = list(jobs)[::-1]
        pending: dict = {}

        def submit(a) -> None:
            i, task = queue.pop()
            pending[a.run.remote(task)] = (a, i, task)

        for _ in range(n):
            if queue:
                submit(actor.remote())
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1, timeout=1.0)
            for ref in ready:
                a, i, task = pending.pop(ref)
                try:
                    row = ray.get(ref)
                except (ray.exceptions.RayActorError, ray.exceptions.WorkerCrashedError) as e:
                    why = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
                    row = failed_row(
                        task, f"Ray worker died ({why}); run the batch again to resume"
                    )
                    a = actor.remote()  # a fresh worker for the rest
                except ray.exceptions.RayError as e:
                    row = failed_row(task, f"Ray: {type(e).__name__}: {e}")
                report(i, row)
                if queue:
                    submit(a)
    except KeyboardInterrupt:
        for _, i, task in pending.values():
            report(i, failed_row(task, "interrupted; resumed next time", "interrupted"))
        raise
    finally:
        t = time.monotonic()
        ray.shutdown()  # a cluster started here stops; a remote one only loses this driver
        if started_here:
            log(f"stopped the local Ray cluster ({time.monotonic() - t:.1f} s)")
