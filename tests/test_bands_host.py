"""The host twin of the KDE interval (treeinfer.evaluation.bands_host) against the jitted one."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from treeinfer.evaluation import bands
from treeinfer.evaluation.bands_host import interval_host


@pytest.mark.parametrize("shape", [(7,), (2, 3)])
def test_host_interval_equals_the_jitted_one(shape):
    """Skewed, bimodal and degenerate series, invalid particles left out: the same ends and
    means as the jitted float32 program's, to its precision (its CDF sums 200 float32 terms:
    a few 1e-5 of the series' scale where the density is thin)."""
    rng = np.random.default_rng(3)
    p = 200
    x = rng.lognormal(0.0, 0.8, (p, *shape)).astype(np.float32)
    flat = x.reshape(p, -1)
    flat[:, 1] = np.where(rng.random(p) < 0.4, -5.0, 5.0) + rng.normal(0, 0.1, p)  # bimodal
    flat[:, 2] = 3.25  # degenerate: every particle the same
    eff = rng.random(p) > 0.1
    want = bands._interval(jnp.asarray(x), jnp.asarray(eff), 0.025, 60)
    got = interval_host(x, eff, 0.025, 60, np.float32)
    for a, b in zip(got, want):
        b = np.asarray(b)
        assert a.shape == b.shape == shape and a.dtype == b.dtype
        np.testing.assert_allclose(a, b, rtol=5e-5, atol=1e-5 * np.abs(b).max())
    assert got[0].reshape(-1)[2] == got[1].reshape(-1)[2] == np.float32(3.25)
    # and not loose: a shifted series is told apart
    shifted = interval_host(x * 1.001, eff, 0.025, 60, np.float32)[1]
    assert np.abs(shifted - np.asarray(want[1])).max() > 1e-3 * np.abs(want[1]).max() / 2


def test_predictive_interval_of_a_few_series_compiles_nothing(monkeypatch):
    """``predictive_interval`` of parameter columns runs on the host; recordings' bands
    (more series than ``_HOST_MAX_SERIES``) stay on the jitted program."""
    calls = []
    real = bands._interval
    monkeypatch.setattr(bands, "_interval", lambda *a: calls.append(a) or real(*a))
    rng = np.random.default_rng(0)
    lo, hi, mean = bands.predictive_interval(rng.normal(size=(64, 6)))
    assert calls == [] and np.all(np.asarray(lo) < np.asarray(mean))
    bands.predictive_interval(rng.normal(size=(64, 3, 30)))
    assert len(calls) == 1
