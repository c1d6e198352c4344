"""Load-cell noise read through each pull's compliance (``make_problem(noise_force=...)``, the
static model): the likelihood against scipy's normal density with the compliance and the noise
composed by hand, and the force-noise estimate from a force signal."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from treeinfer.data.trajectories import Trajectory
from treeinfer.errors import ConfigError
from treeinfer.inference.problem import make_problem
from treeinfer.inference.static import force_noise_estimate, model_rollout
from treeinfer.tree.description import Bounds, Branch, make_tree


def _tree():
    return make_tree(
        [Branch("a", None, 0.2, 0.006), Branch("b", "a", 0.2, 0.005)],
        grasp_branch="b",
        levels=2,
        parameters=("kp",),
        pull_direction="horizontal",
    )


def test_force_noise_likelihood_matches_scipy():
    tree = _tree()
    rng = np.random.default_rng(0)
    t = 0.5 * np.arange(40)
    trajs = [
        Trajectory(t, f, 1e-3 * f * k + 1e-4 * rng.standard_normal(40), source=f"{k}.csv")
        for k, f in ((1.0, 0.02 * np.arange(40)), (3.0, 0.01 * np.arange(40)))
    ]
    p = make_problem(
        tree, trajs, nn_prior=False, likelihood="gaussian", model_kind="static", noise_force=0.05
    )
    assert p.labels == ("Kp[b]", "Kp[a]", "sigma_x") and p.settings["force_noise"] == 0.05
    theta = np.array([[np.log(2.0), np.log(5.0), np.log(2e-4)], [0.5, 1.5, np.log(5e-4)]])
    got = np.asarray(p.log_likelihood(theta))
    tau = np.asarray(model_rollout(p.sim, p.model, theta[:, :2], p.obs.force).tau, float)
    f = np.asarray(p.obs.force, float)
    x = np.asarray(p.obs.displacement, float)
    for i in range(2):
        ref = 0.0
        for b in range(2):
            c = np.linalg.lstsq(f[b][:, None], tau[i, b], rcond=None)[0][0]  # m/N
            sd = np.hypot(np.exp(theta[i, 2]), 0.05 * c)
            ref += stats.norm(tau[i, b], sd).logpdf(x[b]).sum()
        assert got[i] == pytest.approx(ref, rel=2e-4)
    # one meaning of --noise-force: the same "P%" gives P% of the largest recorded force here
    q = make_problem(
        tree, trajs, nn_prior=False, likelihood="gaussian", model_kind="static", noise_force="5%"
    )
    assert q.settings["force_noise"] == pytest.approx(0.05 * np.abs(p.obs.force).max())
    # a dynamic model that is not the paper's (stiffness only) has neither force-noise term
    short = [Trajectory(0.01 * np.arange(20), tr.force[:20], tr.displacement[:20]) for tr in trajs]
    with pytest.raises(ConfigError, match="--noise-force: available for the paper's dynamic"):
        make_problem(
            tree,
            short,
            nn_prior=False,
            likelihood="gaussian",
            model_kind="dynamic",
            noise_force=0.05,
        )


def test_force_noise_estimate_of_a_noisy_ramp():
    rng = np.random.default_rng(1)
    t = 0.5 * np.arange(400)
    f = np.interp(t, [0, 50, 100, 200], [0, 2, 2, 0]) + 0.01 * rng.standard_normal(400)
    est = force_noise_estimate([Trajectory(t, f, np.zeros(400), source="x.csv")])
    assert est == pytest.approx(0.01, rel=0.15)


def _stiff_stem(kp: float):
    """One horizontal branch hinged at its base, pulled down at its tip, stiff enough that
    0.5 N turns it by < 1e-3 rad: the static model is then linear in the force to ~1e-6, with
    compliance ``L^2 / K`` at distance L from the hinge (gravity's settled rest is ~1e-4 rad)."""
    return make_tree(
        [Branch("s", None, 0.2, 0.004)],
        grasp_branch="s",
        grasp_fraction=1.0,
        levels=1,
        bounds=Bounds(kp=(kp / 2, kp * 2), kd=(0.01, 1.0)),
        parameters=("kp",),
    )


def test_static_band_adds_load_cell_noise_through_the_compliance():
    """The predictive band of a static run with ``--noise-force``: with every draw at one known
    stiffness K, each point's predictive distribution is ``N(tau, sigma_x^2 + (sigma_F c)^2)``,
    ``c = L^2 / K`` (closed form), so the 95% band's half-width is 1.96 times that std."""
    from scipy.stats import norm

    from treeinfer.evaluation.predictive import force_noise_for, predict_run
    from treeinfer.inference.static import StaticForceNoise, model_for
    from treeinfer.sim import make_simulator

    kp, length, sx, sf = 200.0, 0.2, 1e-4, 0.5
    tree = _stiff_stem(kp)
    sim = make_simulator(tree, obs_dt=0.5, backend="fused")
    model = model_for(tree, "static")
    force = np.linspace(0.0, 0.5, 12)[None]
    theta = np.full((6, 1), np.log(kp))
    term = force_noise_for({"model_kind": "static", "force_noise": sf})
    assert isinstance(term, StaticForceNoise) and term.sigma_force == sf
    pred = predict_run(sim, theta, force, noise_sigma=sx, model=model, force_noise=term)
    c = length**2 / kp  # m/N
    np.testing.assert_allclose(pred.mean[0], c * force[0], rtol=2e-3, atol=1e-9)
    assert pred.force_variance.shape == (6, 1, 12)
    np.testing.assert_allclose(pred.force_variance, (sf * c) ** 2, rtol=4e-3)
    half = 0.5 * (pred.predictive_upper - pred.predictive_lower)[0]
    np.testing.assert_allclose(half, norm.ppf(0.975) * np.hypot(sx, sf * c), rtol=2e-3)
    # without the term: sigma_x alone; a dynamic run's settings give no static term
    plain = predict_run(sim, theta, force, noise_sigma=sx, model=model)
    np.testing.assert_allclose(
        0.5 * (plain.predictive_upper - plain.predictive_lower)[0], norm.ppf(0.975) * sx, rtol=2e-3
    )
    assert plain.force_variance is None
    assert force_noise_for({"force_noise": sf}) is None  # not static: no static term


def test_band_with_per_particle_extra_variance_is_the_mixture_quantile():
    """``extra_variance [P, *S]`` (each draw's own load-cell term): with equal simulations
    (no KDE spread) the band is the quantile of ``mean_p N(x, sigma^2 + e_p)``, found here with
    scipy's root finder on the mixture's CDF."""
    from scipy.optimize import brentq
    from scipy.stats import norm

    from treeinfer.evaluation.metrics import noisy_predictive_interval

    pred = np.zeros((4, 3))
    extra = np.array([0.0, 1.0, 4.0, 9.0])[:, None] * np.array([1.0, 0.5, 0.0])[None]
    sigma = 1.0
    lo, hi, _ = noisy_predictive_interval(pred, sigma, 0.95, extra_variance=extra)
    for s in range(3):
        sd = np.sqrt(sigma**2 + extra[:, s])

        def cdf(y, q, sd=sd):
            return norm.cdf(y / sd).mean() - q

        assert float(lo[s]) == pytest.approx(brentq(cdf, -50, 50, args=(0.025,)), rel=1e-5)
        assert float(hi[s]) == pytest.approx(brentq(cdf, -50, 50, args=(0.975,)), rel=1e-5)
    with pytest.raises(ConfigError, match="extra_variance"):
        noisy_predictive_interval(pred, sigma, 0.95, extra_variance=np.zeros((4, 2)))
