"""Bring your own model (treeinfer.tree.usermodel): a user's URDF/MJCF from the tree's model:
section.

The reference for every check is the model treeinfer builds itself from the same tree
(treeinfer.tree.export.to_mjmodel): a user model that describes the same multibody must put the
grasp point at the same place and pull the same way.
"""

from __future__ import annotations

import re
from dataclasses import replace

import mujoco
import numpy as np
import pytest

from treeinfer.errors import TreeFileError
from treeinfer.sim import make_simulator, simulate
from treeinfer.sim.reference import simulate_reference
from treeinfer.tree import generators as gen
from treeinfer.tree.description import Branch, dump_tree, load_tree, make_tree, world_frames
from treeinfer.tree.export import to_mjmodel
from treeinfer.tree.urdf import to_urdf
from treeinfer.tree.usermodel import attach_model, prepare_user_model, tree_from_model


def _rounded(urdf: str, decimals: int = 3) -> str:
    """The URDF with masses and inertias rounded, as in published L-system tree files."""
    return re.sub(
        r'\b(i[xyz]{2}|value)="([-+0-9.eE]+)"',
        lambda m: f'{m.group(1)}="{round(float(m.group(2)), decimals)}"',
        urdf,
    )


@pytest.fixture(scope="module")
def big_tree():
    tree = gen.lsystem("F", {"F": "F[+F][-F]F"}, 4, angle_deg=25, step_length=0.3)
    assert sum(not b.fixed for b in tree.branches) >= 100
    return tree


@pytest.fixture(scope="module")
def big_urdf(big_tree, tmp_path_factory):
    p = tmp_path_factory.mktemp("big") / "lsystem.urdf"
    p.write_text(_rounded(to_urdf(big_tree)))
    return p


def _site_world(m) -> np.ndarray:
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    return d.site_xpos[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, "grasp")].copy()


def test_rounded_inertia_error_names_links(big_tree, big_urdf):
    with pytest.raises(TreeFileError, match=r"degenerate mass or inertia.*s1: inertia"):
        prepare_user_model(attach_model(big_tree, big_urdf))


def test_repaired_100_joint_model_pulls(big_tree, big_urdf):
    tree = attach_model(big_tree, big_urdf, repair_inertia="geometry")
    sim = make_simulator(tree, obs_dt=0.01, substeps=2)
    rep = sim.model_report
    assert len(rep["repaired"]) >= 100 and "solid cylinder" in rep["repaired"]["s1"]
    assert rep["fixed_gains"]["joints"] == sim.mj_model.njnt >= 100
    # the grasp point at rest is where the tree-built model has it
    np.testing.assert_allclose(
        _site_world(sim.mj_model), _site_world(to_mjmodel(big_tree)), atol=1e-9
    )
    # the repaired inertia is the cylinder's: the same mass matrix as the tree-built model
    # up to the masses' rounding (3 decimals of kg)
    ref = make_simulator(big_tree, obs_dt=0.01, substeps=2)
    kp, kd = np.full(tree.n_inferred, 50.0), np.full(tree.n_inferred, 1.0)
    force = np.linspace(0.0, 20.0, 6)
    tau, _ = simulate_reference(sim, kp, kd, force)
    tau_ref, _ = simulate_reference(ref, kp, kd, force)
    assert np.all(np.isfinite(tau)) and tau[-1] > 1e-3
    np.testing.assert_allclose(tau, tau_ref, rtol=0.05, atol=1e-5)


def test_floor_repair_compiles(big_tree, big_urdf):
    prep = prepare_user_model(attach_model(big_tree, big_urdf, repair_inertia="floor"))
    assert "floored" in prep.report["repaired"]["s1"]
    moving = prep.mj_model.body_dofnum > 0  # base_link (welded to the world) stays massless
    assert moving.sum() >= 100 and np.all(prep.mj_model.body_inertia[moving] > 0)


# ---- a small chain: JAX rollouts, name maps, gains, grasp axis, limits --------------------------
@pytest.fixture(scope="module")
def chain():
    return gen.chain(
        3, lengths=[0.6, 0.5, 0.4], radii=[0.03, 0.02, 0.015], angles_deg=[0, 20, 20], levels=2
    )


def _write(tmp_path, text: str, name: str = "m.urdf"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_user_urdf_simulates_like_tree_model(chain, tmp_path):
    """The tree's own URDF, loaded as a user model, pulls exactly like the tree-built model."""
    tree = attach_model(chain, _write(tmp_path, to_urdf(chain)))
    kp, kd = np.array([[40.0] * chain.n_inferred]), np.array([[0.8] * chain.n_inferred])
    force = np.linspace(0.0, 10.0, 8)[None]
    a = simulate(make_simulator(tree, substeps=3), kp, kd, force)
    b = simulate(make_simulator(chain, substeps=3), kp, kd, force)
    assert bool(a.stable.all()) and float(a.tau[0, 0, -1]) > 1e-4
    np.testing.assert_allclose(np.asarray(a.tau), np.asarray(b.tau), atol=2e-6)


def test_name_map_derived_from_urdf_joints(chain, tmp_path):
    """URDF joints named unlike their child links: matched through the joint -> child relation."""
    text = to_urdf(chain)
    for b in chain.branches:
        text = text.replace(f'<joint name="{b.name}"', f'<joint name="hinge_{b.name}"')
    prep = prepare_user_model(attach_model(chain, _write(tmp_path, text)))
    assert prep.report["joints"] == {b.name: f"hinge_{b.name}" for b in chain.branches}
    names = [prep.mj_model.joint(j).name for j in range(prep.mj_model.njnt)]
    assert set(chain.inferred) <= set(names)  # renamed to the branch names for the simulator


def test_explicit_name_map_and_unmatched_error(chain, tmp_path):
    path = _write(tmp_path, to_urdf(chain))
    ren = {b.name: f"branch_{i}" for i, b in enumerate(chain.branches)}
    branches = [
        replace(b, name=ren[b.name], parent=None if b.parent is None else ren[b.parent])
        for b in chain.branches
    ]
    tree = make_tree(branches, grasp_branch=ren[chain.grasp_branch], levels=2)
    with pytest.raises(TreeFileError, match=r"Unmatched branch\(es\) \['branch_0', 'branch_1'"):
        prepare_user_model(attach_model(tree, path))
    model = {
        "file": str(path),
        "joints": {v: k for k, v in ren.items()},
        "bodies": {v: k for k, v in ren.items()},
    }
    tree = replace(tree, model=model)
    sim = make_simulator(tree, substeps=2)
    assert sim.joint_names == tree.inferred
    np.testing.assert_allclose(_site_world(sim.mj_model), _site_world(to_mjmodel(chain)), atol=1e-9)
    bad = replace(tree, model={**model, "joints": {"branch_0": "no_such_joint"}})
    with pytest.raises(TreeFileError, match="branch_0 -> joint 'no_such_joint'"):
        prepare_user_model(bad)


def test_fixed_gains_on_every_other_hinge(chain, tmp_path):
    path = _write(tmp_path, to_urdf(chain))
    root = chain.branches[0].name  # not inferred (levels=2 of 3)
    assert root not in chain.inferred
    branches = [replace(b, kp=123.0, kd=4.5) if b.name == root else b for b in chain.branches]
    tree = attach_model(
        replace(chain, branches=tuple(branches), fixed_kp=777.0, fixed_kd=7.0), path
    )
    m = prepare_user_model(tree).mj_model
    for j in range(m.njnt):
        name = m.joint(j).name
        kp, kd = (123.0, 4.5) if name == root else (777.0, 7.0)
        assert m.jnt_stiffness[j] == pytest.approx(kp) and m.dof_damping[j] == pytest.approx(kd)
    # the model's own gains (URDF has no stiffness): a clear error naming the joints
    keep = replace(tree, model={**tree.model, "gains": "model"})
    non_inferred = [b.name for b in chain.branches if b.name not in chain.inferred]
    with pytest.raises(TreeFileError, match=re.escape(str(non_inferred))):
        prepare_user_model(keep)


_Z_CHAIN = """<mujoco model="zchain">
  <worldbody>
    <body name="trunk" pos="0 0 0">
      <joint name="j_trunk" type="hinge" axis="0 1 0"/>
      <geom type="cylinder" fromto="0 0 0 0 0 0.8" size="0.03" density="700"/>
      <body name="limb" pos="0 0 0.8" euler="0 30 0">
        <joint name="j_limb" type="hinge" axis="0 1 0"/>
        <geom type="cylinder" fromto="0 0 0 0 0 0.5" size="0.02" density="700"/>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


def test_grasp_along_real_link_axis(tmp_path):
    """Links along local z (MJCF): the grasp point lies on that axis, not on local x."""
    path = _write(tmp_path, _Z_CHAIN, "z.xml")
    tree = tree_from_model(path, grasp="limb", grasp_fraction=0.5, levels=2)
    assert [b.length for b in tree.branches] == pytest.approx([0.8, 0.5])
    # the description's own geometry (summaries) puts the grasp point where the model has it
    p0, rot = world_frames(tree)["limb"]
    described = p0 + rot[:, 0] * 0.5 * tree.branch("limb").length
    sim = make_simulator(tree, substeps=2)
    np.testing.assert_allclose(sim.mj_model.site_pos[sim.grasp_site], [0, 0, 0.25], atol=1e-12)
    np.testing.assert_allclose(described, _site_world(sim.mj_model), atol=1e-9)
    # the same tree built by treeinfer (vertical trunk, limb tilted by the same angle)
    own = make_tree(
        [Branch("trunk", None, 0.8, 0.03), Branch("limb", "trunk", 0.5, 0.02, angle_deg=-30.0)],
        grasp_branch="limb",
        grasp_fraction=0.5,
        levels=2,
        base_pitch_deg=90.0,
    )
    np.testing.assert_allclose(_site_world(sim.mj_model), _site_world(to_mjmodel(own)), atol=1e-9)
    # a fraction given per profile goes along the same axis
    np.testing.assert_allclose(np.asarray(sim.branch_point(None, 0.5, 1.0)), [0, 0, 0.5], atol=1e-6)
    # an explicit local position wins
    t2 = replace(tree, model={**tree.model, "grasp_position": [0.01, 0.0, 0.4]})
    prep = prepare_user_model(t2)
    assert prep.report["grasp_site"] == pytest.approx([0.01, 0.0, 0.4])


def test_joint_limits_refused_or_ignored(chain, tmp_path):
    text = to_urdf(chain).replace(
        'lower="-3.141592653589793" upper="3.141592653589793"', 'lower="-0.5" upper="0.5"', 1
    )
    path = _write(tmp_path, text)
    root = chain.branches[0].name
    with pytest.raises(
        TreeFileError, match=rf"limits the simulator does not model.*{root} \[-0.5, 0.5\]"
    ):
        prepare_user_model(attach_model(chain, path))
    tree = attach_model(chain, path)
    prep = prepare_user_model(replace(tree, model={**tree.model, "limits": "ignore"}))
    assert prep.report["limits_ignored"] == [root]
    assert not np.any(prep.mj_model.jnt_limited)
    # treeinfer's own export writes +-pi limits, which never act: accepted silently
    assert (
        prepare_user_model(attach_model(chain, _write(tmp_path, to_urdf(chain), "ok.urdf"))).report[
            "limits_ignored"
        ]
        == []
    )


def test_model_section_round_trip_and_changed_file(chain, tmp_path):
    path = _write(tmp_path, to_urdf(chain))
    tree = attach_model(chain, path)
    dump_tree(tree, tmp_path / "t.yaml")
    back = load_tree(tmp_path / "t.yaml")
    assert back.model == tree.model and len(back.model["sha256"]) == 64
    path.write_text(to_urdf(replace(chain, fixed_kd=3.0)))
    with pytest.raises(TreeFileError, match="changed since it was recorded"):
        prepare_user_model(back)
    with pytest.raises(TreeFileError, match="URDF/MJCF model, not a tree description"):
        load_tree(path)


# ---- the command line -------------------------------------------------------------------------
@pytest.mark.slow  # ~30 s CPU (tiny infer); over a minute on the shared 2-core machine
def test_cli_model_tree_simulate_infer_predict(chain, tmp_path, capsys):
    """tree --model (rounded inertias: error naming a link, then --repair-inertia), simulate and
    infer from the tree file's model: section, predict with the model file moved (sha256 kept)."""
    import json
    import shutil

    from treeinfer.cli import main

    def run(*argv):
        rc = main([str(a) for a in argv])
        out, err = capsys.readouterr()
        return rc, out, err

    urdf = _write(tmp_path, _rounded(to_urdf(chain), 2))
    rc, _, err = run("tree", "--model", urdf, "--out", tmp_path / "t.yaml")
    assert rc == 2 and "degenerate mass or inertia" in err and "branch" in err, err
    rc, _, err = run("tree", "--from", urdf, "--out", tmp_path / "t.yaml")
    assert rc == 2 and "treeinfer tree --model" in err, err
    rc, out, err = run(
        "tree",
        "--model",
        urdf,
        "--repair-inertia",
        "geometry",
        "--levels",
        "1",
        "--out",
        tmp_path / "t.yaml",
    )
    assert rc == 0, err
    assert "repaired inertia of 3 link(s)" in err
    t = load_tree(tmp_path / "t.yaml")
    assert t.model["repair_inertia"] == "geometry" and t.model["file"] == str(urdf.resolve())

    data = tmp_path / "data"
    rc, _, err = run(
        "simulate",
        "--tree",
        tmp_path / "t.yaml",
        "--out",
        data,
        "--seed",
        "1",
        "--n-traj",
        "2",
        "--duration",
        "0.3",
        "--dt",
        "0.01",
        "--params",
        "60,1.0",
    )
    assert rc == 0, err
    assert "model: " in err and "repaired inertia" in err
    assert load_tree(data / "tree.yaml").model == t.model

    run_dir = tmp_path / "run"
    rc, _, err = run(
        "infer",
        "--tree",
        tmp_path / "t.yaml",
        "--data",
        data,
        "--out",
        run_dir,
        "--particles",
        "4",
        "--iterations",
        "2",
        "--checkpoint-every",
        "0",
        "--no-progress",
    )
    assert rc == 0, err
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["model"]["sha256"] == t.model["sha256"] and summary["model"]["repaired"]
    assert json.loads((run_dir / "config.json").read_text())["tree_dict"]["model"] == t.model

    moved = tmp_path / "moved.urdf"
    shutil.move(urdf, moved)
    traj = sorted(data.glob("traj_*.csv"))[0]
    rc, _, err = run("predict", "--run", run_dir, "--force", traj, "--out", tmp_path / "p0")
    assert rc == 2 and "no such model file" in err, err
    rc, _, err = run(
        "predict", "--run", run_dir, "--model", moved, "--force", traj, "--out", tmp_path / "p1"
    )
    assert rc == 0, err
    moved.write_text(to_urdf(chain))
    rc, _, err = run(
        "predict", "--run", run_dir, "--model", moved, "--force", traj, "--out", tmp_path / "p2"
    )
    assert rc == 2 and "changed since it was recorded" in err, err


def test_tree_from_model_reproduces_generated_tree(big_tree, big_urdf):
    """`tree --model` on treeinfer's own export gives back the generated tree's geometry."""
    t = tree_from_model(big_urdf, grasp=big_tree.grasp_branch)
    assert t.names == big_tree.names and "joints" not in t.model
    for a, b in zip(t.branches, big_tree.branches):
        assert a.parent == b.parent and a.fixed == b.fixed
        got = [a.length, a.radius, a.angle_deg, a.azimuth_deg, a.attach]
        assert got == pytest.approx(
            [b.length, b.radius, b.angle_deg, b.azimuth_deg, b.attach], abs=1e-9
        )
