"""Native MuJoCo side of ``benchmarks/rollout.py``: the tree's model with a grasp-point body
for a plain world-frame pull, the settled per-particle models, the ``xfrc_applied`` controls and
:class:`CRollout` (``mujoco.rollout`` in chunks). Re-exported by :mod:`benchmarks.rollout`."""

from __future__ import annotations

import copy

import numpy as np


def rollout_model(tree, sim):
    """The tree's MuJoCo model plus a 1e-6 kg body at the grasp point (for a plain world-frame
    ``xfrc_applied`` pull) and a ``framepos`` sensor of it; same options and time step as
    ``sim``."""
    import mujoco

    from treeinfer.tree.export import GRASP_SITE, to_mjcf

    spec = mujoco.MjSpec.from_string(to_mjcf(tree, timestep=sim.sim_dt))
    site_pos = np.asarray(sim.mj_model.site_pos[sim.grasp_site], float)
    body = spec.body(tree.grasp_branch)
    pt = body.add_body(name="grasp_point", pos=site_pos)
    pt.explicitinertial = True
    pt.ipos = [0.0, 0.0, 0.0]  # unset (NaN) otherwise, and the compiler does not put it at pos
    pt.iquat = [1.0, 0.0, 0.0, 0.0]
    pt.mass = 1e-6
    pt.inertia = [1e-12, 1e-12, 1e-12]
    spec.add_sensor(
        name="grasp_pos",
        type=mujoco.mjtSensor.mjSENS_FRAMEPOS,
        objtype=mujoco.mjtObj.mjOBJ_SITE,
        objname=GRASP_SITE,
    )
    m = spec.compile()
    bid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "grasp_point")
    assert bid > 0 and m.nbody == sim.mj_model.nbody + 1, "grasp_point body was fused away"
    return m, bid


def c_pool(sim, m, kp, kd):
    """Models with each pool entry's gains, their settled full-physics states, and C rest points."""
    import mujoco

    from treeinfer.sim.reference import settle_reference

    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    models, states, c_rest = [], [], []
    for a, b in zip(kp, kd):
        mi = copy.copy(m)
        for j, d, x, y in zip(sim.joint_ids, sim.dof_ids, a, b):
            mi.jnt_stiffness[j] = x
            mi.dof_damping[d] = y
        d = mujoco.MjData(mi)
        d.qpos[:] = settle_reference(mi)
        mujoco.mj_forward(mi, d)
        s = np.empty(mujoco.mj_stateSize(mi, spec))
        mujoco.mj_getState(mi, d, s, spec)
        models.append(mi)
        states.append(s)
        c_rest.append(d.site_xpos[sim.grasp_site].copy())
    return models, np.asarray(states), np.asarray(c_rest)


def c_controls(sim, m, bid, forces):
    """[1, T * substeps, nbody * 6] xfrc_applied controls: the pull at the grasp-point body."""
    # the force between samples as the simulator applies it (treeinfer.sim.forcing): under the
    # first-order hold substep j of interval k uses f_k + (j / substeps) (f_{k+1} - f_k)
    f0 = np.asarray(forces[0], float)
    f1 = np.concatenate([f0[1:], f0[-1:]])
    w = (
        np.arange(sim.substeps) / sim.substeps
        if sim.force_interp == "linear"
        else np.zeros(sim.substeps)
    )
    f = (f0[:, None] + w[None, :] * (f1 - f0)[:, None]).reshape(-1)
    ctrl = np.zeros((1, f.size, m.nbody * 6))
    ctrl[0, :, bid * 6 : bid * 6 + 3] = f[:, None] * sim.gravity_dir[None, :]
    return ctrl


class CRollout:
    """``mujoco.rollout`` of N pool-cycled models in chunks (bounded output buffers)."""

    def __init__(self, sim, m, bid, models, states, forces, threads: int, chunk: int = 512):
        import mujoco
        from mujoco import rollout

        self.sim, self.models, self.states = sim, models, states
        self.ctrl = c_controls(sim, m, bid, forces)
        self.nstep = self.ctrl.shape[1]
        self.threads = threads
        self.chunk = chunk
        self.pool = rollout.Rollout(nthread=threads)
        self.datas = [mujoco.MjData(m) for _ in range(max(threads, 1))]
        nstate = states.shape[1]
        self.state_buf = np.empty((chunk, self.nstep, nstate))
        self.sens_buf = np.empty((chunk, self.nstep, m.nsensordata))
        self.spec = mujoco.mjtState.mjSTATE_XFRC_APPLIED.value

    def run(self, n: int):
        done = 0
        while done < n:
            k = min(self.chunk, n - done)
            idx = [(done + i) % len(self.models) for i in range(k)]
            self.pool.rollout(
                [self.models[i] for i in idx],
                self.datas,
                self.states[idx],
                self.ctrl,
                control_spec=self.spec,
                state=self.state_buf[:k],
                sensordata=self.sens_buf[:k],
            )
            done += k
        return self.sens_buf

    def tau(self, c_rest0):
        """Displacement [T] of rollout 0 of the last chunk (sensor recorded before each step)."""
        self.run(1)
        pos = self.sens_buf[0, :: self.sim.substeps, :3]
        return (pos - c_rest0) @ self.sim.gravity_dir

    def close(self):
        self.pool.close()
