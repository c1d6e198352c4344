"""Benchmark scripts (figures, not tests): ``python -m benchmarks.rollout``,
``python -m benchmarks.inference``.

See ``BENCHMARKS.md`` for the figures, machines and commands."""
