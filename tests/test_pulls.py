"""Tests for treeinfer.data.pulls: the data folder's pulls.yaml sidecar."""

from __future__ import annotations

import math

import numpy as np
import pytest

from treeinfer.data.pulls import (
    PullSpec,
    ResolvedPull,
    check_same_pull,
    data_grasp_fractions,
    load_data_pulls,
    parse_direction,
    parse_tree_pull,
    pull_direction,
    read_pulls,
    resolve_pull,
    stack_resolved,
    write_pulls,
)
from treeinfer.errors import ConfigError
from treeinfer.tree.description import Branch, make_tree

SIDECAR = """\
default: {branch: stem, fraction: 0.5}
pulls:
  low.csv: {distance: 0.1, direction: horizontal}
  mid.csv: {fraction: 0.8, direction: [0, 3, 0]}
  tip.csv: {branch: tip, direction: down}
"""


@pytest.fixture
def tree():
    # vertical stem (pitch 90) with a horizontal tip branch along +x
    return make_tree(
        [
            Branch("stem", None, 0.4, 0.01),
            Branch("tip", "stem", 0.2, 0.005, angle_deg=-90.0),
        ],
        grasp_branch="tip",
        grasp_fraction=0.7,
        levels=2,
        base_pitch_deg=90.0,
    )


def test_read_resolve(tmp_path, tree):
    p = tmp_path / "pulls.yaml"
    p.write_text(SIDECAR)
    side = read_pulls(p, tree)
    r = load_data_pulls(tmp_path, tree, ["low.csv", "mid.csv", "tip.csv", "other.csv"])
    assert [x.branch for x in r] == ["stem", "stem", "tip", "stem"]
    assert r[0].fraction == pytest.approx(0.1 / 0.4)
    assert r[1].fraction == 0.8
    assert r[2].fraction == 0.7  # the tree's grasp fraction on its grasp branch
    assert r[3].fraction == 0.5  # from the default entry
    np.testing.assert_allclose(r[1].direction, [0, 1, 0])
    np.testing.assert_allclose(r[2].direction, [0, 0, -1])
    # vertical stem: horizontal = the hinge's bending direction; horizontal and unit length
    h = r[0].direction
    assert abs(h[2]) < 1e-12 and np.linalg.norm(h) == pytest.approx(1.0)
    assert side.pulls["low.csv"].distance == 0.1
    branches, fracs, dirs = stack_resolved(r, tree)
    assert branches == ("stem", "stem", "tip", "stem") and fracs.shape == (4,)
    assert dirs.shape == (4, 3)


def test_horizontal_is_perpendicular_to_branch(tree):
    # the tip branch points along +x (stem up, turned -90 deg): horizontal is up x axis
    from treeinfer.tree.description import world_frames

    axis = world_frames(tree)["tip"][1][:, 0]
    h = pull_direction(tree, "tip", "horizontal")
    assert abs(h @ axis) < 1e-12 and abs(h[2]) < 1e-12
    np.testing.assert_allclose(
        h, np.cross([0, 0, 1], axis) / np.linalg.norm(np.cross([0, 0, 1], axis))
    )


@pytest.mark.parametrize(
    "text, message",
    [
        ("pulls:\n  a.csv: {branch: nope}\n", "pulls.a.csv: field 'branch': unknown branch 'nope'"),
        ("pulls:\n  a.csv: {fraction: 1.5}\n", "pulls.a.csv: field 'fraction': must be in (0, 1]"),
        ("pulls:\n  a.csv: {fraction: 0}\n", "field 'fraction'"),
        ("pulls:\n  a.csv: {direction: [0, 0, 0]}\n", "field 'direction': the zero vector"),
        ("pulls:\n  a.csv: {direction: sideways}\n", "field 'direction': expected 'down'"),
        ("pulls:\n  a.csv: {direction: [1, 2]}\n", "field 'direction'"),
        ("pulls:\n  a.csv: {distance: 0.5, branch: stem}\n", "beyond the end of branch 'stem'"),
        ("pulls:\n  a.csv: {distance: 0.1, fraction: 0.5}\n", "not both"),
        ("pulls:\n  a.csv: {colour: red}\n", "unknown field(s) ['colour']"),
        ("default: {branch: x}\n", "default: field 'branch': unknown branch 'x'"),
        ("pulls: [1, 2]\n", "pulls: expected a mapping"),
        ("pulls:\n  a.csv: {fraction: [\n", "line"),
    ],
)
def test_errors_name_file_and_field(tmp_path, tree, text, message):
    p = tmp_path / "pulls.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError) as e:
        read_pulls(p, tree)
    assert str(p) in str(e.value) and message in str(e.value)


def test_write_read_round_trip(tmp_path, tree):
    specs = {
        "a.csv": PullSpec("stem", None, 0.25, "horizontal"),
        "b.csv": PullSpec("tip", 0.5, None, (1.0, 0.0, 0.0)),
    }
    p = write_pulls(tmp_path / "pulls.yaml", specs, PullSpec(direction="down"), header="made here")
    assert p.read_text().startswith("# made here\n")
    back = read_pulls(p, tree)
    assert back.pulls == specs
    assert back.default == PullSpec(direction="down")
    with pytest.raises(ConfigError, match="zero vector"):
        write_pulls(tmp_path / "x.yaml", {"c.csv": PullSpec(direction=(0, 0, 0))})


def test_tree_pull_default(tree):
    assert parse_tree_pull(None) == "down"
    assert parse_tree_pull({"direction": "horizontal"}) == "horizontal"
    assert parse_tree_pull({"direction": [1, 0, 0]}, "t.yaml") == (1.0, 0.0, 0.0)
    with pytest.raises(ConfigError, match="t.yaml: pull: unknown field"):
        parse_tree_pull({"dir": "down"}, "t.yaml")
    with pytest.raises(ConfigError, match="t.yaml: pull: field 'direction'"):
        parse_tree_pull({"direction": [0, 0, 0]}, "t.yaml")
    # the tree file's default applies when neither the entry nor the sidecar default says
    r = resolve_pull(PullSpec(), tree, default_direction=(0.0, 2.0, 0.0))
    np.testing.assert_allclose(r.direction, [0, 1, 0])
    assert r.label == "[0, 2, 0]"


def test_parse_direction_text():
    assert parse_direction("Down") == "down"
    assert parse_direction("1,0,-1") == (1.0, 0.0, -1.0)
    with pytest.raises(ConfigError):
        parse_direction([math.nan, 0, 1])


def test_check_same_pull():
    down = np.array([0.0, 0.0, -1.0])
    a = ResolvedPull("b", 1.0, down, "down")
    assert check_same_pull(a, a) is None
    msg = check_same_pull(a, ResolvedPull("b", 0.5, down, "down"), "traj_000.csv")
    assert "traj_000.csv" in msg and "fraction 0.5 instead of 1" in msg
    msg = check_same_pull(a, ResolvedPull("b", 1.0, np.array([1.0, 0, 0]), "horizontal"))
    assert "direction horizontal instead of down" in msg


def test_data_grasp_fractions(tmp_path, tree):
    assert data_grasp_fractions(tmp_path, tree, ["a.csv"]) is None
    write_pulls(tmp_path / "pulls.yaml", {"a.csv": PullSpec("tip", 0.5), "b.csv": PullSpec()})
    np.testing.assert_allclose(data_grasp_fractions(tmp_path, tree, ["a.csv", "b.csv"]), [0.5, 0.7])
    write_pulls(tmp_path / "pulls.yaml", {"a.csv": PullSpec("stem", 0.5)})
    with pytest.raises(ConfigError, match="a.csv was grasped on branch 'stem'"):
        data_grasp_fractions(tmp_path, tree, ["a.csv"])
    # pulling a vertical stem straight down bends no hinge: refused whatever the simulator
    with pytest.raises(ConfigError, match="acts along the axes of all its hinges"):
        data_grasp_fractions(tmp_path, tree, ["a.csv"], any_branch=True)
    write_pulls(tmp_path / "pulls.yaml", {"a.csv": PullSpec("stem", 0.5, direction=(1, 0, 0))})
    got = data_grasp_fractions(tmp_path, tree, ["a.csv"], any_branch=True, any_direction=True)
    assert got[0] == 0.5
    write_pulls(tmp_path / "pulls.yaml", {"a.csv": PullSpec(direction="horizontal")})
    with pytest.raises(ConfigError, match="pulled horizontal, but this model pulls only down"):
        data_grasp_fractions(tmp_path, tree, ["a.csv"])


def test_pull_leverage_flags_pushes_along_the_hinge_axes():
    from treeinfer.data.pulls import check_pull_moves, pull_leverage
    from treeinfer.examples import example_path
    from treeinfer.tree.description import load_tree, world_frames

    three = load_tree(example_path("three_branch"))  # every hinge bends in the x-z plane
    r = resolve_pull(PullSpec(direction="horizontal"), three)
    np.testing.assert_allclose(r.direction, [0, 1, 0], atol=1e-12)
    assert "acts along the axes of all its hinges" in check_pull_moves(three, r, "a.csv")
    down = resolve_pull(PullSpec(), three)
    assert check_pull_moves(three, down) is None
    # independent figure: the root hinge's lever for a downward pull at the tip is the
    # horizontal distance from the root joint to the grasp point
    o, rot = world_frames(three)["branch2"]
    tip = o + rot[:, 0] * three.branch("branch2").length
    assert pull_leverage(three, down) >= abs(tip[0] - three.base_position[0]) - 1e-12
