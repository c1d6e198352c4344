"""Exact forward-mode gradients of the fused simulator (``gradients.jvp_value_and_grad``).

Three independent references:

* the likelihood gradient against central differences of the same batched likelihood, in
  float64 (so the FD error, ~h^2 f''' + eps f / h with h = 6e-6, is far below the tolerance);
* one fused step's derivative with respect to the state against MuJoCo's own finite-difference
  transition matrix ``mujoco.mjd_transitionFD`` (centred, float64) on random states;
* one fused step's derivative with respect to the gains (stiffness, damping) against central
  differences of ``mujoco.mj_step`` on the C model, float64.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from treeinfer.data.trajectories import Trajectory, stack_trajectories
from treeinfer.errors import ConfigError
from treeinfer.examples import example_path
from treeinfer.model.gradients import (
    combined_value_and_grad,
    jvp_combined_value_and_grad,
    jvp_value_and_grad,
    likelihood_value_and_grad,
)
from treeinfer.model.likelihood import boltzmann_log_likelihood
from treeinfer.sim import fused as hd
from treeinfer.sim import levels as lv
from treeinfer.sim import make_simulator
from treeinfer.sim.reference import simulate_reference
from treeinfer.tree.description import load_tree
from treeinfer.tree.export import to_mjmodel

# The hand-written model of tests/test_hinge_dynamics.py (copied so each file stands alone). It
# uses what our exports do not: a welded (joint-less) body, joint anchors and axes off the body
# frame, rotated principal axes, armature, a non-zero spring reference and qpos0, and a
# sideways gravity component.
GENERAL_MJCF = """
<mujoco>
  <option timestep="0.002" integrator="implicitfast" gravity="0.5 -1 -9.81">
    <flag contact="disable" constraint="disable"/>
  </option>
  <worldbody>
    <body name="a" pos="0.1 0.2 1.0" quat="0.9 0.1 0.3 0.2">
      <joint name="ja" type="hinge" axis="0.3 1 0.2" pos="0.05 0 0.02" stiffness="30" damping="0.4"
             springref="0.1" armature="0.01" ref="0.05"/>
      <inertial pos="0.3 0.01 0" quat="0.8 0.2 0.1 0.3" mass="1.2" diaginertia="0.02 0.03 0.01"/>
      <body name="welded" pos="0.6 0 0" quat="0.7 0 0.7 0">
        <inertial pos="0.1 0 0.02" mass="0.3" diaginertia="0.002 0.001 0.003"/>
        <body name="b" pos="0.2 0.05 0" quat="1 0.2 0 0.1">
          <joint name="jb" type="hinge" axis="0 0 1" pos="-0.02 0.01 0" stiffness="12"
                 damping="0.2"/>
          <inertial pos="0.25 0 0" mass="0.5" diaginertia="0.01 0.012 0.004"/>
          <site name="grasp" pos="0.5 0 0"/>
        </body>
        <body name="c" pos="0.1 -0.1 0.05">
          <joint name="jc" type="hinge" axis="1 0 0" stiffness="8" damping="0.1"/>
          <inertial pos="0 0.2 0" mass="0.2" diaginertia="0.003 0.001 0.003"/>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


def _two_branch_data(n_steps=40):
    tree = load_tree(example_path("two_branch"))
    sim = make_simulator(tree, obs_dt=0.01)
    kp, kd = np.array([60.0, 25.0]), np.array([0.8, 0.3])
    t = np.arange(n_steps) * 0.01
    trajs = []
    for i, peak in enumerate((6.0, 3.0)):
        f = peak * np.clip(t / (0.2 + 0.1 * i), 0.0, 1.0)
        trajs.append(Trajectory(t, f, *simulate_reference(sim, kp, kd, f), f"p{i}"))
    return sim, stack_trajectories(trajs), np.log(np.concatenate([kp, kd]))


def test_jvp_gradient_equals_central_differences_float64():
    sim, obs, theta_true = _two_branch_data()
    rng = np.random.default_rng(0)
    with jax.enable_x64(True):
        theta = jnp.asarray(theta_true + rng.normal(scale=0.3, size=(3, 4)))
        loglik = boltzmann_log_likelihood(sim, obs, kT=0.05)
        prior = lambda t: -0.5 * jnp.sum((t - 1.0) ** 2, axis=-1)
        value, grad = jax.jit(jvp_combined_value_and_grad([loglik], [prior]))(theta)
        value_fd, grad_fd = jax.jit(combined_value_and_grad([loglik], [prior]))(theta)
        assert grad.dtype == jnp.float64
    np.testing.assert_allclose(value, value_fd, rtol=1e-12)
    assert np.all(np.abs(np.asarray(grad)) > 0) and np.all(np.isfinite(grad))
    # central differences in float64 are good to ~1e-7 relative here
    np.testing.assert_allclose(grad, grad_fd, rtol=1e-5, atol=1e-6 * np.max(np.abs(grad_fd)))


def test_jvp_gradient_float32_within_fd_error_and_unstable_particles_masked():
    sim, obs, theta_true = _two_branch_data()
    theta = theta_true + np.random.default_rng(1).normal(scale=0.3, size=(4, 4))
    theta[3, 0] = 25.0  # Kp ~ 7e10: the explicit spring blows up
    theta = jnp.asarray(theta, jnp.float32)
    loglik = boltzmann_log_likelihood(sim, obs, kT=0.05)
    value, grad = jax.jit(likelihood_value_and_grad(loglik, "jvp"))(theta)
    _, grad_fd = jax.jit(likelihood_value_and_grad(loglik, "fd"))(theta)
    assert value[3] == -np.inf and np.all(np.asarray(grad[3]) == 0.0)
    assert np.all(np.isfinite(value[:3])) and np.all(np.isfinite(grad[:3]))
    with jax.enable_x64(True):
        _, grad64 = jax.jit(jvp_value_and_grad(loglik))(jnp.asarray(theta[:3], jnp.float64))
    grad, grad_fd = grad[:3], grad_fd[:3]
    # float32 forward mode is closer to the float64 gradient than float32 central differences
    err_jvp = np.abs(np.asarray(grad) - np.asarray(grad64)).max()
    err_fd = np.abs(np.asarray(grad_fd) - np.asarray(grad64)).max()
    assert err_jvp <= err_fd + 1e-6 * np.abs(np.asarray(grad64)).max()
    np.testing.assert_allclose(grad, grad64, rtol=2e-3, atol=2e-3 * np.abs(grad64).max())


def test_bad_gradient_method_names_the_choices():
    with pytest.raises(ConfigError, match="fd, jvp"):
        likelihood_value_and_grad(lambda t: t[:, 0], "adjoint")


def _models():
    yield "general", mujoco.MjModel.from_xml_string(GENERAL_MJCF)
    yield "two_branch", to_mjmodel(load_tree(example_path("two_branch")))


def _random_state(m, rng):
    d = mujoco.MjData(m)
    d.qpos[:] = rng.normal(size=m.nq) * 0.5
    d.qvel[:] = rng.normal(size=m.nv) * 1.5
    kp, kd = rng.uniform(5, 80, m.nv), rng.uniform(0.1, 3, m.nv)
    m.jnt_stiffness[m.dof_jntid] = kp
    m.dof_damping[:] = kd
    body = m.nbody - 1
    force, lever = rng.normal(size=3) * 4, rng.normal(size=3) * 0.1
    d.xfrc_applied[body, :3] = force
    d.xfrc_applied[body, 3:] = np.cross(lever, force)
    return d, kp, kd, body, force, lever


def _fused_next_state(m, t, body, layout="scalar"):
    """(q [nv], v [nv], stiffness [nv], damping [nv], force [3], lever [3]) -> next state [2 nv]
    of the fused step (``layout``: ``"scalar"``, :mod:`treeinfer.sim.fused`; ``"levels"``,
    :mod:`~.levels`). The force and lever are arguments, as in a pull (traced per step), so one
    compiled program serves every random state."""
    spring = m.qpos_spring[m.jnt_qposadr[m.dof_jntid]]

    def next_state(q, v, kp, kd, force, lever):
        force, lever = tuple(force[i] for i in range(3)), tuple(lever[i] for i in range(3))
        if layout == "levels":
            out = lv.step(
                lv.layout(t), q, v, kp, kd, spring, m.opt.timestep, body, (0.1, 0.0, 0.0),
                force, lever,
            )  # fmt: skip
            return jnp.concatenate([out.qpos, out.qvel])
        out = hd.step(
            t,
            q,
            v,
            kp,
            kd,
            jnp.asarray(spring),
            m.opt.timestep,
            body,
            (0.1, 0.0, 0.0),
            force,
            lever,
        )
        return jnp.concatenate([jnp.stack(out.qpos), jnp.stack(out.qvel)])

    return next_state


@pytest.mark.parametrize("layout", ["scalar", "levels"])
@pytest.mark.parametrize(
    "name,model", list(_models()), ids=lambda x: x if isinstance(x, str) else ""
)
def test_step_state_jacobian_matches_mjd_transitionFD(name, model, layout):
    m = model
    t = hd.from_mjmodel(m)
    rng = np.random.default_rng(3)
    # the force acts on the last body in every draw (_random_state): one program for all three
    jac = jax.jit(jax.jacfwd(_fused_next_state(m, t, m.nbody - 1, layout), argnums=(0, 1)))
    with jax.enable_x64(True):
        for _ in range(3):
            d, kp, kd, body, force, lever = _random_state(m, rng)
            assert body == m.nbody - 1
            a = np.zeros((2 * m.nv + m.na, 2 * m.nv + m.na))
            mujoco.mjd_transitionFD(m, d, 1e-6, True, a, None, None, None)
            args = (jnp.asarray(d.qpos), jnp.asarray(d.qvel), jnp.asarray(kp), jnp.asarray(kd))
            jq, jv = jac(*args, jnp.asarray(force), jnp.asarray(lever))
            ours = np.concatenate([np.asarray(jq), np.asarray(jv)], axis=1)
            assert np.abs(ours - np.eye(2 * m.nv)).max() > 1e-3  # the step really couples states
            np.testing.assert_allclose(ours, a, atol=1e-6 * max(1.0, np.abs(a).max()))


@pytest.mark.parametrize("layout", ["scalar", "levels"])
@pytest.mark.parametrize(
    "name,model", list(_models()), ids=lambda x: x if isinstance(x, str) else ""
)
def test_step_gain_jacobian_matches_fd_of_mj_step(name, model, layout):
    m = model
    t = hd.from_mjmodel(m)
    rng = np.random.default_rng(4)
    with jax.enable_x64(True):
        d0, kp, kd, body, force, lever = _random_state(m, rng)
        f = _fused_next_state(m, t, body, layout)
        args = (jnp.asarray(d0.qpos), jnp.asarray(d0.qvel), jnp.asarray(kp), jnp.asarray(kd))
        args += (jnp.asarray(force), jnp.asarray(lever))
        jkp, jkd = (np.asarray(x) for x in jax.jit(jax.jacfwd(f, argnums=(2, 3)))(*args))

    def c_step(kp_, kd_):
        m.jnt_stiffness[m.dof_jntid] = kp_
        m.dof_damping[:] = kd_
        d = mujoco.MjData(m)
        d.qpos[:], d.qvel[:], d.xfrc_applied[:] = d0.qpos, d0.qvel, d0.xfrc_applied
        mujoco.mj_step(m, d)
        return np.concatenate([d.qpos, d.qvel])

    for j in range(m.nv):
        for gains, ours in ((kp, jkp), (kd, jkd)):
            h = 1e-6 * gains[j]
            up, down = gains.copy(), gains.copy()
            up[j] += h
            down[j] -= h
            if gains is kp:
                col = (c_step(up, kd) - c_step(down, kd)) / (2 * h)
            else:
                col = (c_step(kp, up) - c_step(kp, down)) / (2 * h)
            np.testing.assert_allclose(ours[:, j], col, atol=1e-7 * max(1.0, np.abs(col).max()))
