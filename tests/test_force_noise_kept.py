"""The force-noise basis and its bias slope are kept on the simulator (``Simulator.derived``):
a second request with the same inputs takes no Jacobian and gives the same arrays as a fresh
simulator; other inputs are computed anew."""

from __future__ import annotations

import numpy as np

from treeinfer.examples import example_path
from treeinfer.model import force_noise as fn
from treeinfer.model import force_noise_bias as fb
from treeinfer.sim import make_simulator
from treeinfer.tree.description import load_tree


def _setup():
    sim = make_simulator(load_tree(example_path("two_branch")), obs_dt=0.01, substeps=4)
    t = np.arange(20) * 0.01
    forces = np.stack([3.0 * np.clip(t / 0.1, 0, 1), 2.0 + np.sin(9 * t)])
    lo, hi = (np.log(np.asarray(b, float)) for b in sim.prior_box)
    return sim, forces, 0.5 * (lo + hi)


def test_basis_and_slope_kept_and_equal_to_fresh(monkeypatch):
    sim, forces, ref = _setup()
    calls = []
    real = fn.force_jacobian

    def counted(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(fb, "force_jacobian", counted)
    first = fb.with_bias_slope(sim, fn.force_noise_basis(sim, ref, forces, 0.05), ref, forces, 0.05)
    assert len(calls) == ref.size  # the slope's forward differences
    second = fb.with_bias_slope(
        sim, fn.force_noise_basis(sim, ref, forces, 0.05), ref, forces, 0.05
    )
    assert len(calls) == ref.size  # kept: no Jacobian taken again
    second.vectors[:] = 0.0  # a caller's copy: the kept one is untouched
    third = fn.force_noise_basis(sim, ref, forces, 0.05)
    np.testing.assert_array_equal(third.vectors, first.vectors)
    # a fresh simulator (nothing kept) gives the same basis and slope
    sim2 = make_simulator(load_tree(example_path("two_branch")), obs_dt=0.01, substeps=4)
    fresh = fb.with_bias_slope(
        sim2, fn.force_noise_basis(sim2, ref, forces, 0.05), ref, forces, 0.05
    )
    np.testing.assert_array_equal(fresh.values, first.values)
    np.testing.assert_array_equal(fresh.slope, first.slope)
    # other inputs: computed anew
    other = fn.force_noise_basis(sim, ref, forces, 0.1)
    np.testing.assert_allclose(other.values, 4.0 * first.values, rtol=1e-6)
    fb.with_bias_slope(sim, other, ref, forces, 0.1)
    assert len(calls) == 3 * ref.size  # the fresh simulator's and this one
