"""Simulation-based calibration: the rank / coverage / uniformity machinery against a conjugate
Gaussian model with exact posterior draws (must pass) and too-narrow ones (must fail), the
smoothed-box prior sampler against the prior's own density, and a tiny tree end to end."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import scipy.integrate
import scipy.stats

from treeinfer import calibration as cal
from treeinfer.errors import ConfigError


def _conjugate_study(rng, n_sets=400, n_draws=49, n_obs=5, width=1.0, shift=0.0):
    """mu_d ~ N(0, 1) (D = 2 independent coordinates), y_i ~ N(mu, 1) i.i.d. (n_obs each):
    exact posterior N(sum y / (n + 1), 1 / sqrt(n + 1)); ``width`` scales its std (1: exact),
    ``shift`` moves its mean (in posterior stds)."""
    d = 2
    mu = rng.normal(size=(n_sets, d))
    y = mu[:, None, :] + rng.normal(size=(n_sets, n_obs, d))
    post_mean = y.sum(1) / (n_obs + 1)
    post_std = 1.0 / math.sqrt(n_obs + 1)
    draws = (
        post_mean[:, None, :]
        + shift * post_std
        + width * post_std * rng.normal(size=(n_sets, n_draws, d))
    )
    return mu, draws


def test_exact_posterior_passes_and_covers():
    mu, draws = _conjugate_study(np.random.default_rng(3))
    res = cal.summarize_sbc(mu, draws, ["a", "b"], seed=1)
    assert res.uniformity["pass"], res.uniformity
    assert res.ranks.min() >= 0 and res.ranks.max() <= 49
    for row in cal.coverage_table(res):
        assert row["inside_band"], row
    # the ranks' mean is L / 2 for a calibrated posterior (independent of the tests above)
    assert abs(res.ranks.mean() - 24.5) < 2.0


def test_too_narrow_posterior_fails():
    mu, draws = _conjugate_study(np.random.default_rng(3), width=0.6)
    res = cal.summarize_sbc(mu, draws, ["a", "b"], seed=1)
    assert not res.uniformity["pass"]
    for j in range(2):
        assert res.uniformity["parameters"][["a", "b"][j]]["p_chi2"] < 1e-4
    # over-confident: observed 95% coverage far below 95%
    k95 = res.levels.index(0.95)
    assert np.all(res.coverage[k95] < 0.85)


def test_biased_posterior_fails():
    mu, draws = _conjugate_study(np.random.default_rng(4), shift=0.7)
    res = cal.summarize_sbc(mu, draws, ["a", "b"], seed=1)
    assert not res.uniformity["pass"]


def test_ties_are_broken_uniformly():
    truth = np.zeros((3000, 1))
    draws = np.zeros((3000, 4, 1))  # every draw equals the truth
    ranks = cal.sbc_ranks(truth, draws, np.random.default_rng(0))
    counts = np.bincount(ranks[:, 0], minlength=5)
    assert scipy.stats.chisquare(counts).pvalue > 1e-3


def test_fractional_ranks_exact_uniform_and_coverage_identity():
    rng = np.random.default_rng(0)
    ranks = rng.integers(0, 10, size=(20000, 1))  # discrete uniform on 0..9 (L = 9)
    u = cal.fractional_ranks(ranks, 9, rng)
    assert scipy.stats.kstest(u[:, 0], "uniform").pvalue > 1e-3
    cov = cal.rank_coverage(u, (0.5, 0.9))
    assert np.allclose(cov[:, 0], [0.5, 0.9], atol=0.015)


def test_bad_shapes_raise():
    with pytest.raises(ConfigError):
        cal.sbc_ranks(np.zeros((3, 2)), np.zeros((3, 5, 1)))
    with pytest.raises(ConfigError):
        cal.summarize_sbc(np.zeros((3, 2)), np.zeros((3, 5, 2)), ["a"])


def test_binomial_band_against_normal_approximation():
    lo, hi = cal.binomial_band(10000, 0.1, 0.99)
    s = math.sqrt(10000 * 0.1 * 0.9)
    assert abs(lo - (1000 - 2.576 * s)) < 3 and abs(hi - (1000 + 2.576 * s)) < 3


def test_smoothed_box_draws_follow_the_prior_density():
    from treeinfer.priors import smoothed_box

    lo, hi, s = np.array([1.0]), np.array([3.0]), np.array([0.4])
    x = cal.sample_smoothed_box(np.random.default_rng(0), lo, hi, s, 20000)[:, 0]
    # reference CDF: numerical integral of the normalised density from priors.smoothed_box
    grid = np.linspace(-2.0, 6.0, 8001)
    dens = np.exp(np.asarray(smoothed_box(lo, hi, s, normalized=True)(grid[:, None])))
    cdf = scipy.integrate.cumulative_trapezoid(dens, grid, initial=0.0)
    assert abs(cdf[-1] - 1.0) < 1e-4
    p = scipy.stats.kstest(x, lambda v: np.interp(v, grid, cdf)).pvalue
    assert p > 1e-3


def test_config_checks():
    with pytest.raises(ConfigError, match="likelihood"):
        cal.SBCConfig(likelihood="boltzmann").check()
    with pytest.raises(ConfigError, match="sampler"):
        cal.SBCConfig(sampler="nnsvgd").check()
    with pytest.raises(ConfigError, match="noise_displacement"):
        cal.SBCConfig(noise_displacement=-1.0).check()
    with pytest.raises(ConfigError, match="datasets"):
        cal.SBCConfig(datasets=1).check()


def test_tiny_tree_end_to_end(tmp_path):
    from treeinfer.tree import load_tree

    tree = load_tree("treeinfer/examples/two_branch.yaml")
    cfg = cal.SBCConfig(
        datasets=3,
        particles=4,
        iterations=3,
        mh_warmup=4,
        mh_steps=2,
        n_traj=1,
        duration=0.3,
        chunk=2,
        seed=5,
        test_traj=2,
        noise_force=0.02,
    )
    seen = []
    res = cal.run_tree_sbc(tree, cfg, progress=lambda a, b: seen.append((a, b)))
    assert seen[-1] == (3, 3)
    assert res.draws.shape == (3, 4, 5) and res.labels[-1] == "sigma_x"
    assert np.all(np.isfinite(res.draws))
    summary = cal.write_outputs(res, tmp_path, cal.config_record("two_branch.yaml", cfg))
    for name in (
        "sbc_summary.json",
        "ranks.csv",
        "draws.npz",
        "plots/rank_histograms.png",
        "plots/coverage.png",
    ):
        assert (tmp_path / name).is_file(), name
    on_disk = json.loads((tmp_path / "sbc_summary.json").read_text())
    assert on_disk["n_datasets"] == 3 and set(on_disk["uniformity"]["parameters"]) == set(
        res.labels
    )
    assert summary["config"]["options"]["seed"] == 5
    t = res.info["test_inside_95"]
    assert 0.0 <= t["predictive"]["median"] <= 1.0
    # the predictive band contains the parameter band: never fewer points inside
    assert t["predictive"]["mean"] >= t["parameter"]["mean"] - 1e-12
    assert set(res.info["crb"]["parameters"]) == set(res.labels)
    assert all(np.isfinite(v["ratio_median"]) for v in res.info["crb"]["parameters"].values())
