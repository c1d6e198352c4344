"""Items per minute of ``treeinfer batch`` with 1, 2 and 4 worker processes (as many as the
machine's cores allow), and optionally on a local Ray cluster, against a shell loop of
``treeinfer infer`` over the same items (issue 31, section 1).

The items: ``--items`` recordings of the built-in ``two_branch`` example (one pull each,
``--duration`` s at ``--dt`` s, 0.5 mm displacement noise, true parameters drawn per item from
the prior by ``treeinfer simulate --seed i``), written once (not timed). Every item is inferred
with the same options (``--options``, default ``--particles 16``) by

* **loop**: one ``python -m treeinfer infer`` process per item, one after another (what a shell
  loop does: each process imports JAX, builds its simulator and loads its programs);
* **batch wN**: one ``python -m treeinfer batch --workers N`` process over a manifest of all
  items (N = 1 runs them in the batch process itself);
* **ray wN** (``--ray``): ``batch --ray local --workers N``.

All share one compile cache folder, warmed first by one untimed ``infer`` of item 0, so the
figures compare steady-state throughput, not first compiles. Every mode writes fresh folders.
Prints a table and writes JSON (``--json``) with the commands, exit codes and the machine. No
timed assertions: figures from a shared machine are for side-by-side comparison.

Items per minute is a rate: items finished / wall seconds x 60. The loop may run over the first
``--loop-items`` items only (a process per item costs the same for every item: its rate needs
a few), and ``--budget-s`` bounds each timed mode: the loop starts no item after it, a batch is
interrupted at it (Ctrl-C, as a user would: its table is written and the next run resumes) and
its rate counts the items it finished (``items/ID.json``), so an interrupted mode's rate is, if
anything, low (its items in flight are lost). The items are written by a few processes on the
CPU (``treeinfer simulate`` called in them per item: the same files, without a process per
item).

    python -m benchmarks.batch_throughput [--items 8] [--workers 1,2,4] [--ray]
    # a GPU host (16 cores), issue 31's target (batch >= 10x the loop's items per minute):
    JAX_PLATFORMS=cuda python -m benchmarks.batch_throughput --items 100 --loop-items 4 \
        --workers 4 --budget-s 180 --json experiments/results/benchmarks/batch_throughput_h200.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
TREE = ROOT / "treeinfer" / "examples" / "two_branch.yaml"


def _env(cache: Path) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    env["TREEINFER_JAX_CACHE"] = str(cache)
    env.setdefault("JAX_PLATFORMS", "cpu")
    return env


def _run(cmd: list[str], env: dict, log: Path, budget_s: float | None = None):
    """``(exit code, wall s, stopped)``: ``cmd`` to the end, or interrupted (SIGINT, then
    SIGKILL after 30 s) once ``budget_s`` is spent (``stopped``)."""
    t = time.perf_counter()
    with open(log, "ab") as f:
        f.write(("$ " + shlex.join(cmd) + "\n").encode())
        p = subprocess.Popen(cmd, env=env, stdout=f, stderr=subprocess.STDOUT)
        try:
            return p.wait(timeout=budget_s), time.perf_counter() - t, False
        except subprocess.TimeoutExpired:
            wall = time.perf_counter() - t
            p.send_signal(signal.SIGINT)
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
            return p.returncode, wall, True


def _write_items(py: list[str], work: Path, args, env: dict, log: Path, cores: int) -> None:
    """The items' data folders, written by a few processes (one per two cores, at most 8) each
    calling `treeinfer simulate` for its share of the items, on the CPU: a process per item
    would take longer than the benchmark on a GPU host, and a 1 s pull needs no GPU."""
    todo = [i for i in range(args.items) if not (work / "data" / f"item{i:03d}").is_dir()]
    if not todo:
        return
    calls = [
        ["simulate", "--tree", str(TREE), "--out", str(work / "data" / f"item{i:03d}"),
         "--n-traj", "1", "--duration", str(args.duration), "--dt", str(args.dt),
         "--seed", str(i + 1), "--noise-displacement", "0.0005"]
        for i in todo
    ]  # fmt: skip
    code = (
        "import json, sys\nfrom treeinfer.cli import main\n"
        "for argv in json.loads(sys.argv[1]):\n"
        "    rc = main(argv)\n"
        "    if rc:\n        sys.exit(f'simulate {argv}: exit {rc}')\n"
    )
    cpu = {**env, "JAX_PLATFORMS": "cpu"}
    n = max(1, min(8, cores // 2, len(calls)))
    t = time.perf_counter()
    with open(log, "ab") as f:
        procs = [
            subprocess.Popen([py[0], "-c", code, json.dumps(calls[k::n])], env=cpu, stdout=f,
                             stderr=subprocess.STDOUT)
            for k in range(n)
        ]  # fmt: skip
        rcs = [p.wait() for p in procs]
    if any(rcs):
        sys.exit(f"simulate failed (see {log})")
    print(f"wrote {len(todo)} items in {time.perf_counter() - t:.1f} s ({n} processes)", flush=True)


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--items", type=int, default=8, help="number of items (default 8)")
    ap.add_argument(
        "--workers",
        default=None,
        help="comma-separated worker counts (default 1,2,4 up to the cores)",
    )
    ap.add_argument("--duration", type=float, default=1.0, help="s per pull (default 1)")
    ap.add_argument("--dt", type=float, default=0.02, help="s between samples (default 0.02)")
    ap.add_argument(
        "--options",
        default="--particles 16",
        help="infer options of every item (default '--particles 16')",
    )
    ap.add_argument("--ray", action="store_true", help="also time --ray local (needs ray)")
    ap.add_argument("--no-loop", action="store_true", help="leave out the shell loop")
    ap.add_argument(
        "--loop-items", type=int, default=None, help="the loop's items: the first K (default all)"
    )
    ap.add_argument(
        "--budget-s",
        type=float,
        default=None,
        help="s per timed mode: the loop starts no item after it, a batch is interrupted at it "
        "(its rate counts the items it finished)",
    )
    ap.add_argument("--folder", type=Path, help="work folder (default: a temporary one)")
    ap.add_argument(
        "--json",
        type=Path,
        default=ROOT / "experiments" / "results" / "benchmarks" / "batch_throughput.json",
    )
    args = ap.parse_args(argv)
    cores = _cores()
    counts = (
        [int(x) for x in args.workers.split(",")]
        if args.workers
        else [n for n in (1, 2, 4) if n <= cores]
    )
    work = args.folder or Path(tempfile.mkdtemp(prefix="batch_throughput_"))
    work.mkdir(parents=True, exist_ok=True)
    cache, log = work / "jax-cache", work / "commands.log"
    env = _env(cache)
    py = [sys.executable, "-m", "treeinfer"]
    opts = shlex.split(args.options)
    # the items (not timed)
    rows = ["id,tree,recordings," + ",".join(o.lstrip("-").replace("-", "_") for o in opts[::2])]
    _write_items(py, work, args, env, log, cores)
    for i in range(args.items):
        rows.append(f"item{i:03d},{TREE},{work / 'data' / f'item{i:03d}'}," + ",".join(opts[1::2]))
    manifest = work / "manifest.csv"
    manifest.write_text("\n".join(rows) + "\n")
    infer = lambda i, out: (
        py
        + [
            "infer",
            "--tree",
            str(TREE),
            "--data",  # noqa: E731
            str(work / "data" / f"item{i:03d}"),
            "--out",
            str(out),
            "--no-progress",
            "--allow-poor-fit",
            *opts,
        ]
    )
    _, warm_s, _ = _run(infer(0, work / "warm"), env, log)  # fill the compile cache (not timed)
    print(f"warm-up infer (compiles, not timed): {warm_s:.1f} s", flush=True)
    results = []

    def record(mode, workers, rc, wall, cmd, done, stopped=False):
        results.append(
            {
                "mode": mode,
                "workers": workers,
                "rc": rc,
                "items": done,
                "wall_s": round(wall, 2),
                "items_per_min": round(60 * done / wall, 2),
                "stopped_at_budget": stopped,
                "command": cmd,
            }
        )
        print(
            f"{mode:>6} w{workers}: {done:4d} items in {wall:7.1f} s  "
            f"{60 * done / wall:6.2f} items/min  (exit {rc}"
            + (", stopped at the budget)" if stopped else ")"),
            flush=True,
        )

    if not args.no_loop:
        t, rcs = time.perf_counter(), []
        n_loop = args.items if args.loop_items is None else min(args.loop_items, args.items)
        for i in range(n_loop):
            if args.budget_s is not None and time.perf_counter() - t > args.budget_s and rcs:
                break
            rcs.append(_run(infer(i, work / "loop" / f"item{i:03d}"), env, log)[0])
        cmd = shlex.join(infer(0, "loop/ITEM")) + "  # per item"
        wall = time.perf_counter() - t
        record("loop", 1, max(rcs), wall, cmd, len(rcs), len(rcs) < n_loop)
    modes = [("batch", n, []) for n in counts]
    modes += [("ray", n, ["--ray", "local"]) for n in counts if args.ray]
    for mode, n, extra in modes:
        cmd = py + [
            "batch",
            "--manifest",
            str(manifest),
            "--out",
            str(work / f"{mode}_w{n}"),
            "--workers",
            str(n),
            "--no-progress",
            "--allow-poor-fit",
            *extra,
        ]
        rc, wall, stopped = _run(cmd, env, log, args.budget_s)
        done = len(list((work / f"{mode}_w{n}" / "items").glob("*.json")))
        record(mode, n, rc, wall, shlex.join(cmd), done, stopped)
    loop = next((r for r in results if r["mode"] == "loop"), None)
    if loop and loop["items_per_min"] > 0:
        for r in results:  # a ratio of rates: the modes may finish different numbers of items
            r["speedup_vs_loop"] = round(r["items_per_min"] / loop["items_per_min"], 2)
        print(
            "speed-up over the shell loop: "
            + ", ".join(
                f"{r['mode']} w{r['workers']} {r['speedup_vs_loop']:.2f}x" for r in results[1:]
            )
        )
    out = {
        "items": args.items,
        "loop_items": args.loop_items,
        "budget_s": args.budget_s,
        "warm_s": round(warm_s, 1),
        "jax_platforms": env.get("JAX_PLATFORMS"),
        "duration_s": args.duration,
        "dt_s": args.dt,
        "options": args.options,
        "tree": TREE.name,
        "cores": cores,
        "load_avg": os.getloadavg(),
        "machine": platform.node(),
        "python": sys.version.split()[0],
        "results": results,
        "folder": str(work),
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {args.json} (logs: {log})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
