"""QSM cylinder tables (treeinfer.tree.qsm) and their conversion to trees
(treeinfer.tree.qsm_convert), on small synthetic tables written in every layout."""

from __future__ import annotations

import math

import numpy as np
import pytest
from qsm_fixtures import BASE, SUFFIX, WRITERS, sapling, write_simpleforest, write_treeqsm_v23

from treeinfer.errors import ConfigError, TreeFileError
from treeinfer.tree import read_qsm, tree_from_qsm
from treeinfer.tree.qsm_convert import carried_inertia
from treeinfer.tree.qsm_wood import SPECIES, stiffness_box
from treeinfer.tree.types import branch_inertial, world_frames


def _write(tmp_path, kind, **kw):
    return WRITERS[kind](tmp_path / f"qsm_{kind}{SUFFIX.get(kind, '.csv')}", **kw)


# ---- reading ------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", sorted(WRITERS))
def test_every_layout_reads_the_same_table(tmp_path, kind):
    ref = sapling()
    cyl = read_qsm(_write(tmp_path, kind))
    expected_fmt = {"treeqsm-v24": "treeqsm-txt", "treeqsm-v23": "treeqsm-txt"}.get(kind, kind)
    assert cyl.fmt == expected_fmt and cyl.units == "m"
    np.testing.assert_allclose(cyl.start, ref["start"], atol=1e-6)
    np.testing.assert_allclose(cyl.end, ref["end"], atol=1e-6)
    np.testing.assert_allclose(cyl.radius, ref["radius"], atol=1e-6)
    np.testing.assert_array_equal(cyl.parent, ref["parent"])
    np.testing.assert_array_equal(cyl.order, ref["order"])  # aRchi's trunk = 1 read as 0


def test_treeqsm_v23_in_the_mat_field_order(tmp_path):
    cyl = read_qsm(write_treeqsm_v23(tmp_path / "cyl_data_x.txt", mat_order=True))
    np.testing.assert_array_equal(cyl.order, sapling()["order"])


def test_units_are_checked_and_can_be_given(tmp_path):
    path = write_simpleforest(tmp_path / "cm.csv", scale=100.0)
    with pytest.raises(TreeFileError, match="not metres; give the unit"):
        read_qsm(path)
    cyl = read_qsm(path, units="cm")
    np.testing.assert_allclose(cyl.end, sapling()["end"], atol=1e-6)


def _corrupt(tmp_path, line: int, column: int, value: str):
    path = write_simpleforest(tmp_path / "sf.csv")
    lines = path.read_text().splitlines()
    cells = lines[line - 1].split(",")
    cells[column] = value
    lines[line - 1] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize(
    "line, column, value, message",
    [
        (4, 8, "nan", r"line 4, column 'radius'.*not finite"),
        (4, 8, "abc", r"line 4, column 'radius': expected a number"),
        (5, 8, "0", r"line 5 \(cylinder 3\): radius 0 must be positive"),
        (5, 8, "-0.01", r"line 5 \(cylinder 3\): radius -0.01 must be positive"),
        (6, 1, "99", r"line 6 \(cylinder 4\): parent 99 is no cylinder"),
        (2, 1, "5", r"a cycle"),
        (8, 2, "11", r"line 8 \(cylinder 6\): starts .* m from its parent"),
    ],
)
def test_bad_tables_name_file_line_and_column(tmp_path, line, column, value, message):
    path = _corrupt(tmp_path, line, column, value)
    with pytest.raises(TreeFileError, match=message) as e:
        read_qsm(path)
    assert str(path) in str(e.value)


def test_a_nan_in_the_first_row_of_a_headerless_table(tmp_path):
    path = write_treeqsm_v23(tmp_path / "cyl_data_nan.txt")
    rows = path.read_text().splitlines()
    rows[0] = "NaN\t" + rows[0].split("\t", 1)[1]
    path.write_text("\n".join(rows) + "\n")
    with pytest.raises(TreeFileError, match="line 1, column 'radius': NaN \\(not finite\\)"):
        read_qsm(path)


def test_missing_columns_and_unknown_layouts(tmp_path):
    path = write_simpleforest(tmp_path / "sf.csv")
    text = path.read_text().replace("parentID", "parent_id_x")
    path.write_text(text)
    with pytest.raises(TreeFileError, match="no QSM layout"):
        read_qsm(path)
    with pytest.raises(TreeFileError, match=r"needs column\(s\) \['parentID'\]"):
        read_qsm(path, fmt="simpleforest")
    short = tmp_path / "short.txt"
    short.write_text("0.1\t0.2\t0\t0\t0\n")
    with pytest.raises(TreeFileError, match="5 columns; a TreeQSM 2.3 cylinder table"):
        read_qsm(short)
    ragged = write_treeqsm_v23(tmp_path / "ragged.txt")
    rows = ragged.read_text().splitlines()
    rows[3] = rows[3].rsplit("\t", 1)[0]
    ragged.write_text("\n".join(rows) + "\n")
    with pytest.raises(TreeFileError, match="line 4: 14 columns, expected 15"):
        read_qsm(ragged)


# ---- conversion ---------------------------------------------------------------------------------
def _qsm_mass_and_com(cyl, density):
    m = density * math.pi * cyl.radius**2 * cyl.length
    return float(m.sum()), (m[:, None] * 0.5 * (cyl.start + cyl.end)).sum(0) / m.sum()


def _tree_mass_and_com(tree):
    frames = world_frames(tree)
    total, moment = 0.0, np.zeros(3)
    for b in tree.branches:
        p, r = frames[b.name]
        m, com, _ = branch_inertial(tree, b)
        total += m
        moment += m * (p + r @ com)
    return total, moment / total


def _mujoco_body_inertia(mj, body: int):
    """(mass, world com [3], world inertia about it [3, 3]) of a compiled body at qpos0."""
    import mujoco

    d = mujoco.MjData(mj)
    mujoco.mj_kinematics(mj, d)
    rot = d.ximat[body].reshape(3, 3)
    return mj.body_mass[body], d.xipos[body].copy(), rot @ np.diag(mj.body_inertia[body]) @ rot.T


def _lumped_reference(res, name):
    """The link ``name`` and the QSM cylinders lumped onto it as solid cylinder geoms of one
    MuJoCo body, MuJoCo computing the body's inertia from them (independent of
    treeinfer.tree.lump): (mass, world com, world inertia about it)."""
    import mujoco

    cyl, rho = res.cylinders, res.wood.density
    start, end = cyl.start - res.origin, cyl.end - res.origin
    frames = world_frames(res.tree)
    b = res.tree.branch(name)
    p, r = frames[name]
    segs = [(p, p + r[:, 0] * b.length, b.radius, res.tree.density)]
    host = {lk.name: set(lk.cylinders) for lk in res.links}[name]
    for i in np.flatnonzero(res.lumped):  # lumped onto this link: its nearest link ancestor's
        j = i
        while res.lumped[j]:
            j = int(cyl.parent[j])
        if j in host:
            segs.append((start[i], end[i], cyl.radius[i], rho))
    fmt = lambda v: " ".join(f"{x:.12g}" for x in v)
    geoms = "".join(
        f'<geom type="cylinder" fromto="{fmt(a)} {fmt(e)}" size="{rr:.12g}" density="{d:.12g}"/>'
        for a, e, rr, d in segs
    )
    mj = mujoco.MjModel.from_xml_string(
        f'<mujoco><compiler inertiafromgeom="true"/><worldbody><body name="x">'
        f"<freejoint/>{geoms}</body></worldbody></mujoco>"
    )
    return _mujoco_body_inertia(mj, 1)


@pytest.mark.parametrize("kind", sorted(WRITERS))
def test_chain_to_a_grasp_point_keeps_geometry_mass_and_centre_of_mass(tmp_path, kind):
    grasp = BASE + [0.7, 0.0, 1.02]  # 2 cm above the branch, 0.7 m out
    res = tree_from_qsm(_write(tmp_path, kind), grasp_point=tuple(grasp))
    tree = res.tree
    assert [lk.name for lk in res.links] == ["stem", "b1"]
    assert tree.inferred == ("b1", "stem")
    assert tree.grasp_branch == "b1"
    assert tree.grasp_fraction == pytest.approx(0.7, abs=1e-6)  # the branch starts at the stem
    # independent reference: the QSM's own geometry (base moved to the origin)
    frames = world_frames(tree)
    for lk in res.links:
        p, r = frames[lk.name]
        b = tree.branch(lk.name)
        qsm_end = res.cylinders.end[lk.cylinders[-1]] - BASE
        np.testing.assert_allclose(p + r[:, 0] * b.length, qsm_end, atol=1e-5)
    p, r = frames["b1"]
    np.testing.assert_allclose(p, [0, 0, 1.0], atol=1e-5)  # the stem link ends at the fork
    assert tree.branch("stem").length == pytest.approx(1.0)
    # lumping keeps the mass of the whole tree, and the first moment of what it lumps ...
    qm, qc = _qsm_mass_and_com(res.cylinders, res.wood.density)
    tm, tc = _tree_mass_and_com(tree)
    assert tm == pytest.approx(qm, rel=1e-4)
    # ... and every lump is part of its link's body: MuJoCo's own inertia of the link and the
    # cylinders lumped onto it (as geoms of one body) is the exported body's
    from treeinfer.tree.export import to_mjmodel

    mj = to_mjmodel(tree)
    assert mj.nbody == len(res.links) + 1 and mj.njnt == len(res.links)  # one body per joint
    assert set(res.lumps) <= {lk.name for lk in res.links} and res.lumps
    for name in res.lumps:
        m_ref, c_ref, i_ref = _lumped_reference(res, name)
        m, c, inertia = _mujoco_body_inertia(mj, mj.body(name).id)
        assert m == pytest.approx(m_ref, rel=1e-6)
        np.testing.assert_allclose(c, c_ref, atol=1e-7)
        np.testing.assert_allclose(inertia, i_ref, rtol=1e-5, atol=1e-9 * np.abs(i_ref).max())
    # ... while a link of one radius puts its mass at its middle: the tapered QSM's centre of
    # mass moves by less than 2 cm here
    np.testing.assert_allclose(tc, qc - BASE, atol=0.02)
    assert res.report["lumped_mass_kg"] > 0 and res.report["dropped_mass_kg"] == 0


def test_hinges_turn_about_the_pull_moment(tmp_path):
    res = tree_from_qsm(_write(tmp_path, "simpleforest"), grasp_point=tuple(BASE + [1.0, 0, 1]))
    frames = world_frames(res.tree)
    gp = res.grasp_point
    for name in res.tree.inferred:
        p, r = frames[name]
        moment = np.cross(gp - p, [0.0, 0.0, -1.0])
        moment -= np.dot(moment, r[:, 0]) * r[:, 0]
        cos = abs(float(r[:, 1] @ moment)) / np.linalg.norm(moment)
        assert cos > math.cos(math.radians(5.0)), name


def test_joint_spacing_pruning_and_rest_options(tmp_path):
    path = _write(tmp_path, "archi")
    spaced = tree_from_qsm(path, joint_spacing=0.6)  # default grasp: the stem's top
    assert [lk.name for lk in spaced.links] == ["stem_1", "stem_2", "stem_3", "stem_4"]
    lengths = [spaced.tree.branch(lk.name).length for lk in spaced.links]
    np.testing.assert_allclose(lengths, 0.6, atol=1e-6)
    assert spaced.tree.grasp_branch == "stem_4" and spaced.tree.grasp_fraction == 1.0

    keep = tree_from_qsm(path, rest="keep")
    assert {lk.name for lk in keep.links} == {"stem_1", "stem_2", "b1_1", "b1_2", "b2"}
    assert keep.report["lumped_mass_kg"] == 0
    assert keep.tree.inferred == ("stem_2", "stem_1")
    fixed = keep.tree.branch("b1_1")
    assert fixed.kp is not None and fixed.kd is not None  # not inferred: fixed gains from wood

    pruned = tree_from_qsm(path, rest="keep", prune_diameter=0.01)  # the 6 mm twig goes
    assert "b2" not in {lk.name for lk in pruned.links}
    assert pruned.report["pruned"] == 2 and pruned.report["lumped_mass_kg"] > 0

    dropped = tree_from_qsm(path, rest="drop", grasp_cylinder=15)
    assert dropped.report["lumped_mass_kg"] == 0 and dropped.report["dropped_mass_kg"] > 0
    assert not dropped.lumps and dropped.tree.grasp_branch == "b1"

    one = tree_from_qsm(path, grasp_cylinder=15, levels=1)
    assert one.tree.inferred == ("b1",)
    assert one.tree.branch("stem").kp is not None


def test_prior_boxes_follow_the_wood(tmp_path):
    path = _write(tmp_path, "simpleforest")
    res = tree_from_qsm(path, grasp_cylinder=14, species="sugar-maple")
    wood = SPECIES["sugar-maple"]
    assert res.tree.density == pytest.approx(wood.density, rel=1e-3)
    link = next(lk for lk in res.links if lk.name == "b1")
    length = res.tree.branch("b1").length
    second = math.pi * link.base_radius**4 / 4
    lo, hi = res.tree.bounds["b1"].kp
    # the box holds the tip-moment (EI/L), pseudo-rigid-body (2.25 EI/L) and tip-force (3EI/L)
    # stiffness of a cantilever of that length and base radius
    for c in (1.0, 2.25, 3.0):
        assert lo <= c * wood.modulus * second / length <= hi
    assert (lo, hi) == pytest.approx(stiffness_box(wood, link.base_radius, length), rel=1e-3)
    # stiffer wood, stiffer box; the damping box brackets critical damping's few percent
    soft = tree_from_qsm(path, grasp_cylinder=14, modulus=4e9)
    assert soft.tree.bounds["b1"].kp[1] < hi
    kd_lo, kd_hi = res.tree.bounds["b1"].kd
    inertia = carried_inertia(res.tree)["b1"]
    crit = 2 * math.sqrt(math.sqrt(lo * hi) * inertia)
    assert kd_lo < 0.05 * crit < kd_hi


def test_carried_inertia_of_a_rod_about_its_end():
    from treeinfer.tree.description import Branch, make_tree

    tree = make_tree([Branch("a", None, 1.0, 0.01)], "a", base_pitch_deg=0.0, density=1000.0)
    m = 1000.0 * math.pi * 0.01**2
    # rod about a transverse axis through its end: m L^2 / 3 (+ m r^2 / 4 for the thickness)
    assert carried_inertia(tree)["a"] == pytest.approx(m / 3 + m * 0.01**2 / 4, rel=1e-9)


def test_bad_options(tmp_path):
    path = _write(tmp_path, "simpleforest")
    with pytest.raises(ConfigError, match="not both"):
        tree_from_qsm(path, grasp_point=(0, 0, 0), grasp_cylinder=3)
    with pytest.raises(TreeFileError, match="no cylinder with id 99"):
        tree_from_qsm(path, grasp_cylinder=99)
    with pytest.raises(ConfigError, match="species 'baobab'"):
        tree_from_qsm(path, species="baobab")
    with pytest.raises(ConfigError, match="rest 'keep-all'"):
        tree_from_qsm(path, rest="keep-all")
    with pytest.raises(ConfigError, match="joint spacing"):
        tree_from_qsm(path, joint_spacing=0.0)


def test_plot_returns_figure_and_axes(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from treeinfer.tree import plot_qsm

    res = tree_from_qsm(_write(tmp_path, "archi"), grasp_point=tuple(BASE + [1.0, 0, 1]))
    fig, axes = plot_qsm(res)
    assert len(axes) == 2 and axes[0].get_ylabel() == "z (m)"
    plt.close(fig)


# ---- the command --------------------------------------------------------------------------------
def test_cli_writes_a_tree_file_and_the_figure(tmp_path, capsys):
    from treeinfer.cli.main import main
    from treeinfer.tree.description import load_tree

    src = _write(tmp_path, "treeqsm-v24")
    out = tmp_path / "tree.yaml"
    args = ["tree", "--from-qsm", str(src), "--grasp-cylinder", "14", "--out", str(out)]
    assert main(args + ["--joint-spacing", "0.5"]) == 0
    tree = load_tree(out)
    assert tree.grasp_branch == "b1_1" and tree.inferred == ("b1_1", "stem_2", "stem_1")
    assert (tmp_path / "tree_qsm.png").stat().st_size > 1000
    assert "grasp: cylinder 14" in capsys.readouterr().out
    assert main(args) != 0  # exists: refused without --force
    assert "file exists" in capsys.readouterr().err
    assert main(args + ["--force", "--grasp", "b1"]) != 0
    assert "--grasp does not apply to --from-qsm" in capsys.readouterr().err


def test_joints_where_an_axis_bends():
    from treeinfer.tree.qsm_geometry import split_bends

    bend = np.array([math.cos(math.radians(30)), 0.0, math.sin(math.radians(30))])
    pts = [np.zeros(3)]
    for k in range(8):
        pts.append(pts[-1] + (np.array([0.1, 0, 0]) if k < 4 else 0.1 * bend))
    start, end = np.array(pts[:-1]), np.array(pts[1:])
    piece = list(range(8))
    assert split_bends(piece, start, end, 0.01) == [[0, 1, 2, 3], [4, 5, 6, 7]]
    assert split_bends(piece, start, end, 0.11) == [piece]  # the corner is 10.4 cm off the chord
    assert split_bends(piece, start, end, None) == [piece]


def test_straight_axes_get_no_bend_joints(tmp_path):
    res = tree_from_qsm(_write(tmp_path, "simpleforest"), grasp_cylinder=14, max_deviation=0.001)
    assert [lk.name for lk in res.links] == ["stem", "b1"]


def test_lumps_in_files_round_trip_and_bad_lumps_are_refused(tmp_path):
    import yaml

    from treeinfer.tree.description import dump_tree, load_tree, tree_to_dict

    # every converted tree writes as plain YAML and reads back the same
    path = _write(tmp_path, "archi")
    for kw in ({}, {"rest": "keep", "prune_diameter": 0.026}, {"grasp_cylinder": 15}):
        res = tree_from_qsm(path, **kw)
        out = dump_tree(res.tree, tmp_path / "t.yaml")
        yaml.safe_load(out.read_text())
        assert load_tree(out) == res.tree
    d = tree_to_dict(tree_from_qsm(path).tree)
    host = next(i for i, b in enumerate(d["branches"]) if "lump" in b)
    for field, value, message in (
        ("mass", -1.0, "lump: mass: expected a positive number"),
        ("com", [0.0, 1.0], "lump.com: expected a list of 3 numbers"),
        ("inertia", [1.0, 1.0, 3.0, 0.0, 0.0, 0.0], "not those of a rigid body"),
        ("inertia", [1.0, 1.0, "x", 0.0, 0.0, 0.0], "lump.inertia: expected numbers"),
    ):
        bad = yaml.safe_load(yaml.safe_dump(d))
        bad["branches"][host]["lump"][field] = value
        (tmp_path / "bad.yaml").write_text(yaml.safe_dump(bad))
        with pytest.raises(TreeFileError, match=rf"bad.yaml: branches\[{host}\].*{message}"):
            load_tree(tmp_path / "bad.yaml")


def test_a_leaning_stem_still_bends_about_the_pull_moment(tmp_path):
    """A stem leaning 20 degrees sideways to the grasp: its root hinge would be normal to the
    lean; the stem is twisted about its axis to the pull's moment, no welded body added, and the
    geometry is kept."""
    from treeinfer.tree.types import rot_x

    t = sapling()
    rot = rot_x(math.radians(20.0))
    for key in ("start", "end"):
        t[key] = BASE + (t[key] - BASE) @ rot.T
    path = write_simpleforest(tmp_path / "leaning.csv", t)
    grasp = BASE + rot @ np.array([0.9, 0.0, 1.0])
    res = tree_from_qsm(path, grasp_point=tuple(grasp))
    stem = res.tree.branch("stem")
    assert stem.parent is None and abs(stem.twist_deg) > 5.0
    assert not any(b.fixed for b in res.tree.branches)
    frames = world_frames(res.tree)
    for name in res.tree.inferred:
        p, r = frames[name]
        moment = np.cross(res.grasp_point - p, [0.0, 0.0, -1.0])
        moment -= np.dot(moment, r[:, 0]) * r[:, 0]
        assert abs(float(r[:, 1] @ moment)) / np.linalg.norm(moment) > math.cos(math.radians(5))
    for lk in res.links:
        p, r = frames[lk.name]
        end = res.cylinders.end[lk.cylinders[-1]] - BASE
        np.testing.assert_allclose(p + r[:, 0] * res.tree.branch(lk.name).length, end, atol=1e-5)
