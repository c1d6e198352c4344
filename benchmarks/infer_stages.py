"""Where the default ``treeinfer infer`` spends its time: CPU and wall seconds per stage of the
command, and the whole command's wall and CPU time, with an empty and a warm compile cache.

    JAX_PLATFORMS=cpu python -m benchmarks.infer_stages [--data D] [--work W] [--no-warm] \
        [-- extra infer flags]

The standard problem (``three_branch``, 3 pulls of 3 s at 10 ms, 2 mm + 0.05 N noise, written
by ``treeinfer simulate`` once, not timed; or ``--data``) is inferred by the default command,
each run a fresh process, cold (``TREEINFER_JAX_CACHE`` a new empty folder) then warm (the
folder the cold run filled). The child process wraps the command's stages (module functions
listed in :data:`STAGES`, patched where they are looked up) with timers of wall time
(``time.perf_counter``) and process CPU time (``time.process_time``: every thread of the
process, JAX's included) and runs ``treeinfer.cli.main`` itself; nested stages are indented
under the stage that called them (a stage's figures include its nested ones). The parent
times the whole child process (wall, and user + system CPU by ``getrusage``).

On a shared machine the wall times carry the other users' load (the 1-minute load average
before each run is printed); the CPU seconds much less. No timed assertions: figures for
``BENCHMARKS.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
# (module, function, label): the command's stages, in the order they run
STAGES = [
    ("treeinfer.runs.service", "_data_checks", "data checks"),
    ("treeinfer.runs.service", "build_problem", "build the problem"),
    ("treeinfer.runs.cache", "simulator_for", "simulator and its step choice"),
    ("treeinfer.runs.background", "_Prefetch.wait", "wait for a second thread's compile"),
    ("treeinfer.inference.start_pipeline", "force_noise_reference", "force-noise reference MAP"),
    ("treeinfer.inference.start_steps", "screen", "Latin-hypercube screen"),
    ("treeinfer.inference.fast_fit", "fit_map_batched", "LM / GGN MAP fit"),
    ("treeinfer.inference.problem", "make_problem", "make_problem (likelihood terms)"),
    ("treeinfer.model.force_noise", "force_noise_basis", "force-noise basis (J, eigh)"),
    ("treeinfer.model.force_noise_bias", "with_bias_slope", "bias slope (2R Jacobians)"),
    ("treeinfer.model.force_noise", "force_jacobian", "force Jacobian J"),
    ("treeinfer.runs.service", "_start", "start pipeline (importance posterior)"),
    ("treeinfer.inference.start_steps", "multimode_importance", "importance sampling, modes"),
    ("treeinfer.inference.importance", "adaptive_importance", "importance sampling"),
    ("treeinfer.inference.resample_move", "resample_move", "resample-move"),
    ("treeinfer.runs.service", "_sample", "sampler"),
    ("treeinfer.runs.service", "_summarised_posterior", "posterior summaries"),
    ("treeinfer.runs.service", "_training_fit", "training fit (bands)"),
    ("treeinfer.runs.service", "_run_figures", "figures started (second thread)"),
    ("treeinfer.runs.service", "_run_summary", "run summary"),
    ("treeinfer.evaluation.checks", "fit_verdict_from_run", "fit verdict"),
    ("treeinfer.runs.service", "save_run", "write the run folder"),
    ("treeinfer.runs.figures", "write_run_figures", "figures"),
]
DATA = ["--n-traj", "3", "--duration", "3", "--dt", "0.01", "--seed", "0"]
NOISE = ["--noise-displacement", "0.002", "--noise-force", "0.05"]


def _child(out: Path, argv: list[str]) -> int:
    """Run ``treeinfer`` with ``argv`` in this process, the stages timed; JSON to ``out``."""
    t_start, c_start = time.perf_counter(), time.process_time()
    import importlib

    # the module (``treeinfer.cli.main`` the attribute is the function of that name)
    cli = importlib.import_module("treeinfer.cli.main")

    records: dict = {}
    stack: list[str] = []

    def wrap(label, fn):
        def timed(*a, **k):
            depth = len(stack)
            stack.append(label)
            w0, c0 = time.perf_counter(), time.process_time()
            try:
                return fn(*a, **k)
            finally:
                stack.pop()
                r = records.setdefault(
                    label, {"calls": 0, "wall_s": 0.0, "cpu_s": 0.0, "depth": depth,
                            "first": w0 - t_start},
                )  # fmt: skip
                if len(stack) == 0 or label not in stack:  # recursion: count the outer call
                    r["calls"] += 1
                    r["wall_s"] += time.perf_counter() - w0
                    r["cpu_s"] += time.process_time() - c0

        timed.__wrapped__ = fn
        return timed

    import treeinfer.runs.service  # noqa: F401 -- loaded before patching: its names are bound

    for mod_name, attr, label in STAGES:
        mod = importlib.import_module(mod_name)
        if "." in attr:  # a method: patched on its class
            cls_name, meth = attr.split(".")
            cls = getattr(mod, cls_name)
            setattr(cls, meth, wrap(label, getattr(cls, meth)))
            continue
        orig = getattr(mod, attr)
        w = wrap(label, orig)
        # every loaded treeinfer module that bound the same function by name
        for m in list(sys.modules.values()):
            ours = getattr(m, "__name__", "").startswith("treeinfer")
            if ours and getattr(m, attr, None) is orig:
                setattr(m, attr, w)
    t_imports = time.perf_counter() - t_start
    events = _listen_compiles(stack)
    rc = cli.main(argv)
    res = {
        "exit": rc,
        "imports_wall_s": t_imports,
        "in_process_wall_s": time.perf_counter() - t_start,
        "in_process_cpu_s": time.process_time() - c_start,
        "stages": records,
        "compiles": events,
    }
    out.write_text(json.dumps(res, indent=2) + "\n")
    return rc


_EVENTS = {  # JAX's monitoring duration events: what a program's first call costs
    "/jax/core/compile/jaxpr_trace_duration": "trace",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
    "/jax/core/compile/backend_compile_duration": "compile",
}


def _listen_compiles(stack: list[str]) -> list:
    """A list that fills with ``[kind, function, seconds, stage, thread]`` per trace, lowering
    and XLA compile (or persistent-cache load: ``compile`` events of a warm run) of the run."""
    import threading

    from jax import monitoring

    events: list = []
    t0 = time.perf_counter()

    def on_duration(event: str, secs: float, **kw) -> None:
        kind = _EVENTS.get(event)
        if kind is not None:
            where = (
                stack[-1]
                if stack and threading.current_thread() is threading.main_thread()
                else threading.current_thread().name
            )
            events.append([kind, str(kw.get("fun_name", "?")), round(float(secs), 4), where,
                           threading.current_thread().name,
                           round(time.perf_counter() - t0 - secs, 3)])  # fmt: skip

    monitoring.register_event_duration_secs_listener(on_duration)
    return events


def _print_compiles(events: list) -> None:
    """Totals of the traces, lowerings and compiles per kind and per stage, the slowest ones."""
    if not events:
        return
    by: dict = {}
    for kind, _name, secs, where, *_ in events:
        n, s = by.get((kind, where), (0, 0.0))
        by[(kind, where)] = (n + 1, s + secs)
    print(f"  {'kind':8s} {'stage':40s} {'count':>5s} {'wall s':>8s}")
    for (kind, where), (n, s) in sorted(by.items(), key=lambda kv: -kv[1][1]):
        if s >= 0.2:
            print(f"  {kind:8s} {where[:40]:40s} {n:5d} {s:8.2f}")
    for kind in _EVENTS.values():
        ev = [e for e in events if e[0] == kind]
        print(f"  {kind}: {len(ev)} events, {sum(e[2] for e in ev):.1f} s")
    slow = sorted((e for e in events if e[2] >= 0.5), key=lambda e: -e[2])[:25]
    for kind, name, secs, where, th, *start in slow:
        at = f" @{start[0]:.1f}" if start else ""
        print(f"    {kind:8s} {secs:6.2f} s  {name[:40]:40s} {where[:34]} ({th}){at}")


def _env(cache: Path) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    env["TREEINFER_JAX_CACHE"] = str(cache)
    return env


def _run(cmd, cache: Path, log: Path) -> dict:
    import resource

    load = os.getloadavg()[0]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    with open(log, "w") as f:
        rc = subprocess.run(cmd, env=_env(cache), stdout=f, stderr=subprocess.STDOUT).returncode
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"exit": rc, "wall_s": wall, "cpu_s": cpu, "load_before": load}


def _print(phase: str, whole: dict, stages: dict) -> None:
    print(
        f"\n{phase}: whole command {whole['wall_s']:.1f} s wall, {whole['cpu_s']:.1f} CPU-s "
        f"(load {whole['load_before']:.1f} before), exit {whole['exit']}; imports "
        f"{stages.get('imports_wall_s', float('nan')):.1f} s wall"
    )
    print(f"  {'stage':48s} {'calls':>5s} {'CPU-s':>8s} {'wall s':>8s}")
    for label, r in sorted(stages.get("stages", {}).items(), key=lambda kv: kv[1]["first"]):
        name = "  " * r["depth"] + label
        print(f"  {name:48s} {r['calls']:5d} {r['cpu_s']:8.1f} {r['wall_s']:8.1f}")


def main(argv=None) -> dict:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["--child"]:
        raise SystemExit(_child(Path(argv[1]), argv[2:]))
    extra = argv[argv.index("--") + 1 :] if "--" in argv else []
    argv = argv[: argv.index("--")] if "--" in argv else argv
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, help="a data folder (default: the standard problem)")
    ap.add_argument("--work", type=Path, help="scratch folder (default: a new temporary one)")
    ap.add_argument("--no-warm", action="store_true", help="the cold run only")
    ap.add_argument("--json", type=Path, help="write the figures here too")
    args = ap.parse_args(argv)
    work = args.work or Path(tempfile.mkdtemp(prefix="infer_stages_"))
    work.mkdir(parents=True, exist_ok=True)
    py = [sys.executable, "-m", "treeinfer"]
    tree = ROOT / "treeinfer" / "examples" / "three_branch.yaml"
    data = args.data
    if data is None:
        data = work / "data"
        if not (data / "true_params.json").is_file():
            r = _run(
                [*py, "simulate", "--tree", str(tree), "--out", str(data), *DATA, *NOISE,
                 "--force"],
                work / "cache_data", work / "simulate.log",
            )  # fmt: skip
            if r["exit"] != 0:
                raise SystemExit(f"simulate failed: see {work / 'simulate.log'}")
    cache = work / f"cache_{time.strftime('%H%M%S')}"
    res = {"data": str(data), "flags": extra, "runs": {}}
    for phase in ("cold",) if args.no_warm else ("cold", "warm"):
        out, stages_json = work / f"run_{phase}", work / f"stages_{phase}.json"
        cmd = [sys.executable, "-m", "benchmarks.infer_stages", "--child", str(stages_json)]
        cmd += ["infer", "--tree", str(data / "tree.yaml"), "--data", str(data), "--out", str(out)]
        cmd += ["--force", *extra]
        whole = _run(cmd, cache, work / f"{phase}.log")
        stages = json.loads(stages_json.read_text()) if stages_json.is_file() else {}
        res["runs"][phase] = {"whole": whole, **stages}
        _print(phase, whole, stages)
        _print_compiles(stages.get("compiles", []))
    res["machine"] = {"cores": os.cpu_count(), "jax_platforms": os.environ.get("JAX_PLATFORMS")}
    res["commit"] = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True
    ).stdout.strip()
    if args.json:
        args.json.write_text(json.dumps(res, indent=2) + "\n")
    print(f"\nlogs and runs in {work}")
    return res


if __name__ == "__main__":
    main()
