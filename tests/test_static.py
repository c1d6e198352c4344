"""Tests for treeinfer.inference.static: quasi-static equilibria, the quasi-static detector, theta
layout."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import brentq

from treeinfer.data.pulls import pull_direction
from treeinfer.errors import ConfigError
from treeinfer.examples import example_path
from treeinfer.inference.static import (
    damping_note,
    natural_periods,
    parameter_layout,
    parse_parameters,
    static_rollout,
    suggest_static,
)
from treeinfer.sim import make_simulator, simulate
from treeinfer.sim.reference import _c_model, settle_reference
from treeinfer.tree.description import Branch, load_tree, make_tree

G = 9.81


def one_joint(pitch_deg: float):
    tree = make_tree(
        [Branch("b", None, 0.8, 0.02)],
        grasp_branch="b",
        grasp_fraction=1.0,
        base_pitch_deg=pitch_deg,
    )
    return tree, make_simulator(tree, obs_dt=0.5, backend="fused")


def test_one_joint_horizontal_branch_pulled_down():
    """Kp psi = (m g c + F a) cos psi (psi downward): drop of the grasp point a (sin psi)."""
    _, sim = one_joint(0.0)
    m = float(sim.mj_model.body_mass[1])
    c = float(sim.mj_model.body_ipos[1][0])  # centre of mass along the branch
    assert c == pytest.approx(0.4)
    kp, a = 40.0, 0.6
    forces = np.array([[0.0, 5.0, 20.0, 60.0]])

    def psi(f):
        return brentq(lambda p: kp * p - (m * G * c + f * a) * math.cos(p), -1.5, 1.5)

    want = np.array([a * (math.sin(psi(f)) - math.sin(psi(0.0))) for f in forces[0]])
    r = static_rollout(sim, jnp.array([[kp]]), forces, grasp_fraction=a / 0.8)
    assert bool(r.stable[0, 0])
    assert want[-1] > 0.3  # a large deflection: the non-linear (cos psi) regime
    np.testing.assert_allclose(np.asarray(r.tau[0, 0]), want, rtol=2e-4, atol=1e-6)


def test_one_joint_derivatives_by_the_implicit_function_theorem():
    """d tau / d log Kp of the static model (``lax.custom_root``), reverse and forward mode,
    against the closed form: ``G(psi, K) = K psi - (m g c + F a) cos psi = 0`` gives
    ``dpsi/dK = -psi / (K + (m g c + F a) sin psi)``; the second derivative against central
    differences of that closed form."""
    import jax

    _, sim = one_joint(0.0)
    m = float(sim.mj_model.body_mass[1])
    c = float(sim.mj_model.body_ipos[1][0])
    a, forces = 0.6, np.array([[0.0, 5.0, 20.0, 60.0]])

    def closed(kp):  # [T] d tau / d log Kp
        def psi(f):
            return brentq(lambda p: kp * p - (m * G * c + f * a) * math.cos(p), -1.5, 1.5)

        def dpsi(f):
            p = psi(f)
            return -p / (kp + (m * G * c + f * a) * math.sin(p))

        return np.array(
            [
                a * kp * (math.cos(psi(f)) * dpsi(f) - math.cos(psi(0.0)) * dpsi(0.0))
                for f in forces[0]
            ]
        )

    def tau(log_kp):  # [T]
        r = static_rollout(sim, jnp.exp(log_kp)[None, None], forces, grasp_fraction=a / 0.8)
        return r.tau[0, 0]

    lk = jnp.asarray(math.log(40.0))
    want = closed(40.0)
    assert abs(want[-1]) > 0.1  # the non-linear regime: a large, force-dependent sensitivity
    np.testing.assert_allclose(np.asarray(jax.jacfwd(tau)(lk)), want, rtol=2e-3, atol=1e-6)
    np.testing.assert_allclose(np.asarray(jax.jacrev(tau)(lk)), want, rtol=2e-3, atol=1e-6)
    h = 1e-3  # second derivative: d/dlogK of the closed form's first, by central differences
    want2 = (closed(40.0 * math.exp(h)) - closed(40.0 * math.exp(-h))) / (2 * h)
    got2 = np.asarray(jax.jacfwd(jax.jacrev(tau))(lk))
    np.testing.assert_allclose(got2, want2, rtol=1e-2, atol=1e-5)


def test_one_joint_vertical_stem_pushed_sideways():
    """Vertical stem, horizontal push at height a: Kp psi = F a cos psi + m g c sin psi."""
    tree, sim = one_joint(90.0)
    m = float(sim.mj_model.body_mass[1])
    c = float(sim.mj_model.body_ipos[1][0])
    kp, a = 30.0, 0.5
    f = np.array([0.0, 2.0, 8.0, 20.0])

    def psi(force):
        return brentq(
            lambda p: kp * p - force * a * math.cos(p) - m * G * c * math.sin(p), -1.2, 1.2
        )

    want = np.array([a * math.sin(psi(x)) for x in f])
    r = static_rollout(
        sim, jnp.array([[kp]]), f[None], grasp_fraction=a / 0.8, direction=[1.0, 0.0, 0.0]
    )
    np.testing.assert_allclose(np.asarray(r.tau[0, 0]), want, rtol=2e-4, atol=1e-6)
    # 'horizontal' for a vertical stem is its hinge's bending direction (here -x): by symmetry
    # the same displacement along it
    h = pull_direction(tree, "b", "horizontal")
    np.testing.assert_allclose(np.abs(h), [1.0, 0.0, 0.0], atol=1e-12)
    r2 = static_rollout(sim, jnp.array([[kp]]), f[None], grasp_fraction=a / 0.8, direction=h)
    np.testing.assert_allclose(np.asarray(r2.tau), np.asarray(r.tau), rtol=1e-5, atol=1e-7)


def _c_pull(sim, kp, kd, force, direction, frac):
    """Plain MuJoCo C (mj_step, float64): the grasp point's displacement along ``direction``
    under ``force`` [T] held per observation interval (an independent reference)."""
    import mujoco

    m = _c_model(sim, kp, kd, frac)
    d = mujoco.MjData(m)
    d.qpos[:] = settle_reference(m)
    mujoco.mj_forward(m, d)
    sid, bid = sim.grasp_site, sim.grasp_body
    c_rest = d.site_xpos[sid].copy()
    out = []
    for f in force:
        for _ in range(sim.substeps):
            fv = f * np.asarray(direction, float)
            d.xfrc_applied[:] = 0
            d.xfrc_applied[bid, :3] = fv
            d.xfrc_applied[bid, 3:] = np.cross(d.site_xpos[sid] - d.xipos[bid], fv)
            mujoco.mj_step(m, d)
        out.append(d.site_xpos[sid].copy())
    return (np.asarray(out) - c_rest) @ np.asarray(direction, float)


@pytest.fixture(scope="module")
def three():
    tree = load_tree(example_path("three_branch"))
    return tree, make_simulator(tree, obs_dt=0.1, backend="fused")


KP3 = np.array([60.0, 150.0, 300.0])


def test_three_joints_match_slow_dynamic_pull_down(three):
    """A long ramp and hold with heavy damping ends at the static equilibrium (fused simulate)."""
    _, sim = three
    t = 0.1 * np.arange(120)
    forces = np.stack([np.clip(t / 6.0, 0, 1) * 10.0, np.clip(t / 6.0, 0, 1) * 4.0])
    dyn = simulate(
        sim,
        jnp.asarray(KP3[None]),
        jnp.full((1, 3), 9.0),
        jnp.asarray(forces),
        jnp.asarray([1.0, 0.5]),
    )
    st = static_rollout(sim, jnp.asarray(KP3[None]), forces, grasp_fraction=[1.0, 0.5])
    assert np.asarray(st.stable).all() and np.asarray(dyn.stable).all()
    assert float(st.tau[0, 0, -1]) > 0.02
    np.testing.assert_allclose(
        np.asarray(st.tau[0, :, -1]), np.asarray(dyn.tau[0, :, -1]), atol=2e-4
    )
    # quasi-static all along the slow ramp too (the branch follows the force)
    np.testing.assert_allclose(
        np.asarray(st.tau[0, 0, 70:]), np.asarray(dyn.tau[0, 0, 70:]), atol=5e-4
    )


def test_three_joints_sideways_match_mujoco_c(three):
    """A sideways push (any direction): equilibrium = the end of a slow, damped C rollout."""
    tree, sim = three
    h = pull_direction(tree, tree.grasp_branch, "horizontal")
    push = np.array([1.0, 0.3, 0.2]) / np.linalg.norm([1.0, 0.3, 0.2])
    force = np.concatenate([np.linspace(0, 6.0, 40), np.full(40, 6.0)])
    st = static_rollout(
        sim,
        jnp.asarray(KP3[None]),
        np.stack([force, force]),
        grasp_fraction=0.8,
        direction=np.stack([h, push]),
    )
    for b, d in enumerate((h, push)):
        ref = _c_pull(sim, KP3, np.full(3, 9.0), force, d, 0.8)
        np.testing.assert_allclose(float(st.tau[0, b, -1]), ref[-1], atol=2e-4)
    # this tree's hinges all bend in one vertical plane: a horizontal push perpendicular to the
    # branch acts along the hinge axes and moves nothing; the oblique push does
    assert abs(ref[-1]) > 0.003


def test_several_branches_and_flags(three):
    tree, sim = three
    f = np.tile(np.linspace(0, 5, 6), (3, 1))
    r = static_rollout(
        sim,
        jnp.asarray(np.stack([KP3, 2 * KP3])),
        f,
        grasp_fraction=[1.0, 1.0, 0.5],
        grasp_branch=["branch2", "branch1", "branch2"],
        tree=tree,
    )
    assert r.tau.shape == (2, 3, 6) and np.asarray(r.stable).all()
    tau = np.asarray(r.tau)
    np.testing.assert_allclose(tau[:, :, 0], 0.0, atol=1e-6)
    assert np.all(tau[0] >= tau[1] - 1e-7)  # stiffer deflects less
    assert tau[0, 1, -1] < tau[0, 0, -1]  # nearer the trunk deflects less
    with pytest.raises(ConfigError, match="pass the tree"):
        static_rollout(sim, jnp.asarray(KP3[None]), f, grasp_branch=["branch1"] * 3)
    with pytest.raises(ConfigError, match="non-zero"):
        static_rollout(sim, jnp.asarray(KP3[None]), f, direction=[0, 0, 0])


def test_natural_period_and_detector():
    """1 joint, horizontal: omega^2 = K_eff / I with K_eff = Kp - m g c sin(psi0) ... checked
    against the textbook pendulum-spring formula at the settled angle."""
    _, sim = one_joint(0.0)
    m = sim.mj_model
    kp = 40.0
    mass, c = float(m.body_mass[1]), float(m.body_ipos[1][0])
    inertia = float(m.body_inertia[1][1]) + mass * c**2 + float(m.dof_armature[0])
    psi0 = brentq(lambda p: kp * p - mass * G * c * math.cos(p), -1.5, 1.5)
    k_eff = kp + mass * G * c * math.sin(psi0)  # d/dpsi of (Kp psi - m g c cos psi)
    want = 2 * math.pi / math.sqrt(k_eff / inertia)
    periods = natural_periods(sim, [kp])
    assert periods[0] == pytest.approx(want, rel=1e-4)
    assert suggest_static(0.01, sim, [kp]) is None
    msg = suggest_static(100 * want, sim, [kp])
    assert msg is not None and "--model-kind static" in msg and "100x" in msg


def test_parameter_layout(three):
    tree, _ = three
    full = parameter_layout(tree)
    assert full.dim == 6 and full.labels[3] == "Kd[branch2]"
    only = parameter_layout(tree, ["kp"], fixed_kd=2.0)
    assert only.dim == 3 and only.labels == ["Kp[branch2]", "Kp[branch1]", "Kp[branch0]"]
    theta = only.theta([[10.0, 20.0, 30.0]])
    kp, kd = only.gains(jnp.asarray(theta))
    np.testing.assert_allclose(np.asarray(kp), [[10, 20, 30]], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(kd), [[2, 2, 2]], rtol=1e-6)
    np.testing.assert_allclose(
        np.asarray(only.full_theta(jnp.asarray(theta)))[0, 3:], np.log(2.0), rtol=1e-6
    )
    np.testing.assert_allclose(only.lower, np.log([5.0] * 3))
    default_kd = parameter_layout(tree, ["kp"]).fixed_kd
    np.testing.assert_allclose(default_kd, math.sqrt(0.05 * 10.0))
    assert parse_parameters(["KD", "kp"]) == ("kp", "kd")
    for bad in (["kd"], ["kp", "kp"], ["mass"], []):
        with pytest.raises(ConfigError):
            parse_parameters(bad)
    assert "not identified" in damping_note(only, "static")
    assert "held at" in damping_note(only, "dynamic")


def test_quasi_static_notice_on_the_stem():
    """The synthetic stem pushes (0.5 s samples) are quasi-static for the 3-link chain."""
    from treeinfer.inference.static import quasi_static_notice
    from treeinfer.tree.stem import Stem, stem_tree

    tree = stem_tree(Stem())
    # the notice reads the model (masses, joints) only: the stability step spares the accuracy
    # probes of the default step (seconds of 2,000-substep rollouts)
    sim = make_simulator(tree, obs_dt=0.5, backend="fused", accuracy="coarse")
    msg = quasi_static_notice(tree, sim, 0.5)
    assert msg is not None and "quasi-static" in msg
    assert quasi_static_notice(tree, sim, 1e-4) is None
