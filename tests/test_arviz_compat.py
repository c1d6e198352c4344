"""treeinfer.inference.diagnostics.arviz_compat: the same results on ArviZ 0.2x and 1.x (issue 25),
checked against independent references: R-hat against a NumPy/SciPy implementation of Vehtari et al.
(2021), ESS against the closed form of an AR(1) chain, PSIS against
treeinfer.inference.importance.psis (written from Vehtari et al. 2024, equal to ArviZ 0.2x's
psislw)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats as st

from treeinfer.inference.diagnostics import arviz_compat as azc
from treeinfer.inference.importance import psis


def _trace(rng, chains=4, draws=400, d=2, shift=0.0):
    x = rng.normal(size=(chains, draws, d))
    x[0] += shift
    return x


def test_version_and_series():
    major = int(azc.arviz_version().split(".")[0])
    assert azc.is_arviz1() == (major >= 1)


def test_from_dict_netcdf_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    theta, lp, force = rng.normal(size=(3, 20, 2)), rng.normal(size=(3, 20)), rng.normal(size=7)
    idata = azc.from_dict(
        {"theta": theta},
        sample_stats={"lp": lp},
        observed_data={"force": force},
        dims={"theta": ["param"]},
        coords={"param": ["Kp[a]", "Kd[a]"]},
        attrs={"sampler": "sgld", "seed": 3},
    )
    assert dict(idata.posterior.sizes) == {"chain": 3, "draw": 20, "param": 2}
    path = tmp_path / "p.nc"
    azc.write_netcdf(idata, path)
    back = azc.read_netcdf(path)
    np.testing.assert_array_equal(back.posterior["theta"].values, theta)
    np.testing.assert_array_equal(back.sample_stats["lp"].values, lp)
    np.testing.assert_array_equal(back.observed_data["force"].values, force)
    assert list(back.posterior["param"].values) == ["Kp[a]", "Kd[a]"]
    for group in (back.posterior, back.sample_stats, back.observed_data):
        assert group.attrs["sampler"] == "sgld" and int(group.attrs["seed"]) == 3
    path.unlink()  # read_netcdf loaded everything and closed the file


def test_add_group_survives_a_round_trip(tmp_path):
    rng = np.random.default_rng(5)
    idata = azc.from_dict({"theta": rng.normal(size=(2, 6, 3))})
    extra = rng.normal(size=(2, 6))
    assert azc.add_group(idata, "log_posterior", {"lp": extra}, attrs={"units": "nat"}) is idata
    azc.write_netcdf(idata, tmp_path / "g.nc")
    back = azc.read_netcdf(tmp_path / "g.nc")
    np.testing.assert_array_equal(back.log_posterior["lp"].values, extra)
    assert back.log_posterior.attrs["units"] == "nat"


def test_update_attrs_reaches_every_group_and_survives_a_round_trip(tmp_path):
    """Attributes set after the data exist (run_figures' run attributes): every group on both
    series (a 1.x DataTree's ``groups`` is a tuple, not 0.2x's method), and its root on 1.x."""
    rng = np.random.default_rng(7)
    idata = azc.from_dict(
        {"theta": rng.normal(size=(2, 5, 2))}, sample_stats={"lp": np.ones((2, 5))}
    )
    azc.update_attrs(idata, {"likelihood": "gaussian", "n_train": 2})
    azc.write_netcdf(idata, tmp_path / "a.nc")
    back = azc.read_netcdf(tmp_path / "a.nc")
    assert sorted(azc.group_names(back)) == ["posterior", "sample_stats"]
    for name in azc.group_names(back):
        assert (
            back[name].attrs["likelihood"] == "gaussian" and int(back[name].attrs["n_train"]) == 2
        )
    if azc.is_arviz1():
        assert back.attrs["likelihood"] == "gaussian"


def test_convert_to_dataset_of_an_array():
    x = np.arange(24.0).reshape(2, 4, 3)
    ds = azc.convert_to_dataset(x)
    assert dict(ds["x"].sizes) == {"chain": 2, "draw": 4, "x_dim_0": 3}
    np.testing.assert_array_equal(ds["x"].values, x)


def _rhat_reference(x):
    """Rank-normalised split R-hat (Vehtari et al. 2021, eqs. in section 4.1) of ``x [chain,
    draw]``: the larger of the bulk (rank-normalised) and tail (folded, then
    rank-normalised) split R-hats."""

    def split(a):
        half = a.shape[1] // 2
        return np.concatenate([a[:, :half], a[:, -half:]])

    def z(a):
        r = st.rankdata(a, method="average").reshape(a.shape)
        return st.norm.ppf((r - 0.375) / (a.size + 0.25))

    def classic(a):
        m, n = a.shape
        w = a.var(axis=1, ddof=1).mean()
        b = n * a.mean(axis=1).var(ddof=1)
        return np.sqrt(((n - 1) / n * w + b / n) / w)

    s = split(x)
    return max(classic(z(s)), classic(z(np.abs(s - np.median(s)))))


@pytest.mark.parametrize("shift", [0.0, 1.0, 3.0])
def test_rhat_matches_the_reference(shift):
    x = _trace(np.random.default_rng(1), shift=shift)
    got = azc.rhat(x)["x"].values
    ref = [_rhat_reference(x[:, :, i]) for i in range(x.shape[2])]
    np.testing.assert_allclose(got, ref, rtol=1e-10)
    assert (got.max() > 1.05) == (shift > 0)


def test_ess_of_an_ar1_chain_matches_the_closed_form():
    """AR(1) with coefficient rho: ESS = N (1 - rho) / (1 + rho) for the mean."""
    rng = np.random.default_rng(2)
    rho, chains, draws = 0.6, 4, 5000
    x = np.zeros((chains, draws, 1))
    eps = rng.normal(size=(chains, draws)) * np.sqrt(1 - rho**2)
    x[:, 0, 0] = rng.normal(size=chains)
    for t in range(1, draws):
        x[:, t, 0] = rho * x[:, t - 1, 0] + eps[:, t]
    expected = chains * draws * (1 - rho) / (1 + rho)
    bulk = float(azc.ess(x)["x"].values[0])
    assert bulk == pytest.approx(expected, rel=0.15)
    iid = rng.normal(size=(chains, draws, 1))
    assert float(azc.ess(iid, "tail")["x"].values[0]) == pytest.approx(chains * draws, rel=0.15)


def test_summary_columns_and_values():
    x = _trace(np.random.default_rng(3))
    idata = azc.from_dict({"theta": x}, dims={"theta": ["param"]}, coords={"param": ["a", "b"]})
    table = azc.summary(idata, var_names=["theta"])
    assert list(table.columns) == list(azc.SUMMARY_COLUMNS)
    assert list(table.index) == ["theta[a]", "theta[b]"]
    flat = x.reshape(-1, 2)
    np.testing.assert_allclose(table["mean"], flat.mean(0), rtol=1e-12)
    np.testing.assert_allclose(table["sd"], flat.std(0, ddof=1), rtol=1e-6)
    np.testing.assert_allclose(table["r_hat"], azc.rhat(idata)["theta"].values, rtol=1e-12)
    ess_bulk = azc.ess(idata, "bulk", var_names=["theta"])["theta"].values
    np.testing.assert_allclose(table["ess_bulk"], ess_bulk, rtol=1e-12)


def test_summary_table_names_the_interval_as_0_2x():
    x = np.random.default_rng(6).normal(size=(1, 400, 1))
    idata = azc.from_dict({"theta": x})
    table = azc.summary_table(idata, kind="stats", hdi_prob=0.9)
    assert {"mean", "sd", "hdi_5%", "hdi_95%"} <= set(table.columns)
    lo, hi = float(table["hdi_5%"].iloc[0]), float(table["hdi_95%"].iloc[0])
    inside = np.mean((x >= lo) & (x <= hi))
    assert 0.88 <= inside <= 0.92  # 0.2x rounds the bounds to 2 decimals
    assert "r_hat" in azc.summary_table(idata, kind="all").columns


# ---- PSIS -------------------------------------------------------------------------------------

# light tails (normal log weights, small scale) to heavy (Student-t 3 log weights, large scale)
CASES = [("normal", 0.3), ("normal", 1.0), ("t3", 1.0), ("t3", 2.5)]


def _log_weights(kind, scale, n, seed=4):
    rng = np.random.default_rng(seed)
    return scale * (rng.normal(size=n) if kind == "normal" else rng.standard_t(3, size=n))


@pytest.mark.parametrize("kind, scale", CASES)
@pytest.mark.parametrize("n", [100, 900, 3600])
def test_psis_equals_treeinfers_where_the_tail_lengths_agree(kind, scale, n):
    """M = 100, 900, 3600: M / 5 and 3 sqrt(M) are whole numbers, so both ArviZ series cut the
    same tail as importance.psis: equal to rounding."""
    lw = _log_weights(kind, scale, n)
    ours, k = psis(lw)
    got, k_az = azc.psis_log_weights(lw)
    np.testing.assert_allclose(got, ours, rtol=1e-10, atol=1e-10)
    assert k_az == pytest.approx(k, rel=1e-10)
    assert np.logaddexp.reduce(got) == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("kind, scale", CASES)
def test_psis_close_to_treeinfers_elsewhere(kind, scale):
    """M = 3000: ArviZ 1.x fits a tail one weight shorter (164 against 165, it rounds 3 sqrt(M)
    down); 0.2x is equal to rounding."""
    lw = _log_weights(kind, scale, 3000)
    ours, k = psis(lw)
    got, k_az = azc.psis_log_weights(lw)
    if azc.is_arviz1():
        assert abs(k_az - k) < 0.05 and (k_az > 0.7) == (k > 0.7)
        w, w_ref = np.exp(got), np.exp(ours)
        assert np.abs(w - w_ref).sum() < 0.05  # total variation of the normalised weights
    else:
        np.testing.assert_allclose(got, ours, rtol=1e-10, atol=1e-12)
        assert k_az == pytest.approx(k, rel=1e-10)


def test_psis_heavier_tails_give_larger_k():
    ks = [azc.psis_log_weights(_log_weights("normal", s, 3600))[1] for s in (0.3, 1.0, 2.5)]
    assert ks[0] < ks[1] < ks[2] and ks[0] < 0.5 < 0.7 < ks[2]


def test_psis_without_a_fittable_tail_is_unreliable():
    lw = np.array([0.0, -1.0, -2.0, 0.5, -0.3, 0.1, -0.7])  # 7 weights: a tail of 1
    got, k = azc.psis_log_weights(lw)
    assert k == np.inf
    np.testing.assert_allclose(got, lw - np.logaddexp.reduce(lw))
    with pytest.raises(ValueError, match="finite"):
        azc.psis_log_weights([0.0, np.inf, 1.0])
