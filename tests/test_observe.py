"""Observation channels from the simulator (issue 30): forward kinematics of named points against
MuJoCo C and scipy, and whole rollouts against the independent planar Lagrangian reference."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import treeinfer as ti
from treeinfer.sim import observe as ob
from treeinfer.sim.planar_reference import PlanarTree


@pytest.fixture(scope="module")
def tree():
    return ti.load_tree(ti.example_path("two_branch"))


@pytest.fixture(scope="module")
def sim(tree):
    return ti.make_simulator(tree, 0.02, accuracy="coarse")


def test_rotation_vector_matches_scipy():
    rng = np.random.default_rng(0)
    vecs = np.concatenate(
        [rng.normal(size=(20, 3)), 1e-7 * rng.normal(size=(3, 3)), [[0.0, 0.0, 0.0]]]
    )
    vecs[:5] *= 2.5 / np.linalg.norm(vecs[:5], axis=1, keepdims=True)  # large angles, below pi
    mats = Rotation.from_rotvec(vecs).as_matrix()
    got = np.asarray(ob.rotation_vector(np.asarray(mats)))
    want = Rotation.from_matrix(mats).as_rotvec()
    np.testing.assert_allclose(got, want, atol=1e-6)  # float32 (the simulator's dtype)
    np.testing.assert_allclose(got[20:23], want[20:23], rtol=1e-3)  # small angles: no 0/0


def test_features_match_mujoco_kinematics(sim):
    import mujoco

    m = sim.mj_model
    d = mujoco.MjData(m)
    rng = np.random.default_rng(1)
    q = rng.uniform(-0.6, 0.6, size=(4, m.nq))  # row 0: the "rest" the features start from
    feats = (
        ob.feature_for(sim, "position", "child", 0.5),
        ob.feature_for(sim, "angle", "child", 0.5),
        ob.feature_for(sim, "position", "parent", 0.3),
        ob.feature_for(sim, "angle", "parent", 1.0),
    )
    got = np.asarray(ob.features_from_q(sim, np.asarray(q), feats))  # [T, F, 3]

    def frame(qk, body):
        d.qpos[:] = qk
        mujoco.mj_kinematics(m, d)
        return d.xpos[body].copy(), d.xmat[body].reshape(3, 3).copy()

    for f_i, f in enumerate(feats):
        p0, r0 = frame(q[0], f.body)
        for k in range(4):
            p, r = frame(q[k], f.body)
            if f.kind == "position":
                want = (p + r @ np.asarray(f.local)) - (p0 + r0 @ np.asarray(f.local))
            else:
                want = Rotation.from_matrix(r @ r0.T).as_rotvec()
            np.testing.assert_allclose(got[k, f_i], want, atol=2e-6)


def test_feature_rollout_keeps_tau(sim):
    forces = ti.data.forces.profile_set("mixed", n=2, duration=1.0, dt=0.02, seed=1)
    kp, kd = np.array([[60.0, 30.0], [100.0, 20.0]]), np.array([[0.5, 0.3], [1.0, 0.2]])
    feats = (ob.feature_for(sim, "position", "child", 0.5),)
    r = ob.simulate_features(sim, kp, kd, forces, feats)
    ro = ti.simulate(sim, kp, kd, forces)
    np.testing.assert_array_equal(np.asarray(r.tau), np.asarray(ro.tau))
    assert r.features.shape == (2, 2, forces.shape[1], 1, 3)
    np.testing.assert_array_equal(np.asarray(r.features)[:, :, 0], 0.0)  # rest at row 0


def test_channels_match_planar_reference(tree):
    """A marker mid-child and the child's and parent's tilt, against Lagrange + scipy."""
    dt = 0.02
    force = ti.data.forces.from_spec("hold:peak=4,ramp=0.4,hold=0.6,release=0.3", 2.0, dt)
    kp, kd = np.array([40.0, 80.0]), np.array([0.3, 0.8])  # order tree.inferred
    sim = ti.make_simulator(tree, dt, forces=force[None], sim_tolerance=2e-5)
    feats = (
        ob.feature_for(sim, "position", "child", 0.5),
        ob.feature_for(sim, "angle", "child", 0.5),
        ob.feature_for(sim, "angle", "parent", 0.5),
    )
    got = np.asarray(ob.simulate_features(sim, kp[None], kd[None], force[None], feats).features)
    ref = PlanarTree(tree, kp, kd)
    q = ref.rollout_q(force, dt)
    marker = np.array([ref.point(qk, "child", 0.5) for qk in q])
    marker -= marker[0]
    tilt_child = np.array([ref.rotation(qk, q[0], "child") for qk in q])
    tilt_parent = np.array([ref.rotation(qk, q[0], "parent") for qk in q])
    assert np.abs(marker).max() > 0.05  # the pull moves the marker by centimetres
    np.testing.assert_allclose(got[0, 0, :, 0], marker, atol=1e-4)
    np.testing.assert_allclose(got[0, 0, :, 1], tilt_child, atol=3e-4)
    np.testing.assert_allclose(got[0, 0, :, 2], tilt_parent, atol=3e-4)


def _camera():
    """A camera 2 m in front of the tree (looking along +y), image x right, y down."""
    rot = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # rows: x_c, y_c, z_c
    return (800.0, 780.0, 640.0, 360.0, *rot.ravel(), 0.5, -2.0, 1.3)


def test_image_channel_matches_pinhole_projection_of_planar_reference(tree):
    dt = 0.02
    force = ti.data.forces.from_spec("hold:peak=4,ramp=0.4,hold=0.6,release=0.3", 1.6, dt)
    kp, kd = np.array([40.0, 80.0]), np.array([0.3, 0.8])
    sim = ti.make_simulator(tree, dt, forces=force[None], sim_tolerance=2e-5)
    cam = _camera()
    f = ob.feature_for(sim, "image", "child", 0.5, cam)
    got = np.asarray(ob.simulate_features(sim, kp[None], kd[None], force[None], (f,)).features)
    ref = PlanarTree(tree, kp, kd)
    p = np.array([ref.point(qk, "child", 0.5) for qk in ref.rollout_q(force, dt)])  # world, m
    rot, centre = np.asarray(cam[4:13]).reshape(3, 3), np.asarray(cam[13:16])
    pc = (p - centre) @ rot.T
    uv = np.column_stack([800.0 * pc[:, 0] / pc[:, 2] + 640.0, 780.0 * pc[:, 1] / pc[:, 2] + 360.0])
    uv -= uv[0]
    assert np.abs(uv).max() > 20  # the marker moves tens of pixels
    np.testing.assert_allclose(got[0, 0, :, 0, :2], uv, atol=0.05)  # px
    np.testing.assert_array_equal(got[0, 0, :, 0, 2], 0.0)
