"""The time-unit check knows the physics (issue 27, item 4): release and step pulls that
treeinfer's own simulator produces, anywhere in the prior box, never draw "minutes instead of
seconds"; the same pulls with time in minutes still do. The speed bound (kinetic energy <=
work of the pull, kinetic energy >= v^2 / (2 mobility)) is checked against MuJoCo's own
kinetic energy."""

from __future__ import annotations

import numpy as np
import pytest

from treeinfer.data.forces import from_spec, random_specs
from treeinfer.data.trajectories import Trajectory
from treeinfer.evaluation.checks import data_checks
from treeinfer.examples import example_path
from treeinfer.sim.synthetic import default_true_params
from treeinfer.tree.description import load_tree
from treeinfer.tree.plausibility import response_range

DT, DURATION = 0.01, 3.0


def _simulate(tree, kp, kd, specs, noise=0.0, seed=0):
    from treeinfer.sim import make_simulator, simulate

    forces = np.stack([from_spec(s, DURATION, DT) for s in specs])
    sim = make_simulator(tree, obs_dt=DT, forces=forces)
    ro = simulate(sim, np.asarray([kp]), np.asarray([kd]), forces)
    assert np.asarray(ro.stable).all()
    tau = np.asarray(ro.tau, float)[0]
    rng = np.random.default_rng(seed)
    t = np.arange(forces.shape[1]) * DT
    return [
        Trajectory(t, forces[b], tau[b] + noise * rng.standard_normal(t.shape), None, f"p{b}")
        for b in range(len(specs))
    ]


@pytest.mark.parametrize("example", ["three_branch", "two_branch"])
def test_release_and_step_pulls_are_not_flagged(example):
    tree = load_tree(example_path(example))
    lo, hi = tree.bounds_array()
    r = tree.n_inferred
    rng = np.random.default_rng(0)
    cases = [default_true_params(tree, rng) for _ in range(2)]
    # the fastest corner of the box: stiffest springs, least damping (the hardest release)
    cases.append((hi[:r], lo[r:]))
    specs = random_specs("release", 2, DURATION, (2.0, 8.0), 1) + random_specs(
        "step", 2, DURATION, (2.0, 8.0), 2
    )
    flagged = []
    for kp, kd in cases:
        trajs = _simulate(tree, kp, kd, specs, noise=1e-3)
        found = [f for f in data_checks(tree, trajs) if f.check == "time-unit"]
        flagged += [(kp.tolist(), kd.tolist(), str(f)) for f in found]
        minutes = [t._replace(time=t.time / 60.0) for t in trajs]
        hits = [f for f in data_checks(tree, minutes) if f.check == "time-unit"]
        assert hits, f"time in minutes not caught for Kp {kp}, Kd {kd}"
    assert flagged == []


def test_speed_bound_against_mujoco_kinetic_energy():
    """On a free release in plain MuJoCo the grasp site's speed never exceeds
    sqrt(2 mobility KE), KE MuJoCo's own kinetic energy (the inequality the check rests on)."""
    import mujoco

    from treeinfer.tree.plausibility import _compliance_model, _sim_attr

    tree = load_tree(example_path("three_branch"))
    _, _, mobility = response_range(tree)
    m, sid = _compliance_model(tree, None)
    m.opt.enableflags |= mujoco.mjtEnableBit.mjENBL_ENERGY
    d = mujoco.MjData(m)
    d.qpos[:] = _sim_attr("settle_reference")(m)
    d.qvel[:] = np.random.default_rng(0).standard_normal(m.nv) * 0.5  # a kick
    jac = np.zeros((3, m.nv))
    worst = 0.0
    for _ in range(300):
        mujoco.mj_step(m, d)
        mujoco.mj_forward(m, d)  # kinematics and energy of the state after the step
        mujoco.mj_jacSite(m, d, jac, None, sid)
        v = float(np.linalg.norm(jac @ d.qvel))
        ke = float(d.energy[1])
        worst = max(worst, v / np.sqrt(2 * mobility * ke))
    assert 0.3 < worst <= 1.05  # the bound holds (mobility: max over the box's poses)
