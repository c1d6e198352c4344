"""Noise models, noise estimation, kT rule and the finite-difference custom_jvp, against
independent references (scipy.stats, closed-form posteriors, jax.grad, numerical grids)."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from treeinfer.data.trajectories import Trajectory, stack_trajectories, velocity_from_displacement
from treeinfer.errors import ConfigError
from treeinfer.model import noise
from treeinfer.model.gradients import (
    autodiff_value_and_grad,
    central_difference_jacobian,
    finite_difference_jvp,
)
from treeinfer.model.likelihood import (
    DEFAULT_KT,
    auto_kT,
    suggest_kT,
    trajectory_loss,
)
from treeinfer.sim import Rollout


def _smooth_pull(t, amp=0.05, omega=8.0, zeta=0.3):
    """Step response of a damped oscillator (m): smooth, like a branch pulled by a ramp."""
    wd = omega * math.sqrt(1 - zeta**2)
    return amp * (
        1 - np.exp(-zeta * omega * t) * (np.cos(wd * t) + zeta * omega / wd * np.sin(wd * t))
    )


def _trajs(sigma, n=4, T=301, dt=0.01, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(T) * dt
    out = []
    for b in range(n):
        x = _smooth_pull(t, amp=0.03 + 0.01 * b) + sigma * rng.standard_normal(T)
        out.append(Trajectory(t, np.ones(T), x, None, f"p{b}"))
    return out


# --------------------------------------------------------------------------- densities


@pytest.mark.parametrize("kind", ["gaussian", "student_t"])
def test_residual_log_prob_matches_scipy(kind):
    r = np.linspace(-0.02, 0.03, 11)
    s = 0.004
    got = np.asarray(noise.residual_log_prob(jnp.asarray(r), s, kind, 4.0))
    ref = stats.norm.logpdf(r, scale=s) if kind == "gaussian" else stats.t.logpdf(r, 4.0, scale=s)
    np.testing.assert_allclose(got, ref, rtol=1e-5)
    q = noise.standard_quantile(0.975, kind, 4.0)
    assert q == pytest.approx(
        stats.norm.ppf(0.975) if kind == "gaussian" else stats.t.ppf(0.975, 4)
    )


# --------------------------------------------------------------------------- estimation


@pytest.mark.parametrize("sigma", [0.001, 0.002, 0.005])
def test_noise_estimate_recovers_sigma(sigma):
    est = noise.estimate_displacement_noise(_trajs(sigma))
    assert est.sigma == pytest.approx(sigma, rel=0.10)
    assert est.n_used == 4 * 299
    assert "mm" in est.describe()


def test_noise_estimate_ignores_padding():
    """Padding (last value repeated) must not pull the MAD towards 0."""
    short = _trajs(0.002, n=2, T=120)
    long = _trajs(0.002, n=1, T=301, seed=3)
    est = noise.estimate_displacement_noise(stack_trajectories(short + long))
    assert est.sigma == pytest.approx(0.002, rel=0.12)
    assert est.n_used == 2 * 118 + 299


def test_noise_estimate_too_short_and_noise_free():
    with pytest.raises(ConfigError, match="too short to estimate"):
        noise.estimate_displacement_noise(_trajs(0.002, n=1, T=10))
    t = np.arange(50) * 0.01
    flat = [Trajectory(t, np.ones(50), np.zeros(50), None, "flat")]
    with pytest.raises(ConfigError, match="cannot estimate"):
        noise.estimate_displacement_noise(flat)


@pytest.mark.parametrize("bad", [-0.001, 0.0, float("nan"), float("inf"), "abc"])
def test_bad_sigma_names_the_field(bad):
    with pytest.raises(ConfigError, match="noise_displacement"):
        noise.check_sigma(bad, "noise_displacement")


def test_absurd_sigma_larger_than_data_range():
    obs = stack_trajectories(_trajs(0.002))
    rng_ = noise.displacement_range(obs)
    assert noise.check_sigma(0.002, "noise_displacement", rng_) == 0.002
    with pytest.raises(ConfigError, match="noise_displacement.*larger than the whole range"):
        noise.check_sigma(2 * rng_, "noise_displacement", rng_)


# --------------------------------------------------------------------------- kT rule


def test_kT_rule_matches_gaussian_posterior_width():
    """The kT rule is meant to give the Boltzmann loss (position + differentiated velocity) the
    curvature of the Gaussian likelihood. Check on a toy 'simulator' tau = a * s(t), whose exact
    Gaussian posterior (flat prior on a) has std sigma / ||s|| summed over trajectories."""
    sigma, dt, T = 0.002, 0.01, 301
    rng = np.random.default_rng(1)
    t = np.arange(T) * dt
    shapes = np.stack([_smooth_pull(t, amp=0.04 + 0.01 * b) for b in range(5)])
    y = shapes + sigma * rng.standard_normal(shapes.shape)
    trajs = [Trajectory(t, np.ones(T), y[b], None, f"p{b}") for b in range(5)]
    obs = stack_trajectories(trajs)
    choice = auto_kT(obs)
    a = np.linspace(0.97, 1.03, 601)
    tau = a[:, None, None] * shapes[None]
    ro = Rollout(
        jnp.asarray(tau, jnp.float32),
        jnp.asarray(velocity_from_displacement(tau, dt), jnp.float32),
        jnp.ones(tau.shape[:2], bool),
    )
    ll = -np.asarray(trajectory_loss(ro, obs), float).sum(-1) / choice.kT
    w = np.exp(ll - ll.max())
    w /= w.sum()
    mean = np.sum(w * a)
    std_boltzmann = math.sqrt(np.sum(w * (a - mean) ** 2))
    std_gauss = sigma / math.sqrt(np.sum(shapes**2))
    assert std_boltzmann == pytest.approx(std_gauss, rel=0.3)
    # ... while the paper-reproduction default is far wider (not a noise-level rule)
    assert DEFAULT_KT / choice.kT > 50
    assert "kT auto" in choice.describe() and "sqrt(T)" in choice.describe()


def test_suggest_kT_values_and_checks():
    assert suggest_kT(0.002, 301, 0.01) == pytest.approx(0.002 / math.sqrt(301))
    assert suggest_kT(0.002, 100, 0.01, omega2=100.0) == pytest.approx(
        0.0002 * (1 + math.sqrt(2) * 0.01 * 100)
    )
    with pytest.raises(ConfigError, match="sigma_displacement"):
        suggest_kT(-1.0, 301, 0.01)


# --------------------------------------------------------------------------- custom_jvp


def _smooth_batch(theta):
    """[N, 3] -> [N, 2, 4]: a smooth nonlinear vector function."""
    s = jnp.linspace(0.0, 1.0, 4)
    a = jnp.sin(theta[:, 0:1] * 1.3 + s) * jnp.exp(0.2 * theta[:, 1:2]) + theta[:, 2:3] ** 2 * s
    return jnp.stack([a, jnp.cos(a) * theta[:, 0:1]], axis=1)


def test_finite_difference_jvp_matches_jax_grad():
    theta = jnp.asarray(np.random.default_rng(0).normal(size=(5, 3)), jnp.float32)
    wrapped = finite_difference_jvp(_smooth_batch, rel_step=1e-2)
    np.testing.assert_allclose(wrapped(theta), _smooth_batch(theta), rtol=1e-6)

    def scalar(f):
        return lambda th: jnp.sum(jnp.tanh(f(th)) ** 2)

    g_fd = jax.grad(scalar(wrapped))(theta)
    g_ad = jax.grad(scalar(_smooth_batch))(theta)
    np.testing.assert_allclose(g_fd, g_ad, rtol=2e-3, atol=2e-4)
    # forward mode and under jit as well
    t = jnp.ones_like(theta)
    _, j_fd = jax.jit(lambda x: jax.jvp(wrapped, (x,), (t,)))(theta)
    _, j_ad = jax.jvp(_smooth_batch, (theta,), (t,))
    np.testing.assert_allclose(j_fd, j_ad, rtol=2e-3, atol=2e-4)


def test_central_difference_jacobian_one_batched_call():
    calls = []

    def f(th):
        calls.append(th.shape)
        return _smooth_batch(th)

    value, jac = central_difference_jacobian(f, jnp.zeros((4, 3)), rel_step=1e-2)
    assert calls == [(4 * 7, 3)] and value.shape == (4, 2, 4) and jac.shape == (4, 2, 4, 3)


def test_joint_sigma_inference_closed_form_with_nuts():
    """y = a x + e, e ~ N(0, sigma): (a, log sigma) inferred jointly by numpyro's NUTS through the
    finite-difference custom_jvp 'black box' a -> a x. Reference: the exact posterior (flat prior
    on a; log sigma ~ Normal(log sigma_hat, 1.5) from treeinfer.model.noise) on a 1-D grid in log
    sigma with a | sigma ~ N(a_hat, sigma^2 / sum x^2) integrated analytically."""
    from numpyro.infer import MCMC, NUTS

    rng = np.random.default_rng(4)
    n, a_true, s_true = 40, 1.7, 0.3
    x = np.linspace(-1, 1, n)
    y = a_true * x + s_true * rng.standard_normal(n)
    prior = noise.log_sigma_prior(0.5)  # deliberately off-centre: the data must win
    model_out = finite_difference_jvp(lambda th: th[:, :1] * jnp.asarray(x, jnp.float32), 1e-3)

    def logdensity(theta):  # theta [N, 2] = [a, log sigma]
        mu = model_out(theta[:, :1])
        lp = noise.residual_log_prob(jnp.asarray(y, jnp.float32) - mu, jnp.exp(theta[:, 1:2]))
        return jnp.sum(lp, -1) + prior(theta[:, 1])

    mcmc = MCMC(
        NUTS(potential_fn=lambda th: -logdensity(th[None])[0]),
        num_warmup=400,
        num_samples=1500,
        progress_bar=False,
    )
    mcmc.run(jax.random.key(0), init_params=jnp.zeros(2))
    s = np.asarray(mcmc.get_samples())

    sxx = np.sum(x**2)
    a_hat = np.sum(x * y) / sxx
    rss = np.sum((y - a_hat * x) ** 2)
    ls = np.linspace(-3, 1, 4001)
    sig = np.exp(ls)
    logpost = (
        -(n - 1) * ls
        - rss / (2 * sig**2)
        + stats.norm.logpdf(ls, math.log(0.5), noise.SIGMA_PRIOR_SCALE)
    )
    w = np.exp(logpost - logpost.max())
    w /= w.sum()
    m_ls = np.sum(w * ls)
    sd_ls = math.sqrt(np.sum(w * (ls - m_ls) ** 2))
    sd_a = math.sqrt(np.sum(w * sig**2) / sxx)
    assert np.mean(s[:, 0]) == pytest.approx(a_hat, abs=0.15 * sd_a * 3)
    assert np.std(s[:, 0]) == pytest.approx(sd_a, rel=0.15)
    assert np.mean(s[:, 1]) == pytest.approx(m_ls, abs=0.3 * sd_ls)
    assert np.std(s[:, 1]) == pytest.approx(sd_ls, rel=0.15)
    # and autodiff_value_and_grad (what treeinfer's samplers call) sees the same gradient
    th = jnp.asarray([[1.5, -1.0], [2.0, -1.5]], jnp.float32)
    _, g = autodiff_value_and_grad(logdensity)(th)
    res = y[None] - np.asarray(th[:, :1]) * x
    sg = np.exp(np.asarray(th[:, 1]))
    ga = np.sum(res * x, 1) / sg**2
    gs = -n + np.sum(res**2, 1) / sg**2 - (np.asarray(th[:, 1]) - math.log(0.5)) / 1.5**2
    np.testing.assert_allclose(np.asarray(g), np.stack([ga, gs], 1), rtol=2e-3)


def test_ar1_white_kalman_matches_dense_mvn():
    """The Kalman-filter likelihood of white + AR(1) residuals equals the dense multivariate
    normal with covariance sigma_w^2 I + sigma_c^2 rho^|i-j| (scipy), padding excluded."""
    rng = np.random.default_rng(5)
    T = 40
    mask = np.ones((2, T), bool)
    mask[1, 25:] = False  # a shorter trajectory, padded
    res = rng.normal(0, 0.003, size=(3, 2, T))
    sw = np.array([0.002, 0.001, 0.003])
    sc = np.array([0.003, 0.0005, 0.001])
    rho = np.array([0.95, 0.3, 0.0])
    got = np.asarray(
        noise.ar1_white_log_prob(
            jnp.asarray(res), jnp.asarray(mask), jnp.asarray(sw), jnp.asarray(sc), jnp.asarray(rho)
        ),
        float,
    )
    lag = np.abs(np.subtract.outer(np.arange(T), np.arange(T)))
    for n in range(3):
        ref = 0.0
        for b in range(2):
            m = mask[b]
            cov = sw[n] ** 2 * np.eye(T) + sc[n] ** 2 * rho[n] ** lag
            ref += stats.multivariate_normal(np.zeros(m.sum()), cov[np.ix_(m, m)]).logpdf(
                res[n, b, m]
            )
        assert got[n] == pytest.approx(ref, rel=2e-4)
