"""Diagnostics: R-hat/ESS against known cases, warnings, NetCDF round trip."""

import numpy as np
import pytest

from treeinfer.errors import ConfigError
from treeinfer.inference import diagnostics as dg
from treeinfer.inference.diagnostics import arviz_compat

LABELS = ["Kp[b1]", "Kd[b1]"]


def _ar1(rng, n, chains, d, phi):
    """AR(1) chains with unit marginal variance; ESS = n (1 - phi) / (1 + phi) per chain."""
    x = np.empty((n, chains, d))
    x[0] = rng.normal(size=(chains, d))
    eps = rng.normal(size=(n, chains, d)) * np.sqrt(1 - phi**2)
    for t in range(1, n):
        x[t] = phi * x[t - 1] + eps[t]
    return x


def test_rhat_ess_iid_and_ar1():
    rng = np.random.default_rng(0)
    n, P = 800, 8
    iid = rng.normal(size=(n, P, 2))
    d = dg.mcmc_diagnostics(iid, LABELS, burn_in=0.0)
    assert d["n_chains"] == P and d["n_draws"] == n
    for p in d["parameters"].values():
        assert abs(p["rhat"] - 1.0) < 0.01
        assert 0.8 * n * P < p["ess_bulk"] < 1.2 * n * P
    assert dg.convergence_warnings(d, "mcmc") == []

    phi = 0.6
    d = dg.mcmc_diagnostics(_ar1(rng, n, P, 2, phi), LABELS, burn_in=0.0)
    expected = n * P * (1 - phi) / (1 + phi)  # closed form for AR(1)
    for p in d["parameters"].values():
        assert 0.75 * expected < p["ess_bulk"] < 1.25 * expected


def test_rhat_detects_stuck_chains_and_burn_in():
    rng = np.random.default_rng(1)
    n, P = 400, 6
    stuck = rng.normal(size=(n, P, 2)) + np.arange(P)[None, :, None]  # each chain at its own mean
    d = dg.mcmc_diagnostics(stuck, LABELS)
    assert all(p["rhat"] > 1.1 for p in d["parameters"].values())
    w = dg.convergence_warnings(d, "mcmc")
    assert any("Kp[b1]: R-hat" in m for m in w) and any("Kd[b1]: R-hat" in m for m in w)
    # first half far from the target, second half iid: burn-in removes it
    warm = rng.normal(size=(n, P, 2))
    warm[: n // 2] += 10 * rng.normal(size=(1, P, 2))
    assert dg.mcmc_diagnostics(warm, LABELS, burn_in=0.0)["rhat_max"] > 1.1
    d = dg.mcmc_diagnostics(warm, LABELS, burn_in=0.5)
    assert d["n_burn_in"] == n // 2 and d["rhat_max"] < 1.02
    np.testing.assert_allclose(d["parameters"]["Kd[b1]"]["mean"], warm[n // 2 :, :, 1].mean())


def test_mcmc_excluded_unstable_and_low_ess_warnings():
    rng = np.random.default_rng(2)
    n, P = 200, 10
    x = _ar1(rng, n, P, 2, 0.98)  # strongly autocorrelated -> low ESS
    x[150, 4, 0] = np.nan
    lp = np.zeros((n, P))
    lp[-1, [1, 2]] = -np.inf
    d = dg.mcmc_diagnostics(x, LABELS, log_density=lp)
    assert d["n_chains"] == 9 and d["n_excluded_chains"] == 1 and d["n_unstable"] == 2
    w = dg.convergence_warnings(d, "mcmc")
    assert any("non-finite positions" in m for m in w)
    assert any("bulk ESS" in m and "per chain" in m for m in w)
    assert any("2 of 10 chains end on an unstable" in m for m in w)
    # tolerated unstable fraction: no unstable warning
    w = dg.convergence_warnings(d, "mcmc", max_unstable_fraction=0.5, min_ess_per_chain=0.0)
    assert not any("unstable" in m for m in w) and not any("ESS" in m for m in w)
    # constant chains (nothing accepted): undefined R-hat is reported, not hidden
    const = np.ones((50, 4, 2))
    w = dg.convergence_warnings(dg.mcmc_diagnostics(const, LABELS), "mcmc")
    assert any("R-hat undefined" in m for m in w)
    with pytest.raises(ConfigError, match="after burn-in"):
        dg.mcmc_diagnostics(np.zeros((6, 4, 2)), LABELS)


def test_svgd_diagnostics_and_warnings():
    rng = np.random.default_rng(3)
    n, P = 200, 20
    it = np.arange(n)[:, None]
    converged = -10.0 - 90.0 * np.exp(-it / 10.0) + 0.01 * rng.normal(size=(n, P))
    rising = -10.0 - 90.0 * np.exp(-it / 150.0) + 0.01 * rng.normal(size=(n, P))
    bw = 1.0 + 0.0 * it[:, 0]
    d = dg.svgd_diagnostics(converged, bw)
    m = converged.mean(1)
    np.testing.assert_allclose(
        d["rel_change"], (m[-1] - m[d["window_start"]]) / abs(m[d["window_start"]])
    )
    assert d["window_start"] == n - 1 - 20
    assert dg.convergence_warnings(d, "svgd") == []
    d = dg.svgd_diagnostics(rising, bw)
    assert d["rel_change"] > 0.01
    assert any("still rising" in w for w in dg.convergence_warnings(d, "svgd"))

    collapsing = np.geomspace(1.0, 1e-3, n)
    d = dg.svgd_diagnostics(converged, collapsing, bandwidth_floor=1e-3)
    assert d["bandwidth_collapsed"] and d["bandwidth_rel_change"] < 0
    assert any("collapsed" in w for w in dg.convergence_warnings(d, "svgd"))
    assert not dg.svgd_diagnostics(converged, collapsing, bandwidth_floor=1e-4)[
        "bandwidth_collapsed"
    ]
    assert dg.svgd_diagnostics(converged, np.geomspace(1.0, 1e-4, n))["bandwidth_collapsed"]

    bad = converged.copy()
    bad[-1, :5] = -np.inf
    d = dg.svgd_diagnostics(bad)
    assert d["n_unstable_final"] == 5 and np.isfinite(d["rel_change"])
    assert any("5 of 20 particles" in w for w in dg.convergence_warnings(d, "svgd"))
    with pytest.raises(ConfigError):
        dg.convergence_warnings(d, "hmc")


def test_inference_data_netcdf_round_trip(tmp_path):
    rng = np.random.default_rng(4)
    trace = rng.normal(size=(30, 5, 2))
    lp = rng.normal(size=(30, 5))
    idata = dg.to_inference_data(trace, LABELS, log_density=lp, sampler="sgld")
    assert dict(idata.posterior.sizes) == {"chain": 5, "draw": 30, "param": 2}
    np.testing.assert_array_equal(idata.posterior["theta"].values[2, 7], trace[7, 2])
    np.testing.assert_array_equal(idata.sample_stats["lp"].values[2, 7], lp[7, 2])
    path = tmp_path / "out" / "posterior.nc"
    dg.save_inference_data(idata, path)
    back = arviz_compat.read_netcdf(path)
    np.testing.assert_array_equal(back.posterior["theta"].values, idata.posterior["theta"].values)
    np.testing.assert_array_equal(back.sample_stats["lp"].values, idata.sample_stats["lp"].values)
    assert list(back.posterior["param"].values) == LABELS
    assert back.posterior.attrs["sampler"] == "sgld"
    assert [p.name for p in path.parent.iterdir()] == ["posterior.nc"]  # no temporaries left

    particles = rng.normal(size=(40, 2))
    idata = dg.to_inference_data(
        particles, LABELS, log_density=rng.normal(size=40), sampler="nnsvgd"
    )
    assert dict(idata.posterior.sizes) == {"chain": 1, "draw": 40, "param": 2}
    np.testing.assert_array_equal(idata.posterior["theta"].values[0], particles)
    with pytest.raises(ConfigError, match="log_density"):
        dg.to_inference_data(particles, LABELS, log_density=np.zeros(3))
    with pytest.raises(ConfigError, match="labels"):
        dg.to_inference_data(particles, ["a", "a"])
