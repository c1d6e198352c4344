"""The cost of a second data set: ``treeinfer infer`` on data set B after data set A, with the
samplers' shape buckets on (their programs take the padded data as an argument) or off (the data
are constants of the programs), issue 15 item 4.

Two data sets of the standard problem's tree (three_branch, R = 3): A has 3 pulls of 3.0 s
(301 samples), B 3 pulls of 2.9 s (291 samples), other seeds: one shape bucket ([3, 320]),
different data. Two measurements, each in fresh child processes per setting:

* ``--mode process``: one process runs A then B through :func:`treeinfer.runs.run_inference`
  with one :class:`treeinfer.runs.SimulatorCache` (as a long-lived robot service would), the
  persistent compile cache off, so only the in-process program cache can help.
* ``--mode cli``: ``python -m treeinfer infer`` on A, then a second process on B, with a fresh
  persistent compile cache (``TREEINFER_JAX_CACHE``) per setting: the second process's wall time,
  imports included.

    python -m benchmarks.second_dataset --mode process --iterations 5
    python -m benchmarks.second_dataset --mode cli --iterations 5

Prints one JSON object (seconds per phase, compile seconds from JAX's compile log, the recorded
shape bucket and sampler substeps of each run).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
TREE = ROOT / "treeinfer" / "examples" / "three_branch.yaml"
DATA = {"a": (1, 3.0), "b": (2, 2.9)}  # seed, duration (s): one bucket, other data
# the standard step (4 substeps of 2.5 ms) for both data sets: an accuracy-controlled
# step chosen on each data set's forces would give each its own simulator (31 and 53 substeps
# here), and no program could be shared whatever the buckets
MAX_SIM_DT, SIM_TOLERANCE = 0.0025, 1.0


def _env(cache: str | None) -> dict:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "JAX_PLATFORMS": "cpu"}
    env["TREEINFER_JAX_CACHE"] = cache if cache is not None else "off"
    return env


def make_data(work: Path) -> dict[str, Path]:
    """Simulated training sets A and B (``treeinfer simulate``, fixed true gains)."""
    out = {}
    for name, (seed, duration) in DATA.items():
        d = work / f"data_{name}"
        if not d.is_dir():
            subprocess.run(
                [sys.executable, "-m", "treeinfer", "simulate", "--tree", str(TREE), "--out",
                 str(d), "--n-traj", "3", "--seed", str(seed), "--duration", str(duration),
                 "--noise-displacement", "0.002"],
                check=True, env=_env(None), capture_output=True,
            )  # fmt: skip
        out[name] = d
    return out


def _infer_args(data: Path, out: Path, buckets: str, particles: int, iterations: int):
    return ["infer", "--tree", str(TREE), "--data", str(data), "--out", str(out), "--particles",
            str(particles), "--iterations", str(iterations), "--checkpoint-every", "0",
            "--no-progress", "--force", "--allow-poor-fit", "--shape-buckets", buckets,
            "--max-sim-dt", str(MAX_SIM_DT), "--sim-tolerance", str(SIM_TOLERANCE)]  # fmt: skip


def _recorded(out: Path) -> dict:
    p = json.loads((out / "config.json").read_text())["problem"]
    return {k: p.get(k) for k in ("shape_bucket", "sampler_data", "substeps", "n_steps")}


class _CompileLog(logging.Handler):
    def __init__(self):
        super().__init__(logging.DEBUG)
        self.seconds, self.count, self.entries = 0.0, 0, []

    def emit(self, record):
        msg = record.getMessage()
        if "Finished XLA compilation of" in msg:
            s = float(msg.split(" in ")[-1].split(" sec")[0])
            self.count += 1
            self.seconds += s
            self.entries.append((msg.split("compilation of ")[1].split(" in ")[0], round(s, 2)))


def child_process(args) -> dict:
    """One process: A then B, one SimulatorCache (mode ``process``)."""
    t0 = time.perf_counter()
    import jax

    from treeinfer import runs
    from treeinfer.cli.main import main  # noqa: F401  (the CLI's own imports, as a run pays)

    log = _CompileLog()
    logging.getLogger("jax").addHandler(log)
    logging.getLogger("jax").setLevel(logging.DEBUG)
    jax.config.update("jax_log_compiles", True)
    result = {"imports_s": time.perf_counter() - t0}
    cache = runs.SimulatorCache()
    from treeinfer.cli import INFER_DEFAULTS

    for name in ("a", "b"):
        data, out = Path(args.data[name]), Path(args.work) / f"run_{name}_{args.buckets}"
        o = {**INFER_DEFAULTS, "particles": args.particles, "iterations": args.iterations,
             "checkpoint_every": 0, "shape_buckets": args.buckets, "max_sim_dt": MAX_SIM_DT,
             "sim_tolerance": SIM_TOLERANCE}  # fmt: skip
        o["grasp_fraction"] = None
        c0, n0, t = log.seconds, log.count, time.perf_counter()
        inputs = runs.load_run_inputs(TREE, data, None, None, "dynamic", None, None)
        config = runs.infer_config(TREE, data, out, force=True, inputs=inputs, **o)
        runs.run_inference(config, progress=False, cache=cache, inputs=inputs)
        result[name] = {
            "wall_s": time.perf_counter() - t,
            "compile_s": log.seconds - c0,
            "compiles": log.count - n0,
            "slowest_compiles": sorted(log.entries[n0:], key=lambda e: -e[1])[:5],
            **_recorded(out),
        }
    return result


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--mode", choices=["process", "cli"], default="process")
    p.add_argument("--particles", type=int, default=128)
    p.add_argument("--iterations", type=int, default=5)
    p.add_argument("--work", default=None, help="folder for data and runs (default: a temp dir)")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--buckets", default="on", help=argparse.SUPPRESS)
    p.add_argument("--data", type=json.loads, default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        print(json.dumps(child_process(args)))
        return 0
    work = Path(args.work or tempfile.mkdtemp(prefix="second_dataset_"))
    work.mkdir(parents=True, exist_ok=True)
    data = make_data(work)
    report = {"mode": args.mode, "particles": args.particles, "iterations": args.iterations,
              "load_at_start": os.getloadavg(), "settings": {}}  # fmt: skip
    for buckets in ("on", "off"):
        if args.mode == "process":
            cmd = [sys.executable, "-m", "benchmarks.second_dataset", "--child", "--buckets",
                   buckets, "--work", str(work), "--particles", str(args.particles),
                   "--iterations", str(args.iterations),
                   "--data", json.dumps({k: str(v) for k, v in data.items()})]  # fmt: skip
            r = subprocess.run(cmd, check=True, env=_env(None), capture_output=True, text=True)
            report["settings"][buckets] = json.loads(r.stdout.strip().splitlines()[-1])
            continue
        cache = str(work / f"jax_cache_{buckets}")
        row = {}
        for name in ("a", "b"):
            out = work / f"cli_{name}_{buckets}"
            cmd = [
                sys.executable,
                "-m",
                "treeinfer",
                *_infer_args(data[name], out, buckets, args.particles, args.iterations),
            ]
            t = time.perf_counter()
            r = subprocess.run(cmd, env=_env(cache), capture_output=True, text=True)
            if r.returncode not in (0, 4):  # 4: a poor fit after a few iterations is expected
                raise SystemExit(r.stderr)
            row[name] = {"process_wall_s": time.perf_counter() - t, **_recorded(out)}
        report["settings"][buckets] = row
    report["load_at_end"] = os.getloadavg()
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
