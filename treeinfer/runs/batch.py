"""``treeinfer batch``: many items (a tree and its recordings each) in one job, one run folder
per item (written by :func:`treeinfer.runs.run_inference`, as ``treeinfer infer`` writes it) and
one results table (:mod:`.batch_table`).

The batch folder ``OUT/``::

    batch.json          the manifest (path, sha256), the settings and treeinfer's versions
    results.csv         one row per manifest item (and results.parquet with pyarrow)
    runs/ID/            the item's run folder; runs/ID.partial/ while it is interrupted
    items/ID.json       the finished item's row and the hash of its inputs and options
    logs/ID.log         what the item's run said, with times and the worker

Resume: an item whose run folder is complete, verifies against its ``manifest.json``
(:func:`treeinfer.runs.integrity.verify_run`) and was made from the manifest's inputs and
options, and whose ``items/ID.json`` has the same hash, is skipped (``reused`` in the table);
one with a verified run folder but no row (killed after publishing) is only summarised; one
with ``runs/ID.partial`` continues from its checkpoint (:func:`run_inference`'s ``resume``);
everything else runs afresh. A run folder made from other inputs or options is never
replaced silently: the item fails with the reason unless ``force`` (then the old folder is moved
aside to ``ID.old-<time>``, as ``infer --force`` does).

Where items run (:func:`run_batch`): in this process (``workers=1``), in ``workers`` processes
of this machine (:mod:`.batch_pool`), or as Ray tasks (:mod:`.batch_ray`). Each worker keeps one
:class:`~.cache.SimulatorCache` for all its items, and every worker shares JAX's persistent
compile cache (:func:`treeinfer.configure_runtime`), so items of the same shapes reuse compiled
programs. A run folder appears complete or not at all (:mod:`treeinfer.io.atomic`), so an
interrupted or killed worker leaves at most ``runs/ID.partial`` (resumed next time).
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import NamedTuple

from ..errors import OutputExistsError
from ..io.atomic import mark_output_dir
from ..io.atomic_write import atomic_write_json
from ..io.ownership import refuse_overlap, refuse_unmovable
from ..io.provenance import file_sha256, versions
from .batch_item import ITEMS, LOGS, RUNS, Task, base_row, plan
from .batch_manifest import Item
from .batch_table import write_table

BATCH_FILE = "batch.json"
LOCK_FILE = ".batch.lock"
TABLE_EVERY_S = 5.0  # s between rewrites of the results table while items finish


class BatchResult(NamedTuple):
    """What :func:`run_batch` did: the table's rows (manifest order), counts by status (and fit
    verdict), its wall time in s, the table files written, whether Ctrl-C stopped it."""

    rows: list[dict]
    counts: dict
    seconds: float
    written: list[str]
    interrupted: bool


# ---- the batch folder ----------------------------------------------------------------------
def check_out(out: Path, items: Sequence[Item], manifest: str | None) -> None:
    """Refuse a batch folder that must not be written (before any work): one of the items'
    inputs or inside one, or a non-empty folder that no batch wrote (no ``batch.json``)."""
    out = Path(out)
    inputs = [p for it in items for p in (it.tree, it.recordings, it.test) if p]
    refuse_overlap(out, inputs + ([manifest] if manifest else []), "batch folder")
    if out.exists() and not out.is_dir():
        raise OutputExistsError(f"{out}: the batch folder exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not (out / BATCH_FILE).is_file():
        refuse_unmovable(out, "batch folder")
        raise OutputExistsError(
            f"{out}: holds files but no {BATCH_FILE}: not a batch folder; choose another --out "
            "(a batch folder is resumed by running the same command again)"
        )


def prepare_out(out: Path, items: Sequence[Item], manifest: str | None, settings: dict) -> None:
    """Create the batch folder's parts and record this run in ``batch.json``."""
    for sub in (RUNS, ITEMS, LOGS):
        (out / sub).mkdir(parents=True, exist_ok=True)
    mark_output_dir(out)
    record = {
        "command": "batch",
        "manifest": None if manifest is None else str(Path(manifest).resolve()),
        "manifest_sha256": None if manifest is None else file_sha256(manifest),
        "settings": settings,
        "n_items": len(items),
        "versions": versions(),
        "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    atomic_write_json(out / BATCH_FILE, record)


def default_workers(n_items: int) -> int:
    """Worker processes when ``--workers`` is not given: 1 (this process) where JAX would use
    an NVIDIA GPU (one process owns it; items are not batched on it yet), else one per two
    usable cores (an item's XLA programs use more than one thread while they compile and run;
    on the shared 2-core box a second worker was slower, BENCHMARKS.md), at most one per item."""
    import glob

    platforms = os.environ.get("JAX_PLATFORMS", "").lower()
    if "cpu" != platforms and glob.glob("/dev/nvidia[0-9]*"):
        return 1
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cores = os.cpu_count() or 1
    return max(1, min(n_items, cores // 2))


def run_batch(
    items: Sequence[Item],
    out: str | os.PathLike,
    *,
    workers: int | None = None,
    ray: str | None = None,
    cpus_per_item: int = 1,
    gpus_per_item: float = 0.0,
    force: bool = False,
    progress: bool = True,
    manifest: str | None = None,
    log: Callable[[str], None] = lambda msg: None,
) -> BatchResult:
    """Run every valid item of a manifest (:func:`.batch_manifest.read_manifest`) into the
    batch folder ``out`` and write the results table; see the module docstring.

    Args:
      workers: processes on this machine (1: in this process; None: :func:`default_workers`),
        or with ``ray`` the number of Ray workers (None: as many as the cluster's resources allow).
      ray: None (this machine), "local" (start a Ray cluster here) or a cluster's address.
      cpus_per_item, gpus_per_item: the Ray resources of one item.
      force: run again items whose run folder was made from other inputs or options.
      progress: a tqdm bar over the items. log: one-line messages (stderr in the CLI).

    Returns the rows (manifest order), the counts by status and fit verdict, the wall time,
    the table files written, and whether it was interrupted (Ctrl-C; the table is written
    anyway and the next run resumes).
    """
    t0 = time.perf_counter()
    out = Path(out)
    settings = {"workers": workers, "ray": ray, "cpus_per_item": cpus_per_item,
                "gpus_per_item": gpus_per_item, "force": bool(force)}  # fmt: skip
    check_out(out, items, manifest)
    out.mkdir(parents=True, exist_ok=True)
    with _lock(out):
        prepare_out(out, items, manifest, settings)
        return _run_locked(items, out, workers, ray, cpus_per_item, gpus_per_item, force,
                           progress, log, t0)  # fmt: skip


@contextlib.contextmanager
def _lock(out: Path):
    """One batch process per batch folder at a time (two would run the same items)."""
    import fcntl

    with open(out / LOCK_FILE, "a+") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            f.seek(0)
            raise OutputExistsError(
                f"{out}: another treeinfer batch is running on this folder ({f.read().strip()}); "
                "wait for it, or give another --out"
            ) from None
        f.truncate(0)
        f.write(f"pid {os.getpid()}\n")
        f.flush()
        yield


def _run_locked(items, out, workers, ray, cpus_per_item, gpus_per_item, force, progress, log, t0):
    from tqdm.auto import tqdm

    rows = [base_row(it, out) for it in items]
    jobs: list[tuple[int, Task]] = []
    for i, it in enumerate(items):
        mode, extra = plan(it, out, force)
        if mode == "invalid":
            rows[i]["status"] = "invalid"
        elif mode == "failed":
            rows[i].update(status="failed", error=extra)
        elif mode == "skip":  # where the manifest says things are now (same contents)
            here = {k: rows[i][k] for k in ("tree", "recordings", "test", "manifest_line")}
            rows[i] = {**extra, **here, "reused": True}
        else:
            jobs.append((i, Task(it, mode, str(out), bool(extra))))
    # items of the same shapes one after another: a worker's cache serves the next one
    jobs.sort(key=lambda j: (j[1].item.group, j[0]))
    n_skip = sum(r["reused"] for r in rows)
    n_bad = sum(r["status"] in ("invalid", "failed") for r in rows)
    n_resume = sum(t.mode == "resume" for _, t in jobs)
    log(
        f"{len(items)} items: {n_skip} finished before (skipped), {len(jobs)} to run"
        + (f" ({n_resume} resumed from their checkpoint)" if n_resume else "")
        + (f", {n_bad} not runnable (see the table's error column)" if n_bad else "")
    )
    last_write = [time.monotonic()]
    bar = tqdm(total=len(jobs), unit="item", disable=not progress or not jobs, dynamic_ncols=True)

    def report(i: int, row: dict) -> None:
        rows[i] = row
        if row["status"] != "interrupted":
            bar.update(1)
        bad = sum(r["status"] in ("failed", "invalid") for r in rows)
        bar.set_postfix(failed=bad, refresh=False)
        if time.monotonic() - last_write[0] > TABLE_EVERY_S:  # a current table while it runs
            write_table(out, rows)
            last_write[0] = time.monotonic()

    interrupted = False
    try:
        if ray is not None:
            from .batch_ray import run_on_ray

            run_on_ray(jobs, report, ray, workers, cpus_per_item, gpus_per_item, log)
        elif jobs:
            from .batch_pool import run_here, run_pool

            n = default_workers(len(jobs)) if workers is None else int(workers)
            log(f"running {len(jobs)} items in {'this process' if n <= 1 else f'{n} workers'}")
            (run_here(jobs, report) if n <= 1 else run_pool(jobs, n, report))
    except KeyboardInterrupt:
        interrupted = True
    finally:
        bar.close()
        written = write_table(out, rows)
    counts: dict[str, int] = {}
    for r in rows:
        key = r["status"] if r["status"] != "done" else f"done ({r.get('fit_verdict')})"
        counts[key] = counts.get(key, 0) + 1
    return BatchResult(rows, counts, time.perf_counter() - t0, written, interrupted)
