"""The fused hinge-tree step (treeinfer.hinge_dynamics) against MuJoCo's own C step, in float64.

Each check sets a random state, stiffness, damping and applied force on a MuJoCo model, takes
one ``mujoco.mj_step`` and one fused step from the same state, and compares qpos and qvel; the
pieces (kinematics, mass matrix) are compared with ``mj_forward`` too."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from treeinfer.examples import example_path
from treeinfer.sim import fused as hd
from treeinfer.sim import levels as lv
from treeinfer.sim import make_simulator
from treeinfer.sim.fused_backend import LEVELS_FROM_JOINTS, uses_levels
from treeinfer.tree import generators as gen
from treeinfer.tree.description import load_tree
from treeinfer.tree.export import to_mjmodel

# A hand-written model that uses what our exports do not: a welded (joint-less) body, joint
# anchors and axes off the body frame, rotated principal axes, armature, a non-zero spring
# reference and qpos0, and a sideways gravity component.
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


def _models():
    yield "general", mujoco.MjModel.from_xml_string(GENERAL_MJCF)
    for name in ("two_branch", "three_branch", "fractal"):
        yield name, to_mjmodel(load_tree(example_path(name)))


@pytest.mark.parametrize(
    "name,model", list(_models()), ids=lambda x: x if isinstance(x, str) else ""
)
def test_one_step_matches_mj_step(name, model):
    m = model
    t = hd.from_mjmodel(m)
    rng = np.random.default_rng(1)
    body = m.nbody - 1
    with jax.enable_x64(True):
        for _ in range(3):
            d = mujoco.MjData(m)
            d.qpos[:] = rng.normal(size=m.nq) * 0.6
            d.qvel[:] = rng.normal(size=m.nv) * 2.0
            kp, kd = rng.uniform(2, 80, m.nv), rng.uniform(0.05, 3, m.nv)
            m.jnt_stiffness[m.dof_jntid] = kp
            m.dof_damping[:] = kd
            force, lever = rng.normal(size=3) * 4, rng.normal(size=3) * 0.1
            d.xfrc_applied[body, :3] = force
            d.xfrc_applied[body, 3:] = np.cross(lever, force)
            mujoco.mj_forward(m, d)

            q, v = jnp.asarray(d.qpos), jnp.asarray(d.qvel)
            kin = hd.kinematics(t, [q[i] for i in range(m.nv)])
            for b in range(1, m.nbody):
                np.testing.assert_allclose(np.asarray(kin.com[b], float), d.xipos[b], atol=1e-12)
                np.testing.assert_allclose(
                    np.asarray(kin.rot[b], float), d.xmat[b].reshape(3, 3), atol=1e-12
                )
            full = np.zeros((m.nv, m.nv))
            mujoco.mj_fullM(m, full, d.qM) if hasattr(d, "qM") else mujoco.mj_fullM(m, d, full)
            ours = np.zeros_like(full)
            for (i, j), x in hd.mass_matrix(t, kin).items():
                ours[i, j] = ours[j, i] = float(x)
            np.testing.assert_allclose(ours + np.diag(m.dof_armature), full, atol=1e-12)

            spring = m.qpos_spring[m.jnt_qposadr[m.dof_jntid]]
            out = hd.step(
                t,
                q,
                v,
                jnp.asarray(kp),
                jnp.asarray(kd),
                jnp.asarray(spring),
                m.opt.timestep,
                body,
                (0.1, 0.0, 0.0),
                tuple(force),
                tuple(lever),
            )
            site_body = d.xpos[body] + d.xmat[body].reshape(3, 3) @ np.array([0.1, 0.0, 0.0])
            np.testing.assert_allclose(np.asarray(out.site, float), site_body, atol=1e-12)
            mujoco.mj_step(m, d)
            assert np.max(np.abs(d.qvel)) > 0.1  # the state really moves
            np.testing.assert_allclose(np.asarray(out.qpos), d.qpos, atol=1e-10)
            np.testing.assert_allclose(np.asarray(out.qvel), d.qvel, atol=1e-10)


def test_models_it_does_not_reproduce_are_refused():
    slide = GENERAL_MJCF.replace('type="hinge" axis="1 0 0"', 'type="slide" axis="1 0 0"')
    with pytest.raises(hd.UnsupportedModel, match="non-hinge"):
        hd.from_mjmodel(mujoco.MjModel.from_xml_string(slide))
    euler = GENERAL_MJCF.replace('integrator="implicitfast"', 'integrator="Euler"')
    with pytest.raises(hd.UnsupportedModel, match="integrator"):
        hd.from_mjmodel(mujoco.MjModel.from_xml_string(euler))
    motor = GENERAL_MJCF.replace("</mujoco>", '<actuator><motor joint="jb"/></actuator></mujoco>')
    with pytest.raises(hd.UnsupportedModel, match="actuators"):
        hd.from_mjmodel(mujoco.MjModel.from_xml_string(motor))


def test_auto_backend_picks_fused_for_our_trees():
    sim = make_simulator(load_tree(example_path("three_branch")), obs_dt=0.01)
    assert sim.backend == "fused" and sim.hinge_tree is not None


def _random_mj_state(m, rng, body):
    """A random state, gains and applied wrench on ``m`` (in place), as the test above."""
    d = mujoco.MjData(m)
    d.qpos[:] = rng.normal(size=m.nq) * 0.6
    d.qvel[:] = rng.normal(size=m.nv) * 2.0
    kp, kd = rng.uniform(2, 80, m.nv), rng.uniform(0.05, 3, m.nv)
    m.jnt_stiffness[m.dof_jntid] = kp
    m.dof_damping[:] = kd
    force, lever = rng.normal(size=3) * 4, rng.normal(size=3) * 0.1
    d.xfrc_applied[body, :3] = force
    d.xfrc_applied[body, 3:] = np.cross(lever, force)
    mujoco.mj_forward(m, d)
    return d, kp, kd, force, lever


def _big_lsystem():
    """A generated L-system tree of 171 hinges, 5 levels deep."""
    return to_mjmodel(gen.lsystem("F", {"F": "F[+F][-F]F"}, 4, angle_deg=25, step_length=0.3))


@pytest.mark.parametrize(
    "name,model",
    list(_models()) + [("lsystem171", _big_lsystem())],
    ids=lambda x: x if isinstance(x, str) else "",
)
def test_level_step_matches_mj_step(name, model):
    """The level layout (articulated-body algorithm per depth level) equals mj_step in float64:
    frames, gravity torque, grasp point, and the next qpos/qvel."""
    m = model
    lay = lv.layout(hd.from_mjmodel(m))
    assert sorted(np.concatenate([x.bodies for x in lay.levels])) == list(range(1, m.nbody))
    rng = np.random.default_rng(2)
    body = m.nbody - 1
    with jax.enable_x64(True):
        for _ in range(2):
            d, kp, kd, force, lever = _random_mj_state(m, rng, body)
            q, v = jnp.asarray(d.qpos), jnp.asarray(d.qvel)
            kin = lv.kinematics(lay, q)
            for level, k in zip(lay.levels, kin):
                np.testing.assert_allclose(np.asarray(k.com), d.xipos[level.bodies], atol=1e-12)
                np.testing.assert_allclose(
                    np.asarray(k.rot), d.xmat[level.bodies].reshape(-1, 3, 3), atol=1e-12
                )
            spring = m.qpos_spring[m.jnt_qposadr[m.dof_jntid]]
            # gravity torque: MuJoCo's qfrc_bias at zero velocity
            d0 = mujoco.MjData(m)
            d0.qpos[:] = d.qpos
            mujoco.mj_forward(m, d0)
            torque = lv.static_torque(lay, q, kp, spring)
            want = -kp * (d.qpos - spring) - d0.qfrc_bias
            np.testing.assert_allclose(np.asarray(torque), want, atol=1e-10)
            out = lv.step(
                lay, q, v, kp, kd, spring, m.opt.timestep, body, (0.1, 0.0, 0.0), force, lever
            )
            site_body = d.xpos[body] + d.xmat[body].reshape(3, 3) @ np.array([0.1, 0.0, 0.0])
            np.testing.assert_allclose(np.asarray(out.site), site_body, atol=1e-12)
            mujoco.mj_step(m, d)
            assert np.max(np.abs(d.qvel)) > 0.1  # the state really moves
            np.testing.assert_allclose(np.asarray(out.qpos), d.qpos, atol=1e-10)
            np.testing.assert_allclose(np.asarray(out.qvel), d.qvel, atol=1e-10)


def test_auto_layout_switches_to_levels_for_big_trees():
    small = make_simulator(load_tree(example_path("three_branch")), obs_dt=0.01)
    assert small.hinge_tree.nv < LEVELS_FROM_JOINTS and not uses_levels(small)
    tree = gen.chain(LEVELS_FROM_JOINTS, 0.2, 0.02)
    big = make_simulator(tree, obs_dt=0.01, substeps=2)
    assert uses_levels(big)
