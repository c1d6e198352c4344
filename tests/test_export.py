"""MJCF and URDF export: the URDF compiled by MuJoCo's own importer is the same multibody.

The reference for the URDF is the MJCF export, and both are checked against the tree's own
geometry (world_frames, cylinder masses); the strongest check compares the joint-space mass
matrix and the gravity bias at random configurations, and a short passive rollout.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from treeinfer.errors import ConfigError, TreeFileError
from treeinfer.tree import generators as gen
from treeinfer.tree.description import Branch, load_tree, make_tree, world_frames
from treeinfer.tree.export import GRASP_SITE, to_mjmodel, write_mjcf
from treeinfer.tree.urdf import (
    BASE_LINK,
    load_model_file,
    mjmodel_from_urdf,
    rpy_from_matrix,
    to_urdf,
    write_urdf,
)

EXAMPLES = Path(__file__).resolve().parents[1] / "treeinfer" / "examples"
RTOL = 1e-8  # the MJCF writes 10 significant digits


def _mixed_tree():
    """Fixed (welded) branches at the root and mid-chain, a fork part-way along, 3-D azimuths."""
    return make_tree(
        [
            Branch("trunk", None, 0.8, 0.05, fixed=True),
            Branch("a", "trunk", 0.7, 0.03, angle_deg=20.0, azimuth_deg=30.0, attach=0.6),
            Branch("weld", "a", 0.4, 0.02, angle_deg=-10.0, fixed=True, density=900.0),
            Branch("b", "weld", 0.4, 0.015, angle_deg=15.0, azimuth_deg=-70.0, kp=150.0, kd=1.5),
            Branch("c", "a", 0.3, 0.012, angle_deg=-40.0, azimuth_deg=120.0, attach=0.5),
        ],
        grasp_branch="b",
        grasp_fraction=0.8,
        levels=2,
        base_position=(0.2, -0.1, 1.0),
        base_pitch_deg=50.0,
        base_yaw_deg=-30.0,
        gravity=(0.5, 0.0, -9.7),
    )


TREES = {
    "three_branch": lambda: load_tree(EXAMPLES / "three_branch.yaml"),
    "fractal": lambda: gen.fractal(
        3, 2, azimuths_deg=(20.0, -75.0), base_pitch_deg=35.0, base_yaw_deg=40.0
    ),
    "mixed": _mixed_tree,
}


def _jointed(tree):
    return [b.name for b in tree.branches if not b.fixed]


def _state(m, tree, q):
    """World-frame quantities of the tree's joints/bodies by name, at joint angles ``q``."""
    d = mujoco.MjData(m)
    names = _jointed(tree)
    jid = [m.joint(n).id for n in names]
    d.qpos[[m.jnt_qposadr[j] for j in jid]] = q
    mujoco.mj_forward(m, d)  # kinematics, inertia, bias forces at zero velocity
    dof = [m.jnt_dofadr[j] for j in jid]
    full = np.zeros((m.nv, m.nv))
    mujoco.mj_fullM(m, d, full)
    bid = [m.body(b.name).id for b in tree.branches]
    world_inertia = np.stack(
        [
            d.ximat[i].reshape(3, 3) @ np.diag(m.body_inertia[i]) @ d.ximat[i].reshape(3, 3).T
            for i in bid
        ]
    )
    return {
        "M": full[np.ix_(dof, dof)],
        "bias": d.qfrc_bias[dof],
        "anchor": d.xanchor[jid],
        "axis": d.xaxis[jid],
        "xpos": d.xpos[bid],
        "xmat": d.xmat[bid],
        "com": d.xipos[bid],
        "inertia": world_inertia,
        "mass": m.body_mass[bid],
        "site": d.site_xpos[m.site(GRASP_SITE).id],
        "site_body": m.body(m.site_bodyid[m.site(GRASP_SITE).id]).name,
        "stiffness": m.jnt_stiffness[jid],
        "damping": m.dof_damping[dof],
        "springref": m.qpos_spring[[m.jnt_qposadr[j] for j in jid]],
    }


def _models(tree):
    return to_mjmodel(tree), mjmodel_from_urdf(to_urdf(tree), tree)


# ---- rpy ----------------------------------------------------------------------------------------
def test_rpy_from_matrix_matches_scipy():
    rng = np.random.default_rng(0)
    mats = list(Rotation.random(50, random_state=1).as_matrix())
    mats += [
        Rotation.from_euler("xyz", [a, s * math.pi / 2, b]).as_matrix()
        for a, b in rng.uniform(-3, 3, (5, 2))
        for s in (-1, 1)
    ]  # gimbal lock
    mats += [
        Rotation.from_euler("xyz", [0.3, s * (math.pi / 2 - 1e-7), -1.1]).as_matrix()
        for s in (-1, 1)
    ]
    for r in mats:
        rpy = rpy_from_matrix(r)
        # URDF rpy: fixed-axis roll about x, then pitch about y, then yaw about z
        np.testing.assert_allclose(Rotation.from_euler("xyz", rpy).as_matrix(), r, atol=1e-9)


# ---- MJCF ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", sorted(TREES))
def test_mjcf_matches_tree_geometry(kind, tmp_path):
    tree = TREES[kind]()
    m = mujoco.MjModel.from_xml_path(str(write_mjcf(tree, tmp_path / "t.xml")))
    s = _state(m, tree, np.zeros(len(_jointed(tree))))
    frames = world_frames(tree)
    for i, b in enumerate(tree.branches):
        p, r = frames[b.name]
        np.testing.assert_allclose(s["xpos"][i], p, atol=1e-9)
        np.testing.assert_allclose(s["xmat"][i].reshape(3, 3), r, atol=1e-9)
        np.testing.assert_allclose(s["com"][i], p + r[:, 0] * b.length / 2, atol=1e-9)
        dens = tree.density if b.density is None else b.density
        assert s["mass"][i] == pytest.approx(dens * math.pi * b.radius**2 * b.length, rel=RTOL)
    for k, n in enumerate(_jointed(tree)):
        np.testing.assert_allclose(s["anchor"][k], frames[n][0], atol=1e-9)
        np.testing.assert_allclose(s["axis"][k], frames[n][1][:, 1], atol=1e-9)
    g = tree.branch(tree.grasp_branch)
    p, r = frames[g.name]
    np.testing.assert_allclose(s["site"], p + r[:, 0] * tree.grasp_fraction * g.length, atol=1e-9)


# ---- URDF through MuJoCo's importer -------------------------------------------------------------
@pytest.mark.parametrize("kind", sorted(TREES))
def test_urdf_same_kinematic_tree(kind):
    tree = TREES[kind]()
    mj, ur = _models(tree)

    def parent(m, name):
        return m.body(m.body_parentid[m.body(name).id]).name

    for b in tree.branches:
        assert parent(mj, b.name) == ("world" if b.parent is None else b.parent)
        assert parent(ur, b.name) == (BASE_LINK if b.parent is None else b.parent)
    assert ur.body(BASE_LINK).mass[0] == 0 and ur.body_parentid[ur.body(BASE_LINK).id] == 0
    assert sorted(ur.joint(j).name for j in range(ur.njnt)) == sorted(_jointed(tree))
    assert all(t == mujoco.mjtJoint.mjJNT_HINGE for t in ur.jnt_type)
    for m in (mj, ur):
        assert m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT
        assert m.opt.integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST
        np.testing.assert_allclose(m.opt.gravity, tree.gravity)
    q = np.random.default_rng(3).uniform(-0.6, 0.6, len(_jointed(tree)))
    a, b = _state(mj, tree, q), _state(ur, tree, q)
    for key in ("anchor", "axis", "xpos", "xmat", "com", "site"):
        np.testing.assert_allclose(b[key], a[key], rtol=RTOL, atol=1e-9, err_msg=key)
    for key in ("mass", "inertia", "stiffness", "damping", "springref"):
        np.testing.assert_allclose(b[key], a[key], rtol=RTOL, atol=1e-12, err_msg=key)
    assert a["site_body"] == b["site_body"] == tree.grasp_branch


@pytest.mark.parametrize("kind", sorted(TREES))
def test_urdf_same_dynamics(kind):
    """Mass matrix and gravity bias agree at random configurations (they fix the dynamics)."""
    tree = TREES[kind]()
    mj, ur = _models(tree)
    rng = np.random.default_rng(11)
    for _ in range(4):
        q = rng.uniform(-1.0, 1.0, len(_jointed(tree)))
        a, b = _state(mj, tree, q), _state(ur, tree, q)
        np.testing.assert_allclose(b["M"], a["M"], rtol=RTOL, atol=1e-12 * np.abs(a["M"]).max())
        np.testing.assert_allclose(
            b["bias"], a["bias"], rtol=RTOL, atol=1e-10 * np.abs(a["bias"]).max()
        )
        assert np.all(np.linalg.eigvalsh(a["M"]) > 0)


def test_urdf_same_passive_motion():
    """A short free swing under gravity and the springs: both models move alike."""
    tree = TREES["mixed"]()
    out = []
    for m in _models(tree):
        d = mujoco.MjData(m)
        for _ in range(200):
            mujoco.mj_step(m, d)
        out.append(np.array([d.qpos[m.jnt_qposadr[m.joint(n).id]] for n in _jointed(tree)]))
    assert np.abs(out[0]).max() > 1e-3  # it did move
    np.testing.assert_allclose(out[1], out[0], rtol=1e-6, atol=1e-9)


def test_urdf_text_structure(tmp_path):
    tree = _mixed_tree()
    root = ET.fromstring(write_urdf(tree, tmp_path / "t.urdf").read_text())
    assert root.tag == "robot" and root.find("mujoco/compiler").get("fusestatic") == "false"
    joints = {j.get("name"): j for j in root.findall("joint")}
    assert joints["weld"].get("type") == "fixed" and joints["trunk"].get("type") == "fixed"
    assert joints["a"].get("type") == "revolute"
    assert joints["a"].find("axis").get("xyz") == "0 1 0"
    lim = joints["a"].find("limit")
    assert float(lim.get("lower")) <= -3.14 and float(lim.get("upper")) >= 3.14
    assert float(joints["b"].find("dynamics").get("damping")) == 1.5
    for link in root.findall("link")[2:]:
        assert link.find("inertial/inertia") is not None
        assert (
            link.find("visual/geometry/cylinder") is not None
            and link.find("collision/geometry/cylinder") is not None
        )


def test_urdf_reserved_names_and_bad_integrator():
    tree = make_tree([Branch("base_link", None, 1.0, 0.05)], "base_link")
    with pytest.raises(TreeFileError, match="reserved"):
        to_urdf(tree)
    with pytest.raises(ConfigError, match="integrator"):
        to_urdf(_mixed_tree(), integrator="leapfrog")


# ---- users' own model files ---------------------------------------------------------------------
def test_load_model_file(tmp_path):
    tree = load_tree(EXAMPLES / "three_branch.yaml")
    m_xml = load_model_file(write_mjcf(tree, tmp_path / "t.xml"))
    m_urdf = load_model_file(write_urdf(tree, tmp_path / "t.urdf"))
    assert m_xml.njnt == m_urdf.njnt == 4
    # the <mujoco> extension in the URDF is honoured: options, no contacts, fixed bodies kept
    assert m_urdf.opt.timestep == pytest.approx(0.002)
    assert m_urdf.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT
    assert m_urdf.ngeom == 2 * len(tree.branches)  # the visual geoms are kept too
    bad = tmp_path / "bad.urdf"
    bad.write_text(
        "<robot name='x'><link name='a'/><joint name='j' type='revolute'></joint></robot>"
    )
    with pytest.raises(TreeFileError) as e:
        load_model_file(bad)
    assert (
        str(bad) in str(e.value)
        and "URDF" in str(e.value)
        and len(str(e.value)) > len(str(bad)) + 40
    )
    broken = tmp_path / "broken.xml"
    broken.write_text("<mujoco><worldbody><body></worldbody></mujoco>")
    # refused by the model-path checks before MuJoCo parses it: the file, the XML error, where
    with pytest.raises(TreeFileError, match=r"broken\.xml: not valid XML \(mismatched tag: line 1"):
        load_model_file(broken)
    with pytest.raises(TreeFileError, match="no such file"):
        load_model_file(tmp_path / "none.urdf")
    with pytest.raises(TreeFileError, match="expected .xml"):
        load_model_file(tmp_path / "t.yaml")


def test_mjmodel_from_urdf_errors():
    tree = load_tree(EXAMPLES / "three_branch.yaml")
    with pytest.raises(TreeFileError, match="cannot parse"):
        mjmodel_from_urdf("<robot><link></robot>", tree)
    other = gen.chain(2, 0.5, 0.02)
    with pytest.raises(TreeFileError, match="no link named 'branch2'"):
        mjmodel_from_urdf(to_urdf(other), tree)
