"""Run one ``treeinfer`` command in this process and report the XLA programs it compiled.

    python -m benchmarks.compile_probe --report FILE -- infer --tree ... --init importance

Writes ``{"rc", "wall_s", "xla_compiles", "compile_s", "compiled": [[name, s], ...],
"cache_hits"}`` to FILE (:mod:`treeinfer.sim.compile_stats`: an XLA compilation is a backend
compile not served by the persistent cache). ``tests/test_cold_start.py`` and the
cold-start section of BENCHMARKS.md use it.
"""

from __future__ import annotations

import json
import sys
import time


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if len(argv) < 3 or argv[0] != "--report" or argv[2] != "--":
        raise SystemExit("usage: python -m benchmarks.compile_probe --report FILE -- COMMAND ...")
    report, command = argv[1], argv[3:]
    t0 = time.perf_counter()
    from treeinfer.cli.main import main as cli
    from treeinfer.sim.compile_stats import compile_stats

    stats = compile_stats()
    rc = cli(command)
    out = {"rc": rc, "wall_s": round(time.perf_counter() - t0, 3), **stats.since()}
    with open(report, "w") as f:
        json.dump(out, f, indent=1)
    return rc


if __name__ == "__main__":
    raise SystemExit(main())
