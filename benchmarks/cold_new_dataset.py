"""XLA compilations of a cold `treeinfer infer --init importance` process on a NEW data set, the
persistent cache filled by a run on another one of the same shape bucket (issue 15 item 4).

Data: the standard problem (three_branch, 3 pulls) of ``benchmarks/time_to_posterior.py``: set
A its training pulls of data seed 0 (300 samples), set B those of data seed 1 cut to 290 samples
(other force profiles, another accurate step; one bucket, [3, 320]). Each set is inferred in a
fresh process (``benchmarks.compile_probe``) with one cache folder, A first:

    python -m benchmarks.cold_new_dataset --work DIR [--particles 128]

Prints one JSON object: per data set the process's wall time, its XLA compilations (count,
seconds, the slowest) and its loads from the persistent cache. Run it from the checkout to
measure (``PYTHONPATH`` chooses the treeinfer that runs).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
SETS = {"a": (0, 300), "b": (1, 290)}  # data seed, samples per pull


def write_sets(work: Path) -> dict[str, Path]:
    from benchmarks.time_to_posterior import DT, write_data
    from treeinfer.data.trajectories import Trajectory, write_trajectory

    out = {}
    for name, (seed, n) in SETS.items():
        tmp = Path(tempfile.mkdtemp(dir=work))
        write_data(tmp, seed)
        z = np.load(tmp / "data.npz")
        out[name] = work / f"data_{name}"
        out[name].mkdir(parents=True, exist_ok=True)
        t = np.arange(n) * DT
        for i, (f, x) in enumerate(zip(z["train_force"], z["train_tau"])):
            write_trajectory(out[name] / f"pull{i}.csv", Trajectory(t, f[:n], x[:n], None, f"p{i}"))
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--work", default=None, help="folder for data, runs and the cache")
    p.add_argument("--particles", type=int, default=128)
    args = p.parse_args(argv)
    work = Path(args.work or tempfile.mkdtemp(prefix="cold_new_dataset_"))
    work.mkdir(parents=True, exist_ok=True)
    data = write_sets(work)
    path = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)
    env = {**os.environ, "TREEINFER_JAX_CACHE": str(work / "cache"), "PYTHONPATH": path}
    tree = str(ROOT / "treeinfer" / "examples" / "three_branch.yaml")
    report = {"load_at_start": os.getloadavg()}
    for name in SETS:
        rep, run = work / f"{name}.json", work / f"run_{name}"
        cmd = [sys.executable, "-m", "benchmarks.compile_probe", "--report", str(rep), "--",
               "infer", "--tree", tree, "--data", str(data[name]), "--out", str(run),
               "--particles", str(args.particles), "--init", "importance", "--no-progress",
               "--force", "--allow-poor-fit", "--allow-implausible-data"]  # fmt: skip
        subprocess.run(cmd, env=env, cwd=ROOT, check=True, capture_output=True)
        r = json.loads(rep.read_text())
        r["compiled"] = r["compiled"][:8]
        report[name] = r
    report["load_at_end"] = os.getloadavg()
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
