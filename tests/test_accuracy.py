"""Simulator accuracy against an independent reference (tests/planar_chain.py: Lagrange's
equations of planar hinge chains integrated by scipy's DOP853 at rtol 1e-11).

The reference is itself checked first: against the closed-form step response of the linearised
one-joint branch, and against MuJoCo C converging to it as its step shrinks (same physics,
written independently). Then the default simulator (first-order hold of the forces and the
accuracy-controlled step) must agree with it within 0.1 mm over 3 s pulls on 1-, 2- and 3-joint
chains with stiff and soft gains.
"""

from __future__ import annotations

import math
from dataclasses import replace

import jax.numpy as jnp
import numpy as np
import pytest
from planar_chain import PlanarTree

from treeinfer.data import forces as F
from treeinfer.errors import ConfigError
from treeinfer.sim import DEFAULT_SIM_TOLERANCE, make_simulator, simulate
from treeinfer.sim.accuracy import choose_substeps_for_accuracy, default_tolerance
from treeinfer.sim.reference import _c_model, settle_reference, simulate_reference
from treeinfer.tree.description import Bounds, cylinder_inertia
from treeinfer.tree.generators import chain

DT = 0.01
DURATION = 3.0


def _chain(n: int, kp_box=(5.0, 500.0), kd_box=(0.05, 10.0)):
    """1 to 3 tapering branches in a vertical plane, grasped at 90% of the last one."""
    return chain(
        n,
        [0.8, 0.6, 0.4][-n:],
        [0.025, 0.015, 0.01][-n:],
        angles_deg=[10.0, 15.0, -10.0][:n],
        grasp_fraction=0.9,
        bounds=Bounds(kp=kp_box, kd=kd_box),
        base_pitch_deg=5.0,
    )


def _profiles():
    """[2, 300] N: a ramp-hold-release (the branch swings back) and a smooth step."""
    return np.stack(
        [
            F.ramp_hold(6.0, 0.5, 0.5, 0.3, DURATION, DT, start=0.2),
            F.smooth_step(4.0, 0.3, DURATION, DT, start=0.1),
        ]
    )


# ---- the reference itself ------------------------------------------------------------------
def test_reference_matches_the_linearised_step_response():
    """A small force step on one joint: J x'' + Kd x' + k_eff x = a cos(phi) F, in closed form,
    with J = I_c + m (L/2)^2 and k_eff = Kp - m g (L/2) sin(phi) at the rest elevation phi."""
    tree = _chain(1)
    kp, kd, force = 20.0, 0.05, 0.01
    ref = PlanarTree(tree, [kp], [kd])
    b = tree.branches[0]
    m, inertia = cylinder_inertia(b, tree.density)
    half, a = b.length / 2, 0.9 * b.length
    phi = ref.phi(ref.q_rest)[0]
    # the rest pose balances the spring and gravity
    assert kp * ref.q_rest[0] == pytest.approx(m * 9.81 * half * math.cos(phi), rel=1e-9)
    j = inertia[1] + m * half**2
    k_eff = kp - m * 9.81 * half * math.sin(phi)
    w0, zeta = math.sqrt(k_eff / j), kd / (2 * math.sqrt(k_eff * j))
    wd = w0 * math.sqrt(1 - zeta**2)
    profile = np.full(100, force)
    profile[0] = 0.0  # held: the step acts from t = DT
    tau = ref.rollout(profile, DT, "hold")
    t = np.arange(100) * DT - DT
    # joint angle x(t) under the torque a cos(phi) F; tau = a cos(phi) x along gravity
    x_static = a * math.cos(phi) * force / k_eff
    shape = 1 - np.exp(-zeta * w0 * t) * (np.cos(wd * t) + zeta * w0 / wd * np.sin(wd * t))
    expected = a * math.cos(phi) * x_static * np.where(t > 0, shape, 0.0)
    np.testing.assert_allclose(tau, expected, atol=2e-3 * np.max(expected))
    assert np.max(tau) > 1.5 * a * math.cos(phi) * x_static  # overshoot: the dynamics are tested


def test_mujoco_converges_to_the_reference():
    """MuJoCo C (float64) on the 3-joint chain: the same rest pose, and an error that halves
    with the step (first order) towards the reference: both model the same physics."""
    tree = _chain(3)
    kp, kd = np.array([60.0, 30.0, 15.0]), np.array([0.6, 0.3, 0.1])
    ref = PlanarTree(tree, kp, kd)
    sim = make_simulator(tree, obs_dt=DT, substeps=50)  # its MuJoCo model (C path below)
    q_c = settle_reference(_c_model(sim, kp, kd))
    np.testing.assert_allclose(q_c, ref.q_rest, atol=1e-9)
    force = F.ramp_hold(3.0, 0.3, 0.2, 0.2, 1.0, DT)
    expected = ref.rollout(force, DT, "linear")
    assert np.max(np.abs(expected)) > 0.02
    errs = []
    for s in (50, 100):
        tau, _ = simulate_reference(make_simulator(tree, obs_dt=DT, substeps=s), kp, kd, force)
        errs.append(np.max(np.abs(tau - expected)))
    assert errs[1] < 0.6 * errs[0]
    assert errs[1] < 5e-5


# ---- force interpolation --------------------------------------------------------------------
def test_force_interpolation_conventions():
    """``linear`` converges to the reference with a piecewise-linear force, ``hold`` to the one
    with each sample held until the next; the two differ by far more than either's error."""
    tree = _chain(1)
    kp, kd = np.array([8.0]), np.array([0.08])
    ref = PlanarTree(tree, kp, kd)
    prof = _profiles()[:1]
    for interp in ("linear", "hold"):
        sim = make_simulator(tree, obs_dt=DT, substeps=40, force_interp=interp)
        tau = np.asarray(simulate(sim, kp[None], kd[None], jnp.asarray(prof)).tau[0, 0])
        own = ref.rollout(prof[0], DT, interp)
        other = ref.rollout(prof[0], DT, "hold" if interp == "linear" else "linear")
        assert np.max(np.abs(tau - own)) < 2e-4
        assert np.max(np.abs(tau - other)) > 1e-3
    with pytest.raises(ConfigError, match="force_interp"):
        make_simulator(tree, obs_dt=DT, force_interp="cubic")


# ---- the accuracy-controlled step ------------------------------------------------------------
GAINS = {"stiff": (400.0, 5.0), "soft": (8.0, 0.08)}  # N m/rad, N m s/rad on every joint


# one joint and the three-joint chain in the default run; two joints (between them: no path of
# its own) under -m slow
@pytest.mark.parametrize("n", [1, pytest.param(2, marks=pytest.mark.slow), 3])
def test_default_simulator_agrees_with_the_reference(n):
    """The defaults (first-order hold, step refined to 0.1 mm on the data's profile over the
    default prior box) on a 3 s ramp-hold-release: within 0.1 mm of the reference for stiff
    and soft gains (one simulator call for both)."""
    tree = _chain(n)
    prof = _profiles()[:1]
    sim = make_simulator(tree, obs_dt=DT, forces=prof)
    assert sim.force_interp == "linear"
    assert sim.step_info["method"] == "accuracy"
    assert sim.step_info["estimated_error"] <= DEFAULT_SIM_TOLERANCE
    kp = np.array([[GAINS[g][0]] * n for g in GAINS])
    kd = np.array([[GAINS[g][1]] * n for g in GAINS])
    tau = np.asarray(simulate(sim, kp, kd, jnp.asarray(prof)).tau[:, 0])
    for i, g in enumerate(GAINS):
        expected = PlanarTree(tree, kp[i], kd[i]).rollout(prof[0], DT)
        assert np.max(np.abs(expected)) > 1e-3
        assert np.max(np.abs(tau[i] - expected)) < 1e-4, (n, g, sim.substeps)


def test_tolerance_sets_the_step():
    """A tighter tolerance takes more substeps; each estimate is at most its tolerance, and the
    estimate bounds the true error against the reference at the box's softest corner."""
    tree = _chain(1, (5.0, 20.0), (0.05, 0.3))
    prof = _profiles()[:1]
    sim = make_simulator(tree, obs_dt=DT)
    coarse, err_coarse = choose_substeps_for_accuracy(sim, prof, 1e-3)
    fine, err_fine = choose_substeps_for_accuracy(sim, prof, 1e-4)
    assert coarse < fine
    assert err_coarse <= 1e-3 and err_fine <= 1e-4
    ref = PlanarTree(tree, [5.0], [0.05]).rollout(prof[0], DT)
    tau = simulate(
        replace(sim, substeps=coarse), np.array([[5.0]]), np.array([[0.05]]), jnp.asarray(prof)
    ).tau
    true = np.max(np.abs(np.asarray(tau[0, 0]) - ref))
    assert 0.5 * err_coarse <= true <= 1.25 * err_coarse  # step doubling: a close estimate
    assert default_tolerance(2e-3) == pytest.approx(2e-4)
    assert default_tolerance(None) == DEFAULT_SIM_TOLERANCE
    with pytest.raises(ConfigError, match="sim_tolerance"):
        make_simulator(tree, obs_dt=DT, sim_tolerance=-1.0)
