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
of this machine (:func:`_run_pool`), or as Ray tasks (:mod:`.batch_ray`). Each worker keeps one
:class:`~.cache.SimulatorCache` for all its items, and every worker shares JAX's persistent
compile cache (:func:`treeinfer.configure_runtime`), so items of the same shapes reuse compiled
programs. A run folder appears complete or not at all (:mod:`treeinfer.io.atomic`), so an
interrupted or killed worker leaves at most ``runs/ID.partial`` (resumed next time).
"""

from __future__ import annotations

import contextlib
import os
import queue
import signal
import socket
import time
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import NamedTuple

from ..errors import OutputExistsError, TreeinferError
from ..io.atomic import mark_output_dir
from ..io.atomic_write import atomic_write_json
from ..io.jsonio import read_json
from ..io.ownership import refuse_overlap, refuse_unmovable
from ..io.provenance import file_sha256, versions
from .batch_manifest import Item
from .batch_table import write_table
from .cache import SimulatorCache
from .checkpoint import partial_dir
from .config import OPTION_FIELDS, RunConfig

BATCH_FILE = "batch.json"
RUNS, ITEMS, LOGS = "runs", "items", "logs"
STOP_GRACE_S = 2.0  # s a worker gets to stop by itself after Ctrl-C before it is signalled
TABLE_EVERY_S = 5.0  # s between rewrites of the results table while items finish
# options that do not change what a run computes (they are not compared with a run folder's)
_NOT_COMPARED = {"tree", "data", "out", "force", "prior_from", "model", "repair_inertia"}


class Task(NamedTuple):
    """What a worker runs: ``mode`` fresh | resume | summarise; ``force``: a previous run folder
    or an unusable ``ID.partial`` of this item is moved aside."""

    item: Item
    mode: str
    out: str
    force: bool = False


class BatchResult(NamedTuple):
    rows: list[dict]
    counts: dict
    seconds: float
    written: list[str]
    interrupted: bool


def _utc() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def base_row(item: Item, out: Path) -> dict:
    return {
        "id": item.id,
        "status": "pending",
        "run_dir": f"{RUNS}/{item.id}" if item.id else None,  # in the batch folder
        "tree": item.tree,
        "recordings": item.recordings,
        "test": item.test,
        "manifest_line": item.line,
        "reused": False,
        "error": item.error,
    }


# ---- the batch folder and the plan -----------------------------------------------------------
def prepare_out(out: Path, items: Sequence[Item], manifest: str | None, settings: dict) -> None:
    """Check and create the batch folder (before any work): a new or empty folder, or one a
    batch wrote (its ``batch.json``); never one of the items' inputs nor inside one."""
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
        "started_utc": _utc(),
    }
    atomic_write_json(out / BATCH_FILE, record)


def mismatch(config: dict, item: Item) -> str | None:
    """Why the run of ``config`` (a run's config.json) was not made from ``item``'s inputs and
    options (None: it was)."""
    if (config.get("tree") or {}).get("sha256") != item.digests.get("tree"):
        return "its tree file differs from the manifest's (sha256)"
    files = {f.get("name"): f.get("sha256") for f in (config.get("data") or {}).get("files", [])}
    if files != item.digests.get("recordings"):
        return "its recordings differ from the manifest's (sha256 of the CSVs)"
    then = RunConfig.from_json(config)
    now = RunConfig(
        tree="", data="", out="", grasp_fraction=item.grasp_fraction, **item.run_options()
    )
    for k in OPTION_FIELDS:
        if k not in _NOT_COMPARED and getattr(then, k) != getattr(now, k):
            return f"its option {k} is {getattr(then, k)!r}, the manifest gives {getattr(now, k)!r}"
    return None


def plan(item: Item, out: Path, force: bool) -> tuple[str, object]:
    """What to do with ``item`` in the batch folder ``out``: ("invalid", None), ("failed",
    error), ("skip", its earlier row), ("summarise" | "resume" | "fresh", force flag)."""
    from .integrity import check_partial, verify_run

    if item.error is not None:
        return "invalid", None
    run_dir = Path(out) / RUNS / item.id
    if run_dir.exists() or run_dir.is_symlink():
        try:
            config = read_json(run_dir / "config.json", "the item's run config")
            verify_run(run_dir, config)
            why = mismatch(config, item)
        except (TreeinferError, OSError, ValueError, TypeError) as e:
            why = f"not a usable run folder ({e})"
        if why is None:
            rec_path = Path(out) / ITEMS / f"{item.id}.json"
            with contextlib.suppress(TreeinferError, OSError, ValueError):
                rec = read_json(rec_path, "the item's row")
                if rec.get("spec_hash") == item.spec_hash() and isinstance(rec.get("row"), dict):
                    return "skip", rec["row"]
            return "summarise", False
        if not force:
            return "failed", (
                f"{run_dir}: {why}; pass --force to run the item again (the old folder is then "
                f"kept as {item.id}.old-<time>)"
            )
        return "fresh", True
    partial = partial_dir(run_dir)
    if partial.is_dir():
        why = check_partial(partial)
        if why is None:
            try:
                why = mismatch(read_json(partial / "config.json", "run config"), item)
            except (TreeinferError, ValueError, TypeError) as e:
                why = str(e)
        # an interrupted run of other inputs or options is moved aside (never deleted)
        return ("resume", False) if why is None else ("fresh", True)
    return "fresh", False


# ---- one item, in its worker -----------------------------------------------------------------
def summary_columns(summary: dict) -> dict:
    """The table's columns from a run's summary.json: verdict, warnings, posterior table."""
    fit = summary.get("fit") or {}
    warns = [str(w) for w in summary.get("convergence_warnings") or []]
    warns += [str(r) for r in fit.get("reasons") or []]
    warns += [str(f) for f in summary.get("data_checks") or []]
    row = {
        "fit_verdict": fit.get("status", summary.get("status")),
        "n_warnings": len(warns),
        "warnings": " | ".join(warns) or None,
    }
    for label, s in (summary.get("posterior") or {}).items():
        for stat in ("mean", "lower", "upper"):
            v = s.get(stat)
            row[f"{label}_{stat}"] = None if v is None else float(v)
    return row


def run_item(task: Task, cache: SimulatorCache) -> dict:
    """Run one item (fresh, resumed or only summarised) and return its table row; the row of a
    finished item is also written to ``items/ID.json``. Errors become a ``failed`` row (the
    traceback of an internal one goes to ``logs/ID.log``); KeyboardInterrupt propagates (the
    run keeps ``runs/ID.partial`` for the next time)."""
    from . import folder
    from .config import infer_config
    from .heldout import held_out_metrics
    from .inputs import load_run_inputs
    from .service import run_inference

    item, out = task.item, Path(task.out)
    run_dir = out / RUNS / item.id
    row = base_row(item, out)
    t0 = time.perf_counter()
    row.update(started_utc=_utc(), worker=f"{socket.gethostname()}:{os.getpid()}")
    with open(out / LOGS / f"{item.id}.log", "a", encoding="utf-8") as logf:

        def log(msg: str) -> None:
            logf.write(f"{_utc()} {msg}\n")
            logf.flush()

        log(f"item {item.id} ({task.mode}) in worker {row['worker']}")
        try:
            t = time.perf_counter()
            if task.mode == "resume":
                summary = run_inference(
                    resume=run_dir, progress=False, log=log, cache=cache
                ).summary
            elif task.mode == "fresh":
                o = item.run_options()
                inputs = load_run_inputs(
                    item.tree,
                    item.recordings,
                    None,
                    None,
                    o["model_kind"],
                    o["tie"],
                    o["tie_scale"],
                )
                config = infer_config(
                    item.tree,
                    item.recordings,
                    run_dir,
                    force=task.force,
                    inputs=inputs,
                    grasp_fraction=item.grasp_fraction,
                    **o,
                )
                outcome = run_inference(config, progress=False, log=log, cache=cache, inputs=inputs)
                summary = outcome.summary
            else:
                summary = read_json(run_dir / "summary.json", "the item's summary")
            row["seconds_infer"] = time.perf_counter() - t
            row.update(summary_columns(summary))
            if item.test is not None:
                t = time.perf_counter()
                m = held_out_metrics(folder.load_run(run_dir, cache), item.test)
                row.update(
                    test_coverage_pct=100.0 - float(m["pct_outside"]),
                    test_band_width_mm=1000.0 * float(m["ci_width"]),
                    test_nll_per_point=float(m["predictive_nll_per_point"]),
                    n_test_points=int(m["n_points"]),
                    seconds_test=time.perf_counter() - t,
                )
            row["status"] = "done"
        except TreeinferError as e:
            row.update(status="failed", error=str(e))
            log(f"failed: {e}")
        except Exception as e:  # noqa: BLE001 -- a bug in one item must not end the batch
            row.update(status="failed", error=f"internal error ({type(e).__name__}: {e})")
            log("failed with an internal error:\n" + traceback.format_exc())
        row.update(seconds_total=time.perf_counter() - t0, finished_utc=_utc())
        if row["status"] == "done":
            record = {"spec_hash": item.spec_hash(), "row": row}
            atomic_write_json(out / ITEMS / f"{item.id}.json", record)
        log(f"{row['status']} in {row['seconds_total']:.1f} s")
    return row


def failed_row(task: Task, error: str, status: str = "failed") -> dict:
    return {**base_row(task.item, Path(task.out)), "status": status, "error": error}


# ---- executors -------------------------------------------------------------------------------
Report = Callable[[int, dict], None]  # (index of the item, its row)


def _run_here(jobs: Sequence[tuple[int, Task]], report: Report) -> None:
    """Every job in this process, one after another, with one cache."""
    cache = SimulatorCache()
    for i, task in jobs:
        try:
            report(i, run_item(task, cache))
        except KeyboardInterrupt:
            report(i, failed_row(task, "interrupted (Ctrl-C); resumed next time", "interrupted"))
            raise


def _pool_worker(tasks, results) -> None:
    """A worker process of :func:`_run_pool`: items from ``tasks`` until None, one cache."""
    from ..io import interrupt

    interrupt.install()  # Ctrl-C in compiled code still ends it, its staging folders removed
    import treeinfer

    treeinfer.configure_runtime()
    cache = SimulatorCache()
    pid = os.getpid()
    while True:
        job = tasks.get()
        if job is None:
            return
        i, task = job
        results.put(("start", i, pid, None))
        try:
            row = run_item(task, cache)
        except KeyboardInterrupt:
            results.put(("interrupted", i, pid, None))
            return
        results.put(("done", i, pid, row))


def _exit_text(code: int | None) -> str:
    if code is not None and code < 0:
        with contextlib.suppress(ValueError):
            return f"killed by signal {signal.Signals(-code).name}"
    return f"exit code {code}"


def _run_pool(jobs: Sequence[tuple[int, Task]], workers: int, report: Report) -> None:
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
    left = len(jobs)
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
                        why = f"worker process {pid} died ({_exit_text(p.exitcode)})"
                        report(j, failed_row(by_index[j], f"{why}; run the batch again to resume"))
                        if left > len(running):
                            start()  # the dead worker's sentinel is still queued
                if not procs and left:
                    raise RuntimeError("every batch worker process exited early")
                continue
            if kind == "start":
                running[pid] = i
                continue
            running.pop(pid, None)
            if kind == "interrupted":
                report(i, failed_row(by_index[i], "interrupted (Ctrl-C)", "interrupted"))
                raise KeyboardInterrupt
            left -= 1
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


# ---- the batch -------------------------------------------------------------------------------
def default_workers(n_items: int) -> int:
    """Worker processes when ``--workers`` is not given: one per two usable cores (an item's
    XLA programs use more than one thread while they compile and run), at most one per item."""
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
    from tqdm.auto import tqdm

    t0 = time.perf_counter()
    out = Path(out)
    settings = {"workers": workers, "ray": ray, "cpus_per_item": cpus_per_item,
                "gpus_per_item": gpus_per_item, "force": bool(force)}  # fmt: skip
    prepare_out(out, items, manifest, settings)
    rows = [base_row(it, out) for it in items]
    jobs: list[tuple[int, Task]] = []
    for i, it in enumerate(items):
        mode, extra = plan(it, out, force)
        if mode == "invalid":
            rows[i]["status"] = "invalid"
        elif mode == "failed":
            rows[i].update(status="failed", error=extra)
        elif mode == "skip":
            rows[i] = {**extra, "reused": True}
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
            n = default_workers(len(jobs)) if workers is None else int(workers)
            log(f"running {len(jobs)} items in {'this process' if n <= 1 else f'{n} workers'}")
            (_run_here(jobs, report) if n <= 1 else _run_pool(jobs, n, report))
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
