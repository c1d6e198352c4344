"""The static pulling model with inclinometers (treeinfer.inference.pulltest): the chain's tilts
against independent closed forms (one rotational spring; the two-link chain's equilibrium
solved by hand with scipy), the beam baseline against numerical integration, and NUTS on
synthetic static data recovering the truth within its interval."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import quad
from scipy.optimize import fsolve

from treeinfer.data import PullSetup
from treeinfer.inference.pulltest import (
    BeamFit,
    beam_predict,
    fit_beam,
    fit_pull_test,
    fit_springs,
    initial_stiffness,
    model_tilts,
    predictive_band,
    pull_model,
    springs_predict,
)

G = 9.81
SETUP = PullSetup(
    name="synthetic",
    height=6.0,
    circumference_cm=(50.0,),
    sling_height=1.9,
    anchor_sling_height=0.35,
    anchor_distance=10.5,
    root_clino_height=1.0,
    trunk_clino_height=2.3,
)
KP = np.array([4.0e5, 2.5e5])  # root, stem: the README's scale for halloran_10


@pytest.fixture(scope="module")
def model():
    return pull_model(SETUP)


def hand_chain(model, kp, f):
    """The two-link chain's equilibrium written out: tilts (psi1, psi1 + psi2) from vertical
    toward the anchor (+x). Torques about the y-axis of a force (Fx, Fz) at (x, z): z Fx - x Fz;
    gravity acts at each link's centre of mass."""
    m = model.sim.mj_model
    l1 = model.tree.branch("root").length
    frac = model.load_fraction
    l2 = model.tree.branch("stem").length
    masses = [float(m.body_mass[1]), float(m.body_mass[2])]
    coms = [float(m.body_ipos[1][0]), float(m.body_ipos[2][0])]  # along each link
    a = model.cable_angle
    fx, fz = f * math.cos(a), -f * math.sin(a)

    def eqs(p):
        p1, p12 = p[0], p[0] + p[1]
        u1, u2 = np.array([math.sin(p1), math.cos(p1)]), np.array([math.sin(p12), math.cos(p12)])
        e1 = l1 * u1
        s = e1 + frac * l2 * u2  # the sling
        c1, c2 = coms[0] * u1, e1 + coms[1] * u2
        tau_f0 = s[1] * fx - s[0] * fz
        tau_f1 = (s - e1)[1] * fx - (s - e1)[0] * fz
        g0 = masses[0] * G * c1[0] + masses[1] * G * c2[0]
        g1 = masses[1] * G * (c2 - e1)[0]
        return [kp[0] * p[0] - tau_f0 - g0, kp[1] * p[1] - tau_f1 - g1]

    p = fsolve(eqs, [0.0, 0.0], xtol=1e-13)
    return np.array([p[0], p[0] + p[1]])


def test_chain_layout(model):
    assert model.sensors == {"root": "root", "trunk": "stem"}
    assert model.load_branch == "stem"
    assert model.load_fraction == pytest.approx(0.9 / 5.0)
    assert model.cable_angle == pytest.approx(math.atan(1.55 / 10.5))


def test_two_link_chain_against_the_hand_solution(model):
    forces = np.array([0.0, 500.0, 2000.0, 8000.0])
    tilts, ok = model_tilts(model, jnp.asarray(KP[None]), jnp.asarray(forces))
    assert bool(ok[0])
    want = np.stack([hand_chain(model, KP, f) for f in forces], axis=1)
    assert want[0, -1] > 0.03  # 2 degrees: the cos/sin terms matter
    np.testing.assert_allclose(np.asarray(tilts[0]), want, rtol=2e-4, atol=1e-8)


def test_single_rotational_spring_closed_form(model):
    """Small angles: angle = F h cos(a) / K at the root clino (the whole stem turns on the root
    spring), plus F (h - h_root) cos(a) / K_stem at the trunk clino (two springs in series);
    gravity's P-Delta (m g c / K) is below 0.1% here."""
    f = np.array([100.0, 300.0])
    k_root, k_stem = 2.0e7, 1.0e8
    tilts, _ = model_tilts(model, jnp.asarray([[k_root, k_stem]]), jnp.asarray(f))
    ca = math.cos(model.cable_angle)
    closed = f * SETUP.sling_height * ca / k_root
    m = model.sim.mj_model
    pdelta = sum(float(m.body_mass[b]) * G * float(m.body_ipos[b][0]) for b in (1, 2)) / k_root
    assert pdelta < 1e-3
    np.testing.assert_allclose(np.asarray(tilts[0, 0]), closed, rtol=2e-3)
    trunk = closed + f * (SETUP.sling_height - SETUP.root_clino_height) * ca / k_stem
    np.testing.assert_allclose(np.asarray(tilts[0, 1]), trunk, rtol=2e-3)


def test_gradients_match_the_hand_solution(model):
    f = 3000.0

    def tilt(log_kp):
        t, _ = model_tilts(model, jnp.exp(log_kp)[None], jnp.asarray([f]))
        return t[0, :, 0]

    jac = np.asarray(jax.jacrev(tilt)(jnp.log(jnp.asarray(KP))))
    h = 1e-4
    fd = np.stack(
        [
            (hand_chain(model, KP * np.exp(h * e), f) - hand_chain(model, KP * np.exp(-h * e), f))
            / (2 * h)
            for e in np.eye(2)
        ],
        axis=1,
    )
    np.testing.assert_allclose(jac, fd, rtol=2e-3, atol=1e-7)


def test_beam_design_against_integrated_curvature():
    """theta(z) = F cos a [h/K + integral_0^z M(s)/(F cos a EI) ds], M(s) = F cos a (h - s)."""
    k, ei, h, a, f = 3.0e5, 2.0e6, 1.9, 0.15, 1200.0
    heights = [0.8, 1.9, 2.6]
    fit = BeamFit(k, ei, (1 / k, 1 / ei), 0.0)
    got = beam_predict(fit, heights, h, a, np.array([f]))[:, 0]
    want = [
        f * math.cos(a) * (h / k + quad(lambda s: max(h - s, 0.0) / ei, 0, z, points=[h])[0])
        for z in heights
    ]
    np.testing.assert_allclose(got, want, rtol=1e-9)
    # least squares recovers the compliances from noise-free tilts
    force = np.linspace(0, 2000, 30)
    y = beam_predict(fit, heights, h, a, force)
    back = fit_beam(heights, h, a, force, y)
    assert back.k_root == pytest.approx(k, rel=1e-6) and back.ei == pytest.approx(ei, rel=1e-6)
    ks = fit_springs(h, a, force, y)
    np.testing.assert_allclose(springs_predict(ks, h, a, force), y, rtol=1e-9, atol=1e-15)


def test_nuts_recovers_synthetic_stiffness_and_noise(model):
    """Synthetic static pull (a 40-sample ramp to 3 kN, noise 0.01 and 0.02 deg): the 95%
    intervals hold the truth, and the predictive band covers ~95% of a fresh noisy ramp."""
    rng = np.random.default_rng(3)
    force = np.linspace(20.0, 3000.0, 40)
    clean, _ = model_tilts(model, jnp.asarray(KP[None]), jnp.asarray(force))
    sigma = np.deg2rad([0.01, 0.02])
    y = np.asarray(clean[0]) + sigma[:, None] * rng.standard_normal((2, force.size))
    y[1, 5] = np.nan  # a missing reading is skipped, not fitted
    k0 = initial_stiffness(model, force, y)
    np.testing.assert_allclose(k0, KP, rtol=0.1)
    post = fit_pull_test(model, force, y, num_warmup=150, num_samples=250, num_chains=1, seed=1)
    s = post.summary()
    assert post.diagnostics["divergences"] == 0
    for j, name in enumerate(("root", "stem")):
        assert s[f"kp_{name}"]["q2.5"] < KP[j] < s[f"kp_{name}"]["q97.5"], s
        assert s[f"kp_{name}"]["sd"] / KP[j] < 0.05  # informative
    for c, name in enumerate(("root", "trunk")):
        assert s[f"sigma_{name}"]["q2.5"] < sigma[c] < s[f"sigma_{name}"]["q97.5"], s
    fresh = np.asarray(clean[0]) + sigma[:, None] * rng.standard_normal((2, force.size))
    band = predictive_band(model, post, force, n_draws=200)
    inside = (fresh >= band["lo"]) & (fresh <= band["hi"])
    assert 0.85 <= inside.mean() <= 1.0
    # a band from a wrong stiffness would not cover: the test can fail
    off = np.asarray(model_tilts(model, jnp.asarray([KP * 0.8]), jnp.asarray(force))[0][0])
    assert ((off >= band["lo"]) & (off <= band["hi"])).mean() < 0.5


@pytest.mark.slow  # 31 s of NUTS on a 2-core box; the white-noise NUTS test stays by default
def test_ar1_noise_widens_the_stiffness_interval_and_keeps_the_truth(model):
    """Residuals with a slow AR(1) part (rho 0.95 per sample): the i.i.d. model's stiffness
    intervals are too narrow; ``noise="ar1"`` holds the truth with wider intervals."""
    rng = np.random.default_rng(5)
    n = 120
    force = np.linspace(20.0, 3000.0, n)
    clean, _ = model_tilts(model, jnp.asarray(KP[None]), jnp.asarray(force))
    rho, s_a, s_w = 0.95, np.deg2rad(0.02), np.deg2rad(0.003)
    slow = np.zeros((2, n))
    slow[:, 0] = s_a * rng.standard_normal(2)
    for t in range(1, n):
        slow[:, t] = rho * slow[:, t - 1] + math.sqrt(1 - rho**2) * s_a * rng.standard_normal(2)
    y = np.asarray(clean[0]) + slow + s_w * rng.standard_normal((2, n))
    kw = dict(num_warmup=150, num_samples=250, num_chains=1, seed=2)
    iid = fit_pull_test(model, force, y, **kw)
    ar1 = fit_pull_test(model, force, y, noise="ar1", **kw)
    s = ar1.summary()
    for j, name in enumerate(("root", "stem")):
        assert s[f"kp_{name}"]["q2.5"] < KP[j] < s[f"kp_{name}"]["q97.5"], s
        ratio = np.std(np.log(ar1.kp[:, j])) / np.std(np.log(iid.kp[:, j]))
        assert ratio > 1.5, (name, ratio)
    assert set(ar1.noise_params) == {"sigma_w", "sigma_a", "tau_ar", "rho"}
    np.testing.assert_allclose(
        ar1.sigma, np.hypot(ar1.noise_params["sigma_w"], ar1.noise_params["sigma_a"])
    )
    assert np.median(ar1.noise_params["rho"]) > 0.8
