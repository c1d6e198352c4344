"""Tree descriptions: file round trips, validation errors, frames and inferred-joint pairs."""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path

import numpy as np
import pytest

from treeinfer.errors import TreeFileError
from treeinfer.tree.description import (
    Bounds,
    Branch,
    dump_tree,
    load_tree,
    make_tree,
    tree_from_dict,
    tree_to_dict,
    world_frames,
)

EXAMPLES = Path(__file__).resolve().parents[1] / "treeinfer" / "examples"


def _base_dict() -> dict:
    return {
        "name": "t",
        "base": {"position": [0.0, 0.0, 1.0], "pitch_deg": 10.0, "yaw_deg": 5.0},
        "branches": [
            {"name": "a", "parent": None, "length": 0.8, "radius": 0.03},
            {"name": "b", "parent": "a", "length": 0.6, "radius": 0.02, "angle_deg": 15.0},
            {
                "name": "c",
                "parent": "b",
                "length": 0.4,
                "radius": 0.01,
                "angle_deg": -5.0,
                "azimuth_deg": 30.0,
            },
        ],
        "grasp": {"branch": "c", "fraction": 0.9},
        "inference": {"levels": 2, "prior": {"kp": [5.0, 500.0], "kd": [0.05, 10.0]}},
    }


def _varied_tree():
    """A tree using every optional field, so the round trip covers them all."""
    br = [
        Branch("trunk", None, 1.0, 0.05, fixed=True, density=650.0),
        Branch(
            "a", "trunk", 0.8, 0.03, angle_deg=20.0, azimuth_deg=45.0, attach=0.6, kp=300.0, kd=2.0
        ),
        Branch("b", "a", 0.5, 0.02, angle_deg=-12.5),
        Branch("c", "a", 0.4, 0.015, angle_deg=33.0, azimuth_deg=-90.0, attach=0.5),
    ]
    return make_tree(
        br,
        grasp_branch="b",
        grasp_fraction=0.75,
        inferred=["b", "a"],
        bounds={"b": Bounds((1.0, 100.0), (0.1, 2.0)), "a": Bounds((10.0, 900.0), (0.2, 5.0))},
        name="varied",
        base_position=(0.1, -0.2, 1.3),
        base_pitch_deg=25.0,
        base_yaw_deg=-40.0,
        gravity=(0.0, 0.0, -9.8),
        density=720.0,
        fixed_kp=1500.0,
        fixed_kd=15.0,
    )


# ---- round trips --------------------------------------------------------------------------------
@pytest.mark.parametrize("suffix", [".yaml", ".json"])
def test_round_trip(tmp_path, suffix):
    tree = _varied_tree()
    path = dump_tree(tree, tmp_path / f"tree{suffix}")
    assert load_tree(path) == tree
    # the dict form round-trips too, and the JSON file is plain JSON
    assert tree_from_dict(tree_to_dict(tree)) == tree
    if suffix == ".json":
        assert json.loads(path.read_text())["name"] == "varied"


@pytest.mark.parametrize("path", sorted(EXAMPLES.glob("*.yaml")), ids=lambda p: p.name)
def test_builtin_examples_round_trip(tmp_path, path):
    tree = load_tree(path)
    assert load_tree(dump_tree(tree, tmp_path / "t.yaml")) == tree


# ---- validation errors --------------------------------------------------------------------------
def _mutate(fn):
    d = _base_dict()
    fn(d)
    return d


CASES = {
    "unknown parent": (
        lambda d: d["branches"][2].update(parent="zz"),
        ["branches[2]", "unknown parent", "zz"],
    ),
    "duplicate name": (lambda d: d["branches"][2].update(name="b"), ["branches[2]", "duplicate"]),
    "two roots": (lambda d: d["branches"][2].update(parent=None), ["exactly one root"]),
    "child before parent": (lambda d: d["branches"].reverse(), ["listed before"]),
    "negative length": (lambda d: d["branches"][1].update(length=-0.5), ["branches[1]", "length"]),
    "NaN length": (
        lambda d: d["branches"][1].update(length=float("nan")),
        ["branches[1]", "length"],
    ),
    "string length": (lambda d: d["branches"][1].update(length="long"), ["branches[1]", "length"]),
    "zero radius": (lambda d: d["branches"][1].update(radius=0.0), ["branches[1]", "radius"]),
    "radius > length": (
        lambda d: d["branches"][1].update(radius=0.7),
        ["branches[1]", "radius", "length"],
    ),
    "infinite angle": (lambda d: d["branches"][1].update(angle_deg=float("inf")), ["angle_deg"]),
    "attach 0": (lambda d: d["branches"][1].update(attach=0.0), ["branches[1]", "attach"]),
    "grasp fraction 0": (lambda d: d["grasp"].update(fraction=0.0), ["grasp.fraction"]),
    "grasp fraction 1.5": (lambda d: d["grasp"].update(fraction=1.5), ["grasp.fraction"]),
    "unknown grasp branch": (lambda d: d["grasp"].update(branch="zz"), ["grasp.branch", "zz"]),
    "missing grasp": (lambda d: d.pop("grasp"), ["grasp"]),
    "unknown inferred joint": (
        lambda d: d["inference"].update(joints=["c", "zz"]),
        ["inference.joints", "zz"],
    ),
    "duplicate inferred joint": (
        lambda d: d["inference"].update(joints=["c", "c"]),
        ["inference.joints", "duplicate"],
    ),
    "levels 0": (lambda d: d["inference"].update(levels=0), ["inference.levels"]),
    # found by the fuzz test in CI: a non-mapping 'inference' crashed with a TypeError
    "inference not a mapping": (lambda d: d.update(inference=True), ["inference", "mapping"]),
    "kp lower >= upper": (
        lambda d: d["inference"]["prior"].update(kp=[50.0, 50.0]),
        ["inference.prior.kp", "lower"],
    ),
    "kd lower > upper": (
        lambda d: d["inference"]["prior"].update(kd=[3.0, 1.0]),
        ["inference.prior.kd", "lower"],
    ),
    "negative kp bound": (
        lambda d: d["inference"]["prior"].update(kp=[-1.0, 5.0]),
        ["inference.prior.kp"],
    ),
    "per-joint bounds": (
        lambda d: d["inference"]["prior"].update(joints={"c": {"kp": [9.0, 2.0]}}),
        ["inference.prior.joints.c.kp"],
    ),
    "bounds for a joint not inferred": (
        lambda d: d["inference"]["prior"].update(joints={"a": {"kp": [1.0, 2.0]}}),
        ["inference.prior.joints", "a"],
    ),
    "unknown top-level field": (
        lambda d: d.update(colour="green"),
        ["unknown top-level field", "colour"],
    ),
    "unknown branch field": (
        lambda d: d["branches"][0].update(lenght=1.0),
        ["branches[0]", "unknown field", "lenght"],
    ),
    "missing branch field": (lambda d: d["branches"][0].pop("radius"), ["branches[0]", "radius"]),
    "unknown base field": (lambda d: d["base"].update(roll_deg=3.0), ["base", "roll_deg"]),
    "unknown inference field": (lambda d: d["inference"].update(level=2), ["inference", "level"]),
    "unknown grasp field": (lambda d: d["grasp"].update(fration=0.5), ["grasp", "fration"]),
    "unknown prior field": (
        lambda d: d["inference"]["prior"].update(kpp=[1.0, 2.0]),
        ["inference.prior", "kpp"],
    ),
    "unknown fixed field": (lambda d: d.update(fixed={"kp": 100.0, "kdd": 1.0}), ["fixed", "kdd"]),
    "unknown per-joint prior field": (
        lambda d: d["inference"]["prior"].update(joints={"c": {"kp": [1.0, 2.0], "k": 1}}),
        ["joints.c", "'k'"],
    ),
    "per-joint prior not a mapping": (
        lambda d: d["inference"]["prior"].update(joints=["c"]),
        ["inference.prior.joints"],
    ),
    "zero gravity": (lambda d: d.update(gravity=[0.0, 0.0, 0.0]), ["gravity"]),
    "2-d base position": (lambda d: d["base"].update(position=[0.0, 1.0]), ["base.position"]),
    "fixed is not a bool": (lambda d: d["branches"][0].update(fixed="yes"), ["fixed"]),
    "inferring a fixed branch": (
        lambda d: (d["branches"][1].update(fixed=True), d["inference"].update(joints=["c", "b"])),
        ["inference.joints", "'b'", "fixed"],
    ),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_validation_errors_name_the_field(case):
    fn, words = CASES[case]
    d = _mutate(fn)
    with pytest.raises(TreeFileError) as e:
        tree_from_dict(d, source="my_tree.yaml")
    msg = str(e.value)
    assert msg.startswith("my_tree.yaml: "), msg
    for w in words:
        assert w in msg, f"{w!r} not in {msg!r}"


def test_base_dict_is_valid():
    """The unmodified dict the error cases start from loads (so each case fails for its reason)."""
    tree = tree_from_dict(copy.deepcopy(_base_dict()))
    assert tree.inferred == ("c", "b")


def test_make_tree_errors():
    welded = [Branch("a", None, 1.0, 0.03, fixed=True), Branch("b", "a", 0.5, 0.02, fixed=True)]
    with pytest.raises(TreeFileError, match="inference.joints"):
        make_tree(welded, grasp_branch="b")  # no jointed branch on the path: nothing to infer
    br = [Branch("a", None, 1.0, 0.03), Branch("b", "a", 0.5, 0.02, fixed=True)]
    assert make_tree(br, grasp_branch="b").inferred == ("a",)  # levels count jointed branches
    with pytest.raises(TreeFileError, match="inference.prior"):
        make_tree(br, grasp_branch="a", bounds={"zz": Bounds()})
    with pytest.raises(TreeFileError, match="branches"):
        make_tree([], grasp_branch="a")


def test_malformed_yaml_names_line(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("name: t\nbranches:\n  - {name: a, length: 1.0, radius: 0.1\ngrasp: {branch: a}\n")
    with pytest.raises(TreeFileError) as e:
        load_tree(p)
    assert str(p) in str(e.value) and "line 4" in str(e.value) and "YAML" in str(e.value)


def test_malformed_json_names_line(tmp_path):
    p = tmp_path / "bad.json"
    p.write_text('{\n  "name": "t",\n  "branches": [\n    {"name": "a",,}\n  ]\n}\n')
    with pytest.raises(TreeFileError) as e:
        load_tree(p)
    assert "line 4" in str(e.value) and "JSON" in str(e.value)


def test_missing_file(tmp_path):
    with pytest.raises(TreeFileError, match="no such file"):
        load_tree(tmp_path / "nope.yaml")


def test_yaml_error_with_value_names_file_and_field(tmp_path):
    p = tmp_path / "t.yaml"
    p.write_text(
        "name: t\nbranches:\n  - {name: a, length: .nan, radius: 0.1}\ngrasp: {branch: a}\n"
    )
    with pytest.raises(TreeFileError) as e:
        load_tree(p)
    assert str(p) in str(e.value) and "length" in str(e.value)


# ---- geometry -----------------------------------------------------------------------------------
def test_world_frames_planar_chain_closed_form():
    """A chain bending in one vertical plane: the tip is a sum of segments at cumulative angles."""
    lengths, angles = [0.9, 0.7, 0.5, 0.3], [5.0, 20.0, -35.0, 12.0]
    pitch, yaw, base = 15.0, 30.0, np.array([0.3, -0.1, 1.2])
    br = [
        Branch(f"b{i}", None if i == 0 else f"b{i - 1}", lengths[i], 0.01, angle_deg=angles[i])
        for i in range(4)
    ]
    tree = make_tree(br, "b3", base_position=tuple(base), base_pitch_deg=pitch, base_yaw_deg=yaw)
    frames = world_frames(tree)
    elev = np.radians(pitch + np.cumsum(angles))
    psi = math.radians(yaw)
    dirs = np.stack(
        [np.cos(elev) * math.cos(psi), np.cos(elev) * math.sin(psi), np.sin(elev)], axis=1
    )
    joints = base + np.concatenate(
        [[np.zeros(3)], np.cumsum(dirs * np.array(lengths)[:, None], axis=0)]
    )
    for i in range(4):
        p, r = frames[f"b{i}"]
        np.testing.assert_allclose(p, joints[i], atol=1e-12)
        np.testing.assert_allclose(r[:, 0], dirs[i], atol=1e-12)
        # the hinge axis stays horizontal, perpendicular to the bending plane
        np.testing.assert_allclose(r[:, 1], [-math.sin(psi), math.cos(psi), 0.0], atol=1e-12)
    p, r = frames["b3"]
    np.testing.assert_allclose(p + lengths[3] * r[:, 0], joints[4], atol=1e-12)


def test_world_frames_azimuth_and_attach():
    """Azimuth 90 turns the bending plane sideways; attach puts the fork part-way along."""
    a, az, f, L = 25.0, 90.0, 0.4, 1.5
    tree = make_tree(
        [
            Branch("p", None, L, 0.05),
            Branch("c", "p", 0.5, 0.02, angle_deg=a, azimuth_deg=az, attach=f),
        ],
        "c",
    )
    p, r = world_frames(tree)["c"]
    np.testing.assert_allclose(p, [f * L, 0.0, 0.0], atol=1e-12)
    # rot_x(90) @ rot_y(-a) @ e_x = (cos a, -sin a, 0)
    ar = math.radians(a)
    np.testing.assert_allclose(r[:, 0], [math.cos(ar), -math.sin(ar), 0.0], atol=1e-12)
    np.testing.assert_allclose(r[:, 1], [0.0, 0.0, 1.0], atol=1e-12)  # hinge axis now vertical


# ---- inferred joints ----------------------------------------------------------------------------
@pytest.mark.parametrize("levels", [1, 2, 3, 4, 5])
def test_inferred_pairs_chain(levels):
    br = [Branch(f"b{i}", None if i == 0 else f"b{i - 1}", 0.5, 0.01) for i in range(5)]
    tree = make_tree(br, "b4", levels=levels)
    assert tree.inferred == tuple(f"b{4 - k}" for k in range(levels))
    # inferred[k+1] is the parent of inferred[k]
    assert tree.inferred_pairs() == [(k + 1, k) for k in range(levels - 1)]
    assert tree.parameter_labels()[:levels] == [f"Kp[{n}]" for n in tree.inferred]
    lo, hi = tree.bounds_array()
    assert lo.shape == hi.shape == (2 * levels,) and np.all(lo < hi)


def test_inferred_pairs_branching_and_fixed():
    br = [
        Branch("root", None, 1.0, 0.05),
        Branch("weld", "root", 0.5, 0.04, fixed=True),
        Branch("x", "weld", 0.5, 0.03),
        Branch("y", "weld", 0.5, 0.03),
        Branch("z", "y", 0.3, 0.02),
        Branch("w", "z", 0.2, 0.01),
    ]
    tree = make_tree(br, "x", inferred=["x", "y", "root", "w"])
    # x and y hang (through the welded branch) from root; w's nearest jointed ancestor z is not
    # inferred, so w pairs with nobody even though y above it is.
    assert sorted(tree.inferred_pairs()) == sorted([(2, 0), (2, 1)])
    assert tree.ancestors("w") == ("w", "z", "y", "weld", "root")
    assert tree.children("weld") == ("x", "y")
    # default inference skips the welded branch on the way up
    assert make_tree(br, "x", levels=2).inferred == ("x", "root")


# ---- the data set's pull direction and the inferred gains ---------------------------------------
@pytest.mark.parametrize("suffix", [".yaml", ".json"])
@pytest.mark.parametrize("direction", ["horizontal", [1.0, 0.5, 0.0]])
def test_pull_and_parameters_round_trip(tmp_path, suffix, direction):
    d = _base_dict()
    assert tree_from_dict(d).pull_direction == "down"
    assert tree_from_dict(d).parameters == ("kp", "kd")
    assert "pull" not in tree_to_dict(tree_from_dict(d))  # defaults are not written
    d["pull"] = {"direction": direction}
    d["inference"]["parameters"] = ["kp"]
    tree = tree_from_dict(d)
    expected = direction if isinstance(direction, str) else tuple(direction)
    assert tree.pull_direction == expected
    assert tree.parameters == ("kp",)
    back = load_tree(dump_tree(tree, tmp_path / f"tree{suffix}"))
    assert back == tree
    assert back.pull_direction == expected and back.parameters == ("kp",)


@pytest.mark.parametrize(
    "pull, needle",
    [
        ({"direction": "sideways"}, "pull: field 'direction'"),
        ({"direction": [0, 0, 0]}, "pull: field 'direction'"),
        ({"dir": "down"}, "unknown field"),
        ("down", "expected a mapping"),
    ],
)
def test_bad_pull_raises_tree_file_error_naming_the_file(tmp_path, pull, needle):
    d = _base_dict()
    d["pull"] = pull
    path = tmp_path / "bad_tree.json"
    path.write_text(json.dumps(d))
    with pytest.raises(TreeFileError) as e:
        load_tree(path)
    assert str(path) in str(e.value) and needle in str(e.value)


@pytest.mark.parametrize("params", [["kd"], ["kp", "stiffness"], "", ["kp", "kp"]])
def test_bad_parameters_raise_tree_file_error(params):
    d = _base_dict()
    d["inference"]["parameters"] = params
    with pytest.raises(TreeFileError, match="inference.parameters"):
        tree_from_dict(d, source="t.yaml")


def test_make_tree_validates_pull_and_parameters():
    br = [Branch("a", None, 0.5, 0.01)]
    t = make_tree(br, "a", pull_direction=[0, 1, 0], parameters=["kp"])
    assert t.pull_direction == (0.0, 1.0, 0.0) and t.parameters == ("kp",)
    with pytest.raises(TreeFileError, match="pull.direction"):
        make_tree(br, "a", pull_direction="up")
    with pytest.raises(TreeFileError, match="inference.parameters"):
        make_tree(br, "a", parameters=["kd"])
