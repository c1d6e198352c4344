"""The reference path of :mod:`treeinfer.sim`: plain MuJoCo C (``mujoco.mj_step``, float64),
one rollout at a time. The independent reference in tests and the naive baseline in benchmarks.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import jax.numpy as jnp
import numpy as np

from ..trajectories import velocity_from_displacement

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
    sim: Simulator, kp, kd, force, grasp_fraction=None
) -> tuple[np.ndarray, np.ndarray]:
    """One rollout in plain MuJoCo (``mujoco.mj_step``, float64): tau [T], tau_dot [T].

    Same settle, force application and observation timing as :func:`treeinfer.sim.simulate`; used as the
    independent reference in tests and as the naive baseline in benchmarks."""
    import mujoco

    m = _c_model(sim, kp, kd, grasp_fraction)
    d = mujoco.MjData(m)
    d.qpos[:] = settle_reference(m)
    mujoco.mj_forward(m, d)
    sid, bid = sim.grasp_site, sim.grasp_body
    c_rest = d.site_xpos[sid].copy()
    out = []
    for f in np.asarray(force, float):
        for k in range(sim.substeps):
            fv = f * sim.gravity_dir
            d.xfrc_applied[:] = 0
            d.xfrc_applied[bid, :3] = fv
            d.xfrc_applied[bid, 3:] = np.cross(d.site_xpos[sid] - d.xipos[bid], fv)
            mujoco.mj_step(m, d)
            if k == 0:
                out.append(d.site_xpos[sid].copy())
    tau = (np.asarray(out) - c_rest) @ sim.gravity_dir
    tau_dot = np.asarray(velocity_from_displacement(jnp.asarray(tau), sim.obs_dt))
    return tau, tau_dot
