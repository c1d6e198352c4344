"""Stragglers, kernelized Stein discrepancy and early stopping (issue 11 section 3)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from treeinfer.errors import ConfigError
from treeinfer.inference import diagnostics as dg
from treeinfer.inference.samplers import run, svgd

# ------------------------------------------------------------------ the issue's stuck case

KP_BOX = np.log([5.0, 500.0])
KD_BOX = np.log([0.05, 10.0])
LOWER = np.array([KP_BOX[0], KD_BOX[0]])
UPPER = np.array([KP_BOX[1], KD_BOX[1]])


def issue_case(seed=0):
    """32 particles of (log Kp, log Kd): 25 good ones with log p in -25 ... -9 near the truth
    (Kd 1.23), 7 stuck at log p ~ -296 with Kd 219 ... 394 (the issue's numbers)."""
    rng = np.random.default_rng(seed)
    good = np.column_stack(
        [
            np.log(150.0) + 0.1 * rng.standard_normal(25),
            np.log(1.23) + 0.2 * rng.standard_normal(25),
        ]
    )
    stuck = np.column_stack(
        [np.log(150.0) + 0.1 * rng.standard_normal(7), np.log(rng.uniform(219.0, 394.0, 7))]
    )
    theta = np.concatenate([good, stuck])
    ld = np.concatenate([rng.uniform(-25.0, -9.0, 25), -296.0 + rng.uniform(-2.0, 2.0, 7)])
    perm = rng.permutation(32)
    return theta[perm], ld[perm], perm >= 25


def test_issue_case_is_warned_with_counts():
    theta, ld, truth = issue_case()
    rep = dg.find_stragglers(ld, theta, LOWER, UPPER, labels=["Kp[branch0]", "Kd[branch0]"])
    np.testing.assert_array_equal(rep.mask, truth)
    assert rep.n_stragglers == 7 and rep.n_particles == 32
    np.testing.assert_array_equal(rep.low_density, truth)
    np.testing.assert_array_equal(rep.outside_box, truth)  # Kd 219-394 vs box [0.05, 10]
    text = " ".join(rep.warnings)
    assert "7 of 32 particles are stuck" in text and "Kd[branch0]" in text


def test_each_reason_alone():
    theta, ld, truth = issue_case(1)
    inside = theta.copy()
    inside[truth, 1] = np.log(1.0)  # stuck in log density only, inside the box
    rep = dg.find_stragglers(ld, inside, LOWER, UPPER)
    np.testing.assert_array_equal(rep.low_density, truth)
    assert not rep.outside_box.any()
    good_ld = ld.copy()
    good_ld[truth] = -12.0  # far outside the box only
    rep = dg.find_stragglers(good_ld, theta, LOWER, UPPER)
    assert not rep.low_density.any()
    np.testing.assert_array_equal(rep.outside_box, truth)
    bad = ld.copy()
    bad[0] = -np.inf
    rep = dg.find_stragglers(bad, theta, LOWER, UPPER)
    assert rep.nonfinite[0] and rep.mask[0] and "non-finite" in rep.warnings[-1]


def test_no_false_alarm_on_posterior_draws():
    """Draws from a Gaussian posterior in D = 6 (log p spread ~ chi2_6 / 2) inside the box:
    nothing flagged over 200 sets of 32 particles."""
    rng = np.random.default_rng(3)
    lo, hi = -np.ones(6) * 5, np.ones(6) * 5
    flagged = 0
    for _ in range(200):
        x = 0.3 * rng.standard_normal((32, 6))
        ld = -0.5 * np.sum((x / 0.3) ** 2, 1) - 20.0
        flagged += dg.find_stragglers(ld, x, lo, hi).n_stragglers
    assert flagged == 0


def test_bad_input():
    theta, ld, _ = issue_case()
    with pytest.raises(ConfigError):
        dg.find_stragglers(ld[:5], theta, LOWER, UPPER)
    with pytest.raises(ConfigError):
        dg.find_stragglers(ld, theta, UPPER, LOWER)
    with pytest.raises(ConfigError):
        dg.find_stragglers(ld, theta, LOWER, UPPER, z_max=-1.0)


def test_reinit_moves_only_stragglers_next_to_the_bulk():
    theta, ld, truth = issue_case()
    theta = theta.astype(np.float32)
    new = np.asarray(dg.reinit_stragglers(jax.random.key(0), theta, truth, jitter=0.1))
    np.testing.assert_array_equal(new[~truth], theta[~truth])
    good = theta[~truth]
    assert np.all(new[truth] > good.min(0) - 0.2) and np.all(new[truth] < good.max(0) + 0.2)
    assert not np.any(np.all(new[truth][:, None] == good[None], -1))  # jittered, not copies
    again = np.asarray(dg.reinit_stragglers(jax.random.key(0), theta, truth, jitter=0.1))
    np.testing.assert_array_equal(new, again)
    all_bad = np.asarray(dg.reinit_stragglers(jax.random.key(0), theta, np.ones(32, bool)))
    np.testing.assert_array_equal(all_bad, theta)  # nothing good to copy: unchanged
    kept, kept_ld = dg.drop_stragglers(theta, ld, truth)
    assert kept.shape == (25, 2) and np.all(kept_ld > -30)


# ------------------------------------------------------------------ kernelized Stein discrepancy


def _stein_kernel_autodiff(x, y, sx, sy, c=1.0, beta=-0.5):
    """u_p(x, y) from autodiff of the IMQ kernel (independent of the closed form)."""
    k = lambda a, b: (c**2 + jnp.sum((a - b) ** 2)) ** beta
    gx = jax.grad(k, 0)(x, y)
    gy = jax.grad(k, 1)(x, y)
    tr = jnp.trace(jax.jacfwd(jax.grad(k, 0), 1)(x, y))
    return sx @ sy * k(x, y) + sx @ gy + sy @ gx + tr


def test_ksd_closed_form_matches_autodiff():
    rng = np.random.default_rng(0)
    x = rng.standard_normal((7, 3))
    s = rng.standard_normal((7, 3))
    u = np.array(
        [[_stein_kernel_autodiff(x[i], x[j], s[i], s[j]) for j in range(7)] for i in range(7)]
    )
    want = np.sqrt(u.mean())
    got = float(dg.kernel_stein_discrepancy(x, s, standardise=False))
    assert got == pytest.approx(want, rel=1e-5)


def test_ksd_small_for_target_draws_and_shrinks_large_when_shifted():
    """Target N(0, diag(sd^2)) in D = 3 (score -x / sd^2)."""
    sd = np.array([0.1, 1.0, 30.0])  # very different units: standardising handles them
    rng = np.random.default_rng(1)

    def ksd(n, shift=0.0, seed=0):
        x = sd * np.random.default_rng(seed).standard_normal((n, 3)) + shift * sd
        return float(dg.kernel_stein_discrepancy(x, -x / sd**2))

    small = np.mean([ksd(100, seed=s) for s in range(5)])
    large_n = np.mean([ksd(1600, seed=s) for s in range(5)])
    # V-statistic: KSD^2 = O(1/N), so 16x the particles -> ~1/4 of the KSD
    assert large_n < 0.4 * small
    assert ksd(100, shift=1.0) > 3 * small
    too_narrow = 0.5 * sd * rng.standard_normal((400, 3))  # spread half the target's
    narrow = float(dg.kernel_stein_discrepancy(too_narrow, -too_narrow / sd**2))
    assert narrow > 2 * np.mean([ksd(400, seed=s) for s in range(5)])


def test_moment_change():
    rng = np.random.default_rng(2)
    a = rng.standard_normal((500, 2))
    assert dg.moment_change(a, a) == 0.0
    want = 0.5 / a[:, 0].std(ddof=1)
    assert dg.moment_change(a, a + np.array([0.5, 0.0])) == pytest.approx(want, rel=1e-6)
    assert dg.moment_change(a, 2 * a) == pytest.approx(np.log(2), rel=1e-6)


# ------------------------------------------------------------------ driver: early stop, re-init


def _gauss_vg(mu, sd):
    mu, sd = jnp.asarray(mu), jnp.asarray(sd)

    def vg(theta):
        z = (theta - mu) / sd
        return -0.5 * jnp.sum(z * z, -1), -z / sd

    return vg


def test_svgd_stops_when_converged_and_reports_why():
    alg = svgd(_gauss_vg([1.0, -2.0], [0.5, 2.0]), learning_rate=0.1)
    x0 = jax.random.normal(jax.random.key(0), (40, 2))
    crit = dg.ConvergenceCriterion(min_iterations=50, moment_tol=0.02, ksd_rtol=0.05, window=10)
    res = run(alg, 0, x0, 2000, progress=False, chunk_size=25, stop_when=crit)
    n = res.settings["n_iterations_done"]
    assert res.stop_reason.startswith(f"converged at iteration {n}") and 50 <= n < 2000
    assert res.trace_positions.shape == (n + 1, 40, 2)
    assert res.diagnostics["ksd"].shape == (n,)
    np.testing.assert_array_equal(res.trace_iterations, np.arange(n + 1))
    # it did converge: moments near the target's
    np.testing.assert_allclose(res.final_positions.mean(0), [1.0, -2.0], atol=0.15)
    # never satisfied -> runs to the end
    full = run(alg, 0, x0, 60, progress=False, chunk_size=20, stop_when=lambda *a: None)
    assert full.stop_reason == "max_iterations" and full.settings["n_iterations_done"] == 60


def test_reinit_stragglers_in_the_driver_is_exact_on_resume():
    """A bimodal-looking start: 6 of 24 particles start deep in the tail (log p ~ -200)."""
    vg = _gauss_vg([0.0, 0.0], [1.0, 1.0])
    alg = svgd(vg, learning_rate=1e-3)  # small steps: they would stay stuck for the run
    x0 = np.array(jax.random.normal(jax.random.key(1), (24, 2)))
    x0[:6] += 20.0
    pol = dg.ReinitStragglers(until=20, lower=[-3.0, -3.0], upper=[3.0, 3.0])
    res = run(alg, 0, x0, 40, progress=False, chunk_size=10, reinit_stragglers=pol)
    n_re = res.diagnostics["n_reinitialised"]
    assert n_re.shape == (40,) and n_re[9] == 6 and n_re.sum() == 6
    rep = dg.find_stragglers(res.final_state.logdensity, res.final_positions, pol.lower, pol.upper)
    assert rep.n_stragglers == 0
    # without the remedy they stay and are reported
    plain = run(alg, 0, x0, 40, progress=False, chunk_size=10)
    rep = dg.find_stragglers(
        plain.final_state.logdensity, plain.final_positions, pol.lower, pol.upper
    )
    assert rep.n_stragglers == 6
    # resume from iteration 10 reproduces the uninterrupted run
    first = run(alg, 0, x0, 10, progress=False, chunk_size=10, reinit_stragglers=pol)
    rest = run(
        alg,
        0,
        None,
        40,
        progress=False,
        chunk_size=10,
        reinit_stragglers=pol,
        initial_state=first.final_state,
        start_iteration=10,
    )
    np.testing.assert_array_equal(rest.final_positions, res.final_positions)


# ------------------------------------------------------------------ MCMC draws, prior edge


def test_mcmc_draws_discard_warmup_and_thin():
    S, C, D = 10, 3, 2
    trace = np.arange(S * C * D, dtype=float).reshape(S, C, D)
    d = dg.mcmc_draws(trace, 4, thin=2)
    np.testing.assert_array_equal(d, trace[[4, 6, 8]].reshape(-1, D))
    np.testing.assert_array_equal(dg.mcmc_draws(trace, 0.5), trace[5:].reshape(-1, D))
    bad = trace.copy()
    bad[7, 1, 0] = np.nan
    assert dg.mcmc_draws(bad, 5).shape == (5 * C - 1, D)
    for w in (10, -1, 1.0, True):
        with pytest.raises(ConfigError):
            dg.mcmc_draws(trace, w)
    with pytest.raises(ConfigError):
        dg.mcmc_draws(trace, 0, thin=0)


def test_mcmc_summary_uses_every_chain_after_warmup():
    """AR(1) chains started far away: the post-warm-up draws have the stationary moments."""
    rng = np.random.default_rng(0)
    S, C, rho = 2000, 8, 0.5
    x = np.empty((S, C, 1))
    x[0] = 50.0
    for t in range(1, S):
        x[t] = rho * x[t - 1] + np.sqrt(1 - rho**2) * rng.standard_normal((C, 1))
    s = dg.mcmc_summary(x, ["a"], warmup=100, thin=2)
    assert s["n_draws"] == C * (S - 100) // 2 and s["draws"].shape == (s["n_draws"], 1)
    assert abs(s["draws"].mean()) < 0.1 and s["draws"].std() == pytest.approx(1.0, abs=0.1)
    p = s["diagnostics"]["parameters"]["a"]
    assert p["rhat"] < 1.01
    # ESS of an AR(1) chain: n (1 - rho) / (1 + rho) per chain
    assert p["ess_bulk"] == pytest.approx(C * (S - 100) / 3, rel=0.25)
    final_only = x[-1, :, 0]
    assert final_only.size == C  # what summaries used before: 8 draws


def test_prior_edge_mass_flags_piling_up():
    rng = np.random.default_rng(0)
    theta = np.column_stack([rng.uniform(0.0, 1.0, 200), rng.normal(1.0, 0.1, 200)])
    out = dg.prior_edge_mass(theta, [0.0, 0.0], [1.0, 1.0], labels=["a", "b"])
    assert out["parameters"]["a"] == {"below": 0.0, "above": 0.0}
    assert out["parameters"]["b"]["above"] == pytest.approx(0.5, abs=0.1)
    assert len(out["warnings"]) == 1 and out["warnings"][0].startswith("b:")


def test_svgd_diagnostics_warn_while_ksd_still_falls():
    ld = np.tile(np.linspace(-10, -9.99, 50)[:, None], (1, 8))
    falling = np.linspace(2.0, 0.5, 50)
    d = dg.svgd_diagnostics(ld, ksd_trace=falling)
    assert d["ksd_final"] == pytest.approx(0.5) and d["ksd_rel_change"] < -0.1
    assert any("Stein" in m for m in dg.convergence_warnings(d, "svgd"))
    flat = dg.svgd_diagnostics(ld, ksd_trace=np.full(50, 0.5))
    assert not dg.convergence_warnings(flat, "svgd")
