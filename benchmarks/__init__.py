"""Benchmark scripts (figures, not tests): ``python -m benchmarks.rollout``,
``python -m benchmarks.inference``.

See ``BENCHMARKS.md`` for the figures, machines and commands."""

# The figures in BENCHMARKS.md were taken with the runtime set up as the command line does it
# (persistent compile cache, GPU memory grown on demand), which `import treeinfer` did until
# issue 25; every `python -m benchmarks.X` (and its child processes) imports this package first.
import treeinfer as _treeinfer

_treeinfer.configure_runtime()
