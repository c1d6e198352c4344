"""The reference path of :mod:`treeinfer.sim`: plain MuJoCo C (``mujoco.mj_step``, float64),
one rollout at a time. The independent reference in tests and the naive baseline in benchmarks.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import jax.numpy as jnp
import numpy as np

from ..data.trajectories import velocity_from_displacement

if TYPE_CHECKING:
    from . import Simulator


def _c_model(sim: Simulator, kp, kd, grasp_fraction=None):
    import copy

    m = copy.deepcopy(sim.mj_model)
    for j, d, a, b in zip(sim.joint_ids, sim.dof_ids, np.asarray(kp, float), np.asarray(kd, float)):
        m.jnt_stiffness[j] = a
        m.dof_damping[d] = b
    if grasp_fraction is not None:
        m.site_pos[sim.grasp_site] = sim.grasp_start + float(grasp_fraction) * (
            sim.grasp_end - sim.grasp_start
        )
    return m


def settle_reference(m, iterations: int = 50, tol: float = 1e-10) -> np.ndarray:
    """Static equilibrium of a MuJoCo C model by Newton's method with a finite-difference
    Jacobian (float64), the C twin of :func:`treeinfer.sim.mjx.settle_one`."""
    import mujoco

    d = mujoco.MjData(m)

    def torque(q):
        d.qpos[:] = q
        d.qvel[:] = 0
        mujoco.mj_forward(m, d)
        return d.qfrc_passive - d.qfrc_bias

    q = np.zeros(m.nq)
    for _ in range(iterations):
        r = torque(q)
        if np.max(np.abs(r)) < tol:
            break
        jac = np.zeros((m.nv, m.nq))
        for k in range(m.nq):
            e = np.zeros(m.nq)
            e[k] = 1e-6
            jac[:, k] = (torque(q + e) - torque(q - e)) / 2e-6
        q = q + np.clip(-np.linalg.solve(jac, r), -0.2, 0.2)
    return q


def simulate_reference(
    sim: Simulator, kp, kd, force, grasp_fraction=None, direction=None, grasp_branch=None
) -> tuple[np.ndarray, np.ndarray]:
    """One rollout in plain MuJoCo (``mujoco.mj_step``, float64): tau [T], tau_dot [T].

    Same settle, force application, force interpolation (``sim.force_interp``) and observation
    timing as :func:`simulate`; ``direction`` [3] (None: gravity's) and ``grasp_branch`` (None:
    the tree's) as there, for one profile. Used as the independent reference in tests and as
    the naive baseline in benchmarks."""
    import mujoco

    m = _c_model(sim, kp, kd, grasp_fraction)
    d = mujoco.MjData(m)
    d.qpos[:] = settle_reference(m)
    mujoco.mj_forward(m, d)
    bid, length = sim.grasp_body, float(sim.grasp_end[0])
    if grasp_branch is not None:
        bid, length = sim.branches[grasp_branch]
    if grasp_branch is None or bid == sim.grasp_body:
        local = np.asarray(m.site_pos[sim.grasp_site], float)
    else:
        frac = sim.grasp_fraction if grasp_fraction is None else float(grasp_fraction)
        local = np.asarray(sim.branch_point(bid, length, frac), float)
    ddir = np.asarray(sim.gravity_dir if direction is None else direction, float)
    ddir = ddir / np.linalg.norm(ddir)
    grasp = lambda: d.xpos[bid] + d.xmat[bid].reshape(3, 3) @ local  # C from the last kinematics
    c_rest = grasp()
    f = np.asarray(force, float)
    f_next = np.concatenate([f[1:], f[-1:]])
    w = 0.0 if sim.force_interp == "hold" else 1.0
    out = []
    for f0, f1 in zip(f, f_next):
        for k in range(sim.substeps):
            fv = (f0 + w * (k / sim.substeps) * (f1 - f0)) * ddir
            d.xfrc_applied[:] = 0
            d.xfrc_applied[bid, :3] = fv
            d.xfrc_applied[bid, 3:] = np.cross(grasp() - d.xipos[bid], fv)
            mujoco.mj_step(m, d)
            if k == 0:
                out.append(grasp())
    tau = (np.asarray(out) - c_rest) @ ddir
    tau_dot = np.asarray(velocity_from_displacement(jnp.asarray(tau), sim.obs_dt))
    return tau, tau_dot
