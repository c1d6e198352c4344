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
    from treeinfer.model.priors import smoothed_box

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
    with pytest.raises(ConfigError, match="smc_particles"):
        cal.SBCConfig(smc_particles=8, particles=16).check()
    with pytest.raises(ConfigError, match="smc_target_ess"):
        cal.SBCConfig(smc_target_ess=1.0).check()


@pytest.mark.parametrize("sampler", ["smc", "mh"])
@pytest.mark.slow  # an SBC study, however tiny
def test_tiny_tree_end_to_end(tmp_path, sampler):
    from treeinfer.tree.description import load_tree

    tree = load_tree("treeinfer/examples/two_branch.yaml")
    cfg = cal.SBCConfig(
        sampler=sampler,
        smc_particles=8,
        smc_levels=3,
        smc_mutations=1,
        smc_final=1,
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


# ---- the SMC sampler against posteriors known in closed form -------------------------------


def _linear_gaussian(rng, n_sets, dim=2, m=12, s0=3.0, sig=0.05):
    """Prior N(0, s0^2 I), y = A x + N(0, sig^2): truths, data, exact posterior means/cov."""
    a = rng.normal(size=(m, dim))
    truth = s0 * rng.normal(size=(n_sets, dim))
    y = truth @ a.T + sig * rng.normal(size=(n_sets, m))
    cov = np.linalg.inv(a.T @ a / sig**2 + np.eye(dim) / s0**2)
    mean = (cov @ (a.T @ y.T) / sig**2).T
    return a, truth, y, mean, cov, s0, sig


def _smc_batch(a, y, x0, s0, sig, **kw):
    import jax
    import jax.numpy as jnp

    def one(key, yy, xx):
        return cal.tempered_smc(
            key,
            xx,
            lambda x: -0.5 * jnp.sum(x**2, -1) / s0**2,
            lambda x: -0.5 * jnp.sum((yy - x @ jnp.asarray(a.T, x.dtype)) ** 2, -1) / sig**2,
            **kw,
        )

    keys = jax.random.split(jax.random.key(3), y.shape[0])
    x, info = jax.jit(jax.vmap(one))(
        keys, jnp.asarray(y, jnp.float32), jnp.asarray(x0, jnp.float32)
    )
    return np.asarray(x, float), info


def test_smc_matches_linear_gaussian_posterior_and_passes_sbc():
    """Conjugate model (posterior N(mean, cov) in closed form): the SMC cloud's moments match
    it per data set, and over 100 data sets the ranks of the truths among 32 draws pass the
    same uniformity test as the tree study."""
    rng = np.random.default_rng(0)
    n_sets, n = 100, 128
    a, truth, y, mean, cov, s0, sig = _linear_gaussian(rng, n_sets)
    x0 = s0 * rng.normal(size=(n_sets, n, 2))
    x, info = _smc_batch(a, y, x0, s0, sig, n_levels=24, n_mutations=4, n_final=10)
    assert np.all(np.asarray(info.beta_reached) == 1.0)  # the ladder reached beta = 1 itself
    sd = np.sqrt(np.diag(cov))
    z = (x.mean(1) - mean) / sd  # Monte Carlo error ~ 1 / sqrt(ESS)
    assert np.sqrt(np.mean(z**2)) < 0.25
    ratio = np.mean(x.std(1), 0) / sd
    assert np.all(np.abs(ratio - 1.0) < 0.1), ratio
    res = cal.summarize_sbc(truth, x[:, :32], ["x0", "x1"])
    assert res.uniformity["pass"], res.uniformity
    assert np.all(np.abs(res.coverage[-1] - 0.95) < 0.08)


def test_smc_weights_separated_modes_like_the_exact_posterior():
    """y = x^2 + noise, prior N(0.7, 1): modes at +-1 with unequal mass (exact by quadrature).
    A sampler started at the best mode puts all mass on one side; SMC keeps both shares."""
    import scipy.integrate

    s0, mu0, sig, yobs = 1.0, 0.7, 0.1, 1.0
    grid = np.linspace(-4, 4, 40001)
    dens = np.exp(-0.5 * ((grid - mu0) / s0) ** 2 - 0.5 * ((yobs - grid**2) / sig) ** 2)
    exact = scipy.integrate.trapezoid(dens * (grid > 0), grid) / scipy.integrate.trapezoid(
        dens, grid
    )
    import jax
    import jax.numpy as jnp

    rng = np.random.default_rng(1)
    c, n = 8, 256
    x0 = mu0 + s0 * rng.normal(size=(c, n, 1))

    def one(key, xx):
        return cal.tempered_smc(
            key,
            xx,
            lambda x: -0.5 * jnp.sum((x - mu0) ** 2, -1) / s0**2,
            lambda x: -0.5 * jnp.sum((yobs - x**2) ** 2, -1) / sig**2,
            n_levels=16,
            n_mutations=4,
            n_final=5,
        )

    x, _ = jax.jit(jax.vmap(one))(jax.random.split(jax.random.key(0), c), jnp.asarray(x0))
    share = float(np.mean(np.asarray(x) > 0))
    assert 0.6 < exact < 0.95  # both modes matter
    assert abs(share - exact) < 0.06, (share, exact)


def test_cli_names_the_smc_flag_on_bad_sizes(tmp_path, capsys):
    from treeinfer.cli import main

    rc = main(
        [
            "calibrate",
            "--tree",
            "treeinfer/examples/two_branch.yaml",
            "--out",
            str(tmp_path / "sbc"),
            "--particles",
            "16",
            "--smc-particles",
            "8",
        ]
    )
    assert rc == 2
    assert "--smc-particles" in capsys.readouterr().err
    assert not (tmp_path / "sbc").exists()


def test_unstable_truths_are_redrawn(monkeypatch):
    """A prior draw whose simulation is unstable is redrawn (the GPU run of three_branch hit
    this path: device arrays came back read-only and the redraw's assignment failed)."""
    import treeinfer.calibration.study as study
    from treeinfer.tree.description import load_tree

    real = study._simulate_truths
    calls = []

    def flaky(sim, truth, forces, r):
        tau, stable = real(sim, truth, forces, r)
        calls.append(int(truth.shape[0]))
        if len(calls) == 1:  # first call: mark data set 1 unstable
            stable = stable.at[1].set(False)
        return tau, stable

    monkeypatch.setattr(study, "_simulate_truths", flaky)
    tree = load_tree("treeinfer/examples/two_branch.yaml")
    cfg = cal.SBCConfig(
        smc_particles=8, smc_levels=2, smc_mutations=1, smc_final=1, datasets=3, particles=4,
        n_traj=1, duration=0.3, chunk=3, seed=2, test_traj=1,
    )  # fmt: skip
    res = cal.run_tree_sbc(tree, cfg)
    assert calls[:2] == [3, 1]  # all truths, then the one redraw
    assert np.all(np.isfinite(res.draws))
    assert res.info["n_redrawn_unstable_truths"] == 1


def test_sbc_figures_in_every_format_asked(tmp_path):
    # calibrate --formats: the rank histograms and coverage plot in each format, written whole
    mu, draws = _conjugate_study(np.random.default_rng(4))
    res = cal.summarize_sbc(mu, draws, ["a", "b"], seed=1)
    cal.write_outputs(res, tmp_path, formats=("png", "svg"))
    for stem in ("rank_histograms", "coverage"):
        png, svg = tmp_path / "plots" / f"{stem}.png", tmp_path / "plots" / f"{stem}.svg"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert b"<svg" in svg.read_bytes()[:2000]
    assert not list(tmp_path.rglob("*.tmp")) and not list(tmp_path.rglob(".*"))
