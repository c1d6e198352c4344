"""``treeinfer batch``: infer many items of a manifest into one batch folder with one results
table (:mod:`treeinfer.runs.batch`)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from ..errors import ConfigError
from .common import (
    COMMAND_HELP,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_POOR_FIT,
    EXIT_USER_ERROR,
    _prepare_jax,
    _say,
    add_command_parser,
)

EXIT_PARTIAL = 5  # some items failed or were invalid; the others are in the table

_BATCH_EPILOG = """\
examples:
  treeinfer batch --manifest orchard.csv --out batch/          # this machine
  treeinfer batch --manifest orchard.csv --out batch/ --check  # only validate the manifest
  treeinfer batch --manifest orchard.yaml --out batch/ --ray local --workers 2
  treeinfer batch --manifest orchard.yaml --out batch/ --ray 10.0.0.5:6379 --cpus-per-item 4

manifest.csv (one row per item; paths relative to the manifest; empty cell = default):
  id,tree,recordings,test,grasp_fraction,particles
  b1,trees/t1.yaml,rec/b1/train,rec/b1/test,0.8,
  b2,trees/t1.yaml,rec/b2/train,,,32

manifest.yaml:
  defaults: {particles: 32}        # options for every item
  items:
    - {id: b1, tree: trees/t1.yaml, recordings: rec/b1/train, test: rec/b1/test}
    - {id: b2, tree: trees/t1.yaml, recordings: rec/b2/train, options: {seed: 3}}

Options an item may set: sampler, particles, iterations, seed, likelihood, init, backend,
model_kind, gradients, kT, noise_displacement, noise_force, noise_velocity, eta, prior_tail,
stop_when_converged, reinit_stragglers, max_unstable_share, checkpoint_every, force_interp,
max_sim_dt, sim_tolerance, shape_buckets (as `treeinfer infer`'s flags; the rest are infer's
defaults). The whole manifest is checked first; rows with a missing file, a duplicate id or a
bad option are listed and recorded as 'invalid' while the others run.

OUT/ holds runs/ID/ (the run folder `treeinfer infer` writes), results.csv and results.parquet
(pyarrow installed): per item its status and error, fit verdict, warnings, posterior mean and
95% interval per parameter, coverage of held-out pulls (test column) and timings. Run the same
command again to resume: finished items are skipped (their run folders verified), interrupted
ones continue from their checkpoint, failed ones run again.

exit codes: 0 every item done; 4 every item done but some fit poorly (--allow-poor-fit: 0);
5 some items failed or were invalid (the others are done); 2 a manifest that cannot be used;
130 interrupted (run again to resume).
"""


def configure_batch(subparsers) -> argparse.ArgumentParser:
    p = add_command_parser(
        subparsers,
        "batch",
        help=COMMAND_HELP["batch"],
        description="Infer the posterior of every item (a tree and its recordings) of a CSV or "
        "YAML manifest: one run folder per item, as `treeinfer infer` writes it, and one results "
        "table. Items run in worker processes of this machine (or as Ray tasks with --ray), "
        "failures stay with their item, and running the command again resumes.",
        epilog=_BATCH_EPILOG,
    )
    p.add_argument("--manifest", required=True, type=Path, metavar="FILE",
                   help="items to infer: a .csv or .yaml manifest (see below)")  # fmt: skip
    p.add_argument("--out", required=True, type=Path, metavar="DIR",
                   help="batch folder: new, empty, or an earlier batch's (resumed)")  # fmt: skip
    p.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="items at a time: worker processes on this machine (1: in this process; default: "
        "one per two CPU cores, at most one per item; 1 with a GPU) or Ray workers with --ray "
        "(default: as many as the cluster's CPUs allow)",
    )
    p.add_argument(
        "--ray",
        metavar="ADDRESS",
        help="run the items as Ray tasks: 'local' starts a Ray cluster here, HOST:PORT or "
        "'auto' joins a running one (paths must be the same on every node); needs `pip install "
        "'treeinfer[ray]'`",
    )
    p.add_argument("--cpus-per-item", type=int, default=1, metavar="N",
                   help="with --ray: CPU cores one item asks for")  # fmt: skip
    p.add_argument("--gpus-per-item", type=float, default=0.0, metavar="G",
                   help="with --ray: GPUs one item asks for (1: a GPU each; 0: none)")  # fmt: skip
    p.add_argument(
        "--force",
        action="store_true",
        help="replace the run folders of items made from other inputs or options (the old "
        "folder is kept as ID.old-<time>) and run them again; finished items that match are "
        "always skipped",
    )
    p.add_argument("--check", action="store_true",
                   help="validate the manifest (every row) and exit: 0 valid, 2 not")  # fmt: skip
    p.add_argument("--allow-poor-fit", action="store_true",
                   help="exit 0 even if some items' fit checks judge a poor fit")  # fmt: skip
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def run_batch(args: argparse.Namespace) -> int:
    from ..runs.batch import run_batch as batch
    from ..runs.batch_manifest import read_manifest

    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers: must be an integer >= 1, got {args.workers}")
    if args.cpus_per_item < 1:
        raise ConfigError(f"--cpus-per-item: must be an integer >= 1, got {args.cpus_per_item}")
    if not (math.isfinite(args.gpus_per_item) and args.gpus_per_item >= 0):
        raise ConfigError(f"--gpus-per-item: must be >= 0, got {args.gpus_per_item:g}")
    if args.ray is None and (args.cpus_per_item != 1 or args.gpus_per_item):
        raise ConfigError("--cpus-per-item/--gpus-per-item: only with --ray")
    if args.ray is not None and not args.check:
        from ..runs.batch_ray import _import_ray

        _import_ray()  # clear errors before anything is read
        if args.ray != "local":
            from ..runs.batch_ray import check_reachable

            check_reachable(args.ray)
    items = read_manifest(args.manifest)
    bad = [it for it in items if it.error is not None]
    for it in bad:
        _say(f"invalid item: {it.error}")
    if args.check:
        print(f"{args.manifest}: {len(items) - len(bad)} of {len(items)} items valid")
        return EXIT_USER_ERROR if bad else EXIT_OK
    _prepare_jax()
    result = batch(
        items,
        args.out,
        workers=args.workers,
        ray=args.ray,
        cpus_per_item=args.cpus_per_item,
        gpus_per_item=args.gpus_per_item,
        force=args.force,
        progress=not args.no_progress,
        manifest=str(args.manifest),
        log=_say,
    )
    rows = result.rows
    ran = [r for r in rows if r["status"] in ("done", "failed") and not r.get("reused")]
    ran = [r for r in ran if r.get("seconds_total") is not None]
    rate = f"; {60 * len(ran) / result.seconds:.1f} items/min" if ran and result.seconds else ""
    counts = ", ".join(f"{v} {k}" for k, v in sorted(result.counts.items()))
    print(f"{len(rows)} items in {result.seconds:.1f} s{rate}: {counts}")
    for r in rows:
        if r["status"] in ("failed", "invalid"):
            print(f"  {r['id'] or '(no id)'} {r['status']}: {r['error']}")
    tables = ", ".join(w for w in result.written if not w.startswith("("))
    notes = " ".join(w for w in result.written if w.startswith("("))
    print(f"wrote {args.out}/ (runs/, {tables}) {notes}".rstrip())
    if result.interrupted:
        _say(f"interrupted; run the same command again to resume ({args.out}/runs/ID.partial)")
        return EXIT_INTERRUPTED
    if any(r["status"] in ("failed", "invalid", "pending") for r in rows):
        return EXIT_PARTIAL
    if any(r.get("fit_verdict") == "poor_fit" for r in rows) and not args.allow_poor_fit:
        _say("some items fit poorly (fit_verdict poor_fit in the table); exit code 4")
        return EXIT_POOR_FIT
    return EXIT_OK
