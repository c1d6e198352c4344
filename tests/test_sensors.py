"""Ranking where to add a sensor (issue 30): the linearised information gain against the same
formula with forward-mode derivatives of the simulator (jax.jacfwd), and its limits."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import treeinfer as ti
from treeinfer.design.sensors import candidate_sensors, rank_sensors, sensors_table
from treeinfer.model.gains import gains_from_theta
from treeinfer.sim import observe as ob

LABELS = ["Kp[child]", "Kp[parent]", "Kd[child]", "Kd[parent]"]


@pytest.fixture(scope="module")
def case():
    tree = ti.load_tree(ti.example_path("two_branch"))
    sim = ti.make_simulator(tree, 0.02, accuracy="coarse")
    forces = ti.data.forces.profile_set("mixed", n=1, duration=1.0, dt=0.02, seed=2)
    rng = np.random.default_rng(0)
    mean = np.log([40.0, 80.0, 0.3, 0.8])
    theta = mean + rng.normal(size=(200, 4)) * np.array([0.05, 0.03, 0.5, 0.1])
    return sim, forces, theta


def test_gain_matches_forward_mode_derivatives(case):
    sim, forces, theta = case
    cand = [("angle", "child", 0.5, "y", 1e-3), ("position", "child", 1.0, "xz", 1e-3)]
    scores = rank_sensors(sim, theta, LABELS, forces, cand)
    assert [s.kind for s in scores] == ["angle", "position"] or len(scores) == 2
    feats = tuple(ob.feature_for(sim, k, link, f) for k, link, f, _, _ in cand)

    def g(th):
        kp, kd = gains_from_theta(th[None], 2)
        return ob.simulate_features(sim, kp, kd, forces, feats).features[0]  # [B, T, F, 3]

    jac = np.asarray(jax.jacfwd(g)(jnp.asarray(theta.mean(0), jnp.float32)), float)
    cov = np.cov(theta, rowvar=False)
    for i, (kind, link, frac, comps, sigma) in enumerate(cand):
        axes = ["xyz".index(c) for c in comps]
        j = jac[:, :, i][..., axes, :].reshape(-1, 4)
        new = np.linalg.inv(np.linalg.inv(cov) + j.T @ j / sigma**2)
        want = 0.5 * (np.linalg.slogdet(cov)[1] - np.linalg.slogdet(new)[1])
        got = next(s for s in scores if s.kind == kind)
        assert got.gain == pytest.approx(want, rel=0.03)
        ratio = np.sqrt(np.diag(cov) / np.diag(new))
        np.testing.assert_allclose(list(got.std_ratio.values()), ratio, rtol=0.03)


def test_a_useless_sensor_gains_nothing(case):
    sim, forces, theta = case
    (s,) = rank_sensors(sim, theta, LABELS, forces, [("position", "parent", 0.5, "xyz", 10.0)])
    assert s.gain == pytest.approx(0.0, abs=1e-3)
    assert all(r == pytest.approx(1.0, abs=1e-3) for r in s.std_ratio.values())
    cands = candidate_sensors(["parent", "child"])
    assert len(cands) == 10 and cands[-1][0] == "angle"
    lines = sensors_table([s])
    assert "position xyz at parent@0.5" in lines[1]


def test_static_model_gain_matches_implicit_derivatives(case):
    """The static model (stiffness only, a cable along a direction): the gain from the
    equilibria's exact implicit derivatives (jax.jacfwd through static_equilibria)."""
    from treeinfer.inference.static import model_for, static_equilibria

    sim, _, _ = case
    tree = ti.load_tree(ti.example_path("two_branch"))
    model = model_for(tree, "static", direction=[0.9, 0.0, -0.44])
    forces = np.linspace(0.0, 4.0, 6)[None]
    rng = np.random.default_rng(1)
    theta = np.log([40.0, 80.0]) + rng.normal(size=(100, 2)) * np.array([0.1, 0.05])
    cand = [("angle", "parent", 0.5, "y", 1e-3), ("position", "child", 1.0, "xz", 1e-3)]
    scores = rank_sensors(sim, theta, LABELS[:2], forces, cand, model=model)
    feats = tuple(ob.feature_for(sim, k, link, f) for k, link, f, _, _ in cand)

    def g(th):  # the channels by hand: features of q minus features of the rest
        eq = static_equilibria(sim, jnp.exp(th)[None], forces, None, model.direction)
        q = jnp.concatenate([eq.q_rest[:, None, None, :], eq.q], axis=2)
        return ob.features_from_q(sim, q, feats)[0, 0, 1:]  # [T, F, 3]

    jac = np.asarray(jax.jacfwd(g)(jnp.asarray(theta.mean(0), jnp.float32)), float)
    cov = np.cov(theta, rowvar=False)
    for i, (kind, link, frac, comps, sigma) in enumerate(cand):
        axes = ["xyz".index(c) for c in comps]
        j = jac[:, i][:, axes, :].reshape(-1, 2)
        new = np.linalg.inv(np.linalg.inv(cov) + j.T @ j / sigma**2)
        want = 0.5 * (np.linalg.slogdet(cov)[1] - np.linalg.slogdet(new)[1])
        got = next(s for s in scores if s.kind == kind)
        assert want > 0.5 and got.gain == pytest.approx(want, rel=0.03)
        assert list(got.std_ratio) == LABELS[:2]
