"""One item of ``treeinfer batch`` (:mod:`.batch`): what to do with it given what its batch
folder holds (:func:`plan`), and running it in a worker (:func:`run_item`: a fresh, resumed or
summarised run folder through :func:`treeinfer.runs.run_inference`, its table row)."""

from __future__ import annotations

import contextlib
import os
import socket
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

from ..errors import TreeinferError
from ..io.atomic_write import atomic_write_json
from ..io.jsonio import read_json
from .batch_manifest import Item
from .cache import SimulatorCache
from .checkpoint import partial_dir
from .config import OPTION_FIELDS, RunConfig

RUNS, ITEMS, LOGS = "runs", "items", "logs"  # the batch folder's sub-folders
# options that do not change what a run computes (they are not compared with a run folder's)
_NOT_COMPARED = {"tree", "data", "out", "force", "prior_from", "model", "repair_inertia"}
Report = Callable[[int, dict], None]  # (index of the item, its row): how executors report


class Task(NamedTuple):
    """What a worker runs: ``mode`` fresh | resume | summarise; ``force``: a previous run folder
    or an unusable ``ID.partial`` of this item is moved aside."""

    item: Item
    mode: str
    out: str
    force: bool = False


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


# ---- the plan ------------------------------------------------------------------------------
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
            return (
                f"its option {k} is {getattr(then, k)!r}, the manifest (with this treeinfer's "
                f"defaults) gives {getattr(now, k)!r}"
            )
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
        # an interrupted run of other inputs or options (or any, with force: a checkpoint that
        # cannot be resumed any more) is moved aside, never deleted
        return ("resume", False) if why is None and not force else ("fresh", True)
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
    from ..sim.compile_stats import compile_stats
    from . import folder
    from .config import infer_config
    from .heldout import held_out_metrics
    from .inputs import load_run_inputs
    from .service import run_inference

    stats = compile_stats()
    mark = stats.mark()
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
        compiled = stats.since(mark)
        row.update(
            seconds_total=time.perf_counter() - t0,
            finished_utc=_utc(),
            xla_compiles=compiled["xla_compiles"],
            compile_seconds=compiled["compile_s"],
        )
        if row["status"] == "done":
            record = {"spec_hash": item.spec_hash(), "row": row}
            atomic_write_json(out / ITEMS / f"{item.id}.json", record)
        log(f"{row['status']} in {row['seconds_total']:.1f} s")
    return row


def failed_row(task: Task, error: str, status: str = "failed") -> dict:
    return {**base_row(task.item, Path(task.out)), "status": status, "error": error}
