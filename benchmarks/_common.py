"""Shared helpers of the benchmark scripts: machine description, timing, compile counting,
memory, and merging results into ``experiments/results/benchmarks/<machine>.json``."""

from __future__ import annotations

import datetime as _dt
import json
import os
import platform
import resource
import statistics
import sys
import time
from pathlib import Path

import numpy as np

RESULTS_DIR = Path(__file__).resolve().parent.parent / "experiments" / "results" / "benchmarks"


def machine_info() -> dict:
    """Host and accelerator description recorded with every result."""
    import jax
    import mujoco

    dev = jax.devices()[0]
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    try:
        load = os.getloadavg()
    except OSError:
        load = None
    return {
        "date": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "host_cpu": cpu,
        "host_cores": os.cpu_count(),
        "load_average_at_start": load,
        "platform": dev.platform,
        "device_kind": getattr(dev, "device_kind", str(dev)),
        "n_devices": jax.device_count(),
        "python": sys.version.split()[0],
        "jax": jax.__version__,
        "mujoco": mujoco.__version__,
        "command": " ".join([Path(sys.executable).name, "-m", _module_name()] + sys.argv[1:]),
    }


def _module_name() -> str:
    main = sys.modules.get("__main__")
    spec = getattr(main, "__spec__", None)
    return spec.name if spec is not None else sys.argv[0]


def block(x):
    """Wait for every array in a pytree."""
    import jax

    return jax.block_until_ready(x)


def time_calls(fn, reps: int, min_time_s: float = 0.0) -> dict:
    """Median / min wall time of ``fn()`` (already compiled and warmed), blocking on its output.

    Repeats at least ``reps`` times and until ``min_time_s`` seconds have passed."""
    times = []
    t_start = time.perf_counter()
    while len(times) < reps or (time.perf_counter() - t_start) < min_time_s:
        t0 = time.perf_counter()
        block(fn())
        times.append(time.perf_counter() - t0)
        if len(times) >= 50:
            break
    return {"median_s": statistics.median(times), "min_s": min(times), "reps": len(times)}


class CompileCounter:
    """Counts XLA backend compilations (``/jax/core/compile/backend_compile_duration`` events)
    and persistent-cache hits while installed; ``with CompileCounter() as c: ...; c.n``."""

    COMPILE = "/jax/core/compile/backend_compile_duration"
    HIT = "/jax/compilation_cache/cache_hits"

    def __init__(self):
        self.n = 0
        self.seconds = 0.0
        self.cache_hits = 0
        self._active = False

    def _duration(self, event, duration, **kw):
        if self._active and event == self.COMPILE:
            self.n += 1
            self.seconds += float(duration)

    def _event(self, event, **kw):
        if self._active and event == self.HIT:
            self.cache_hits += 1

    def __enter__(self):
        import jax

        self._active = True
        if not getattr(self, "_registered", False):
            jax.monitoring.register_event_duration_secs_listener(self._duration)
            jax.monitoring.register_event_listener(self._event)
            self._registered = True
        return self

    def __exit__(self, *exc):
        self._active = False


def peak_host_mb() -> float:
    """Peak resident memory of this process (MiB), from ``getrusage`` (kB on Linux)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def device_memory_mb() -> dict | None:
    """Peak / current device memory (MiB) of the first device where the backend reports it (GPU)."""
    import jax

    try:
        stats = jax.local_devices()[0].memory_stats()
    except Exception:  # noqa: BLE001 -- CPU backends have no memory stats
        return None
    if not stats:
        return None
    mb = 1024.0 * 1024.0
    return {
        "peak_mb": stats.get("peak_bytes_in_use", 0) / mb,
        "in_use_mb": stats.get("bytes_in_use", 0) / mb,
        "limit_mb": stats.get("bytes_limit", 0) / mb,
    }


def default_machine_name() -> str:
    import jax

    dev = jax.devices()[0]
    if dev.platform == "gpu":
        kind = getattr(dev, "device_kind", "gpu").lower()
        return "h100" if "h100" in kind else kind.replace(" ", "-")
    return f"cpu-{os.cpu_count()}core"


def merge_results(path: Path, section: str, results: dict, summary: dict) -> Path:
    """Merge ``results`` into ``section`` (key by key) and the top-level ``summary`` keys into the
    JSON at ``path`` (written atomically); everything else already there is kept."""
    from treeinfer.io.atomic import atomic_write_json

    path = Path(path)
    data = {}
    if path.is_file():
        try:
            data = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError):
            data = {}
    old = data.get(section)
    data[section] = {**old, **results} if isinstance(old, dict) else results
    data.update(summary)
    atomic_write_json(path, _plain(data))
    return path


def read_section(path: Path, section: str) -> dict:
    """``section`` of the JSON at ``path`` ({} if absent or unreadable)."""
    try:
        return dict(json.loads(Path(path).read_text()).get(section) or {})
    except (OSError, json.JSONDecodeError, AttributeError):
        return {}


def _plain(x):
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, float) and not np.isfinite(x):
        return None
    return x


def fmt_rate(x: float | None) -> str:
    if x is None or not np.isfinite(x):
        return "-"
    for unit, s in (("G", 1e9), ("M", 1e6), ("k", 1e3)):
        if x >= s:
            return f"{x / s:.3g}{unit}"
    return f"{x:.3g}"


def print_table(rows: list[dict], columns: list[tuple[str, str]]) -> None:
    """Plain fixed-width table: ``columns`` = [(key, header)]."""
    cells = [[h for _, h in columns]] + [[str(r.get(k, "")) for k, _ in columns] for r in rows]
    widths = [max(len(c[i]) for c in cells) for i in range(len(columns))]
    for j, row in enumerate(cells):
        print("  ".join(c.rjust(w) for c, w in zip(row, widths)), flush=True)
        if j == 0:
            print("  ".join("-" * w for w in widths), flush=True)
