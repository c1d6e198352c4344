"""A QSM chain's whole ``infer`` against a built-in example with as many joints (issue 30's
target: "the chain to a grasp point on a 2,000-cylinder QSM infers as fast as a built-in
example of the same size"), in one run, CPU seconds of each command.

For each case, three fresh processes in turn, each with a new empty JAX compile cache (every
program compiled, as a user's first run), timed by the children's user + system CPU
(``resource.getrusage``) and wall:

* ``qsm``: ``treeinfer tree --from-qsm QSM --grasp-point=... --joint-spacing 1.0 --levels 3``
  (the shared TreeQSM sapling's chain from the grasp point of ``docs/qsm.md`` to its base:
  4 joints, 3 inferred), then ``simulate`` and ``infer`` (defaults) on it;
* ``three_branch``: the built-in example (4 joints, 3 inferred), ``simulate`` and ``infer``
  with the same options.

``simulate --n-traj 3 --seed 1 --noise-displacement 0.002 --noise-force 0.05`` (the docs'
table). The cases alternate command by command (a drift of the shared box's speed hits both).
On a loaded machine compare the CPU seconds; the 1-minute load average before each command
is recorded.

    nice python -m benchmarks.qsm_infer [--qsm FILE] [--out DIR] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
GRASP = "1.693,-16.09,256.03"  # the shared sapling's grasp point (docs/qsm.md)
SIMULATE = ["--n-traj", "3", "--seed", "1", "--noise-displacement", "0.002",
            "--noise-force", "0.05"]  # fmt: skip


def timed(cmd: list[str], env: dict) -> dict:
    """Run ``python -m treeinfer CMD``; its exit code, wall and CPU seconds (user + system of
    the child), the load average before it."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "treeinfer", *cmd], env=env, cwd=ROOT,
                          capture_output=True, text=True)  # fmt: skip
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    out = {"cmd": "treeinfer " + " ".join(cmd), "rc": proc.returncode, "wall_s": wall,
           "cpu_s": cpu, "load1": load}  # fmt: skip
    if proc.returncode not in (0, 4):
        out["stderr_tail"] = proc.stderr[-2000:]
    print(f"{out['rc']:>3} {cpu:8.1f} CPU-s {wall:8.1f} s  load {load:4.1f}  {out['cmd']}",
          flush=True)  # fmt: skip
    return out


def shared_qsm() -> Path | None:
    found = [p / "shared/data/qsm/treeqsm_QSM.mat" for p in (ROOT, *ROOT.parents)]
    return next((f for f in found if f.is_file()), None)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--qsm", type=Path, default=shared_qsm())
    ap.add_argument("--out", type=Path, default=None, help="work folder (default: a temp one)")
    ap.add_argument("--json", type=Path, default=ROOT / "benchmarks/results/qsm_infer.json")
    args = ap.parse_args(argv)
    if args.qsm is None:
        print("no QSM: give --qsm (shared/data/qsm/treeqsm_QSM.mat was not found)")
        return 2
    work = args.out or Path(tempfile.mkdtemp(prefix="qsm_infer_"))
    work.mkdir(parents=True, exist_ok=True)
    from treeinfer.examples import example_path

    trees = {"qsm": work / "qsm_chain.yaml", "three_branch": Path(example_path("three_branch"))}
    steps: dict[str, list[list[str]]] = {
        "qsm": [["tree", "--from-qsm", str(args.qsm), f"--grasp-point={GRASP}",
                 "--joint-spacing", "1.0", "--levels", "3", "--out", str(trees["qsm"])]],
        "three_branch": [[]],
    }  # fmt: skip
    for case, tree in trees.items():
        steps[case] += [
            ["simulate", "--tree", str(tree), "--out", str(work / case / "data"), *SIMULATE],
            ["infer", "--tree", str(tree), "--data", str(work / case / "data"),
             "--out", str(work / case / "run")],
        ]  # fmt: skip
    res: dict[str, list[dict]] = {case: [] for case in steps}
    for i in range(3):  # alternate: tree (QSM only), simulate, infer
        for case, cmds in steps.items():
            if not cmds[i]:
                continue
            env = {**os.environ, "TREEINFER_JAX_CACHE": tempfile.mkdtemp(prefix="jaxc_")}
            res[case].append(timed(cmds[i], env))
    summary = {case: {"cpu_s": sum(r["cpu_s"] for r in rs), "wall_s": sum(r["wall_s"] for r in rs)}
               for case, rs in res.items()}  # fmt: skip
    for case in res:
        infer = next(r for r in res[case] if r["cmd"].startswith("treeinfer infer"))
        summary[case]["infer_cpu_s"] = infer["cpu_s"]
        run = work / case / "run" / "summary.json"
        if run.is_file():
            s = json.loads(run.read_text())
            summary[case]["fit"] = (s.get("fit") or {}).get("status")
            summary[case]["elapsed_s_sampling"] = s.get("elapsed_s_sampling")
    base = summary["three_branch"]
    summary["ratio_infer_cpu"] = summary["qsm"]["infer_cpu_s"] / base["infer_cpu_s"]
    summary["ratio_all_cpu"] = summary["qsm"]["cpu_s"] / summary["three_branch"]["cpu_s"]
    print(json.dumps(summary, indent=1))
    args.json.parent.mkdir(parents=True, exist_ok=True)
    record = {"runs": res, "summary": summary, "qsm": str(args.qsm), "machine": platform.node(),
              "cpus": os.cpu_count(), "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
              "commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT,
                                       capture_output=True, text=True).stdout.strip()}  # fmt: skip
    args.json.write_text(json.dumps(record, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
