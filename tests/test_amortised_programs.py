"""The amortised check's small programs take the recording's numbers as arguments
(:mod:`treeinfer.amortised.programs`): a second closure of the same shape over other data runs
the program the first compiled (counted with :func:`treeinfer.sim.compile_stats.compile_stats`,
not timed), with the closure's own values."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from treeinfer.amortised.programs import ArgsProgram, lift_constants
from treeinfer.sim.compile_stats import compile_stats
from treeinfer.sim.program_cache import ProgramCache


def _density(data: np.ndarray, scale: float, lo: float):
    """A closure as the problem's are: an array and two Python numbers (literals in the jaxpr),
    one of them inside a comparison."""
    data = jnp.asarray(data, jnp.float32)

    def f(theta, r):
        inside = jnp.where(theta[:, 0] > lo, 0.0, -jnp.inf)
        return -0.5 * scale * jnp.sum((r - data) ** 2, axis=(-2, -1)) + inside, theta * scale

    return f


def _reference(data, scale, lo, theta, r):
    """The same density in NumPy (float64)."""
    v = -0.5 * scale * np.sum((r - data) ** 2, axis=(-2, -1))
    return np.where(theta[:, 0] > lo, v, -np.inf), theta * scale


def _compiles(mark) -> int:
    s = compile_stats().since(mark)
    return s["xla_compiles"] + s["cache_hits"]


def test_a_second_recording_of_the_same_shape_compiles_nothing():
    rng = np.random.default_rng(0)
    theta = rng.normal(size=(6, 3)).astype(np.float32)
    r = rng.normal(size=(6, 2, 5)).astype(np.float32)
    cache = ProgramCache()
    cases = [(rng.normal(size=(2, 5)), 2.0, -0.5), (rng.normal(size=(2, 5)), 7.5, 0.3)]
    stats = compile_stats()
    counts = []
    for data, scale, lo in cases:
        mark = stats.mark()
        prog = ArgsProgram(_density(data, scale, lo), cache)
        v, t = prog(theta, r)
        counts.append(_compiles(mark))
        v_ref, t_ref = _reference(data, scale, lo, theta.astype(float), r.astype(float))
        np.testing.assert_allclose(np.asarray(v), v_ref, rtol=1e-5)
        np.testing.assert_allclose(np.asarray(t), t_ref, rtol=1e-6)
        assert prog.traces == 1
    assert counts[0] >= 1 and counts[1] == 0, counts
    assert len(cache) == 1
    # another shape is another program; a cache of its own compiles again (the counter counts)
    mark = stats.mark()
    ArgsProgram(_density(*cases[0]), cache)(theta[:4], r[:4])
    ArgsProgram(_density(*cases[1]), ProgramCache())(theta, r)
    assert _compiles(mark) >= 2 and len(cache) == 2


def test_the_lifted_jaxprs_text_holds_no_values():
    a = lift_constants(_density(np.ones((2, 5)), 2.0, -0.5), np.zeros((3, 3)), np.zeros((3, 2, 5)))
    b = lift_constants(_density(np.zeros((2, 5)), 9.0, 0.7), np.zeros((3, 3)), np.zeros((3, 2, 5)))
    assert a[0] == b[0]
    assert "9.0" not in b[0] and "0.7" not in b[0]
    assert any(np.any(np.asarray(c) == 9.0) for c in b[2])
