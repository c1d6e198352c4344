"""Tree generators: chains, fractal trees (da Vinci's rule), L-systems (rewriting and turtle)."""

from __future__ import annotations

import math
from pathlib import Path

import mujoco
import numpy as np
import pytest
import yaml

from treeinfer.errors import ConfigError, TreeFileError
from treeinfer.tree import generators as gen
from treeinfer.tree.description import Bounds, load_tree, world_frames
from treeinfer.tree.export import to_mjcf

EXAMPLES = Path(__file__).resolve().parents[1] / "treeinfer" / "examples"


def _tips(tree):
    return {n: p + r[:, 0] * tree.branch(n).length for n, (p, r) in world_frames(tree).items()}


# ---- chain and explicit -------------------------------------------------------------------------
def test_chain_geometry_and_defaults():
    t = gen.chain(3, [0.6, 0.5, 0.4], 0.02, [0.0, 20.0, -10.0], base_pitch_deg=10.0)
    assert t.names == ("branch0", "branch1", "branch2")
    assert [b.parent for b in t.branches] == [None, "branch0", "branch1"]
    assert t.grasp_branch == "branch2" and t.inferred == ("branch2", "branch1", "branch0")
    elev = np.radians(np.cumsum([10.0, 0.0, 20.0, -10.0])[1:])
    tip = np.sum(
        np.array([0.6, 0.5, 0.4])[:, None] * np.stack([np.cos(elev), 0 * elev, np.sin(elev)], 1), 0
    )
    np.testing.assert_allclose(_tips(t)["branch2"], tip, atol=1e-12)
    assert gen.chain(4, 0.5, 0.02, levels=2).inferred == ("branch3", "branch2")


def test_chain_bad_settings():
    with pytest.raises(ConfigError, match="lengths"):
        gen.chain(3, [0.5, 0.4], 0.02)
    with pytest.raises(ConfigError, match="n"):
        gen.chain(0, 0.5, 0.02)
    with pytest.raises(ConfigError, match="radius"):
        gen.chain(2, 0.5, 0.8)  # radius > length: the tree validation, reported as a bad setting
    with pytest.raises(ConfigError, match="colour"):
        gen.chain(2, 0.5, 0.02, colour="red")


def test_explicit_matches_file_semantics():
    branches = [
        {"name": "a", "length": 1.0, "radius": 0.03},
        {
            "name": "b",
            "parent": "a",
            "length": 0.5,
            "radius": 0.02,
            "attach": 0.5,
            "angle_deg": 30.0,
        },
        {"name": "c", "parent": "a", "length": 0.4, "radius": 0.02, "fixed": True},
    ]
    t = gen.explicit(
        branches,
        grasp="b",
        levels=2,
        bounds=Bounds((1.0, 50.0), (0.1, 1.0)),
        base_pitch_deg=5.0,
        fixed_kp=900.0,
    )
    assert t.inferred == ("b", "a") and t.base_pitch_deg == 5.0 and t.fixed_kp == 900.0
    assert t.bounds["a"] == Bounds((1.0, 50.0), (0.1, 1.0))
    assert t.branch("c").fixed and t.branch("b").attach == 0.5
    assert gen.explicit(branches).grasp_branch == "c"
    with pytest.raises(TreeFileError, match=r"explicit\(\).*lenght"):
        gen.explicit([{"name": "a", "lenght": 1.0, "radius": 0.1}])
    with pytest.raises(TreeFileError, match=r"unknown parent"):
        gen.explicit(
            [
                {"name": "a", "length": 1.0, "radius": 0.1},
                {"name": "b", "parent": "x", "length": 1.0, "radius": 0.1},
            ]
        )


# ---- fractal ------------------------------------------------------------------------------------
@pytest.mark.parametrize("depth,branching", [(0, 2), (2, 2), (3, 2), (2, 3), (1, 11)])
def test_fractal_counts_lengths_and_da_vinci(depth, branching):
    ratio, r0, L0 = 0.65, 0.05, 1.2
    t = gen.fractal(depth, branching, length_ratio=ratio, base_length=L0, base_radius=r0)
    assert len(t.branches) == sum(branching**k for k in range(depth + 1))
    assert len(set(t.names)) == len(t.names)
    leaves = [b for b in t.branches if not t.children(b.name)]
    assert len(leaves) == branching**depth
    for b in t.branches:
        level = len(t.ancestors(b.name)) - 1
        assert b.length == pytest.approx(L0 * ratio**level, rel=1e-12)
        kids = [t.branch(c) for c in t.children(b.name)]
        if kids:
            assert len(kids) == branching
            assert all(k.length / b.length == pytest.approx(ratio, rel=1e-12) for k in kids)
            # Leonardo da Vinci: the parent's cross-section area equals the children's total
            area = math.pi * b.radius**2
            assert sum(math.pi * k.radius**2 for k in kids) == pytest.approx(area, rel=1e-12)
    assert t.grasp_branch == gen.fractal_name((0,) * depth, branching)
    assert t.inferred == t.ancestors(t.grasp_branch)  # default: the whole path is inferred


def test_fractal_unequal_split_and_exponent():
    fr, e = (0.7, 0.3), 2.5
    t = gen.fractal(3, 2, area_fractions=fr, da_vinci_exponent=e, base_radius=0.04)
    for b in t.branches:
        kids = [t.branch(c) for c in t.children(b.name)]
        if kids:
            assert sum(k.radius**e for k in kids) == pytest.approx(b.radius**e, rel=1e-12)
            for k, f in zip(kids, fr):
                assert k.radius**e == pytest.approx(f * b.radius**e, rel=1e-12)
    with pytest.raises(ConfigError, match="area_fractions"):
        gen.fractal(2, 2, area_fractions=(0.7, 0.4))
    with pytest.raises(ConfigError, match="fork_angles_deg"):
        gen.fractal(2, 3, fork_angles_deg=(10, 20))


def test_fractal_names_angles_grasp_levels():
    t = gen.fractal(2, 2, fork_angles_deg=(25, -40), azimuths_deg=(0, 90), grasp="b10", levels=2)
    assert t.names == ("b", "b0", "b00", "b01", "b1", "b10", "b11")
    assert (
        t.branch("b01").parent == "b0"
        and t.branch("b01").angle_deg == -40
        and t.branch("b01").azimuth_deg == 90
    )
    assert t.inferred == ("b10", "b1")
    assert gen.fractal(1, 12).names[-1] == "b_11"
    with pytest.raises(ConfigError, match="grasp"):
        gen.fractal(1, 2, grasp="b7")


# ---- L-system rewriting -------------------------------------------------------------------------
ALGAE = {"A": "AB", "B": "A"}


def test_rewrite_algae_known_strings():
    # Lindenmayer's algae (Prusinkiewicz & Lindenmayer, The Algorithmic Beauty of Plants, ch. 1)
    known = ["A", "AB", "ABA", "ABAAB", "ABAABABA", "ABAABABAABAAB"]
    for n, s in enumerate(known):
        assert gen.rewrite("A", ALGAE, n) == s


def test_rewrite_algae_fibonacci_lengths():
    fib = [1, 1]
    for _ in range(20):
        fib.append(fib[-1] + fib[-2])
    for n in range(16):
        s = gen.rewrite("A", ALGAE, n)
        assert len(s) == fib[n + 1]
        assert s.count("A") == fib[n] and s.count("B") == (fib[n - 1] if n >= 1 else 0)


def test_rewrite_stochastic_reproducible_and_calibrated():
    rules = {"A": [(0.3, "x"), (0.7, "y")]}
    axiom = "A" * 4000
    s1 = gen.rewrite(axiom, rules, 1, rng=123)
    assert s1 == gen.rewrite(axiom, rules, 1, rng=np.random.default_rng(123))
    assert s1 != gen.rewrite(axiom, rules, 1, rng=124)
    frac = s1.count("x") / len(s1)
    assert abs(frac - 0.3) < 4 * math.sqrt(0.3 * 0.7 / len(s1))
    with pytest.raises(ConfigError, match="seed"):
        gen.rewrite("A", rules, 1)
    with pytest.raises(ConfigError, match="sum to 1"):
        gen.rewrite("A", {"A": [(0.3, "x"), (0.3, "y")]}, 1, rng=0)
    # stochastic trees: reproducible with a seed, different across seeds
    kw = {
        "axiom": "X",
        "rules": {"X": [(0.5, "F[+X]FX"), (0.5, "F[-X]F[&X]X")], "F": "FF"},
        "iterations": 3,
        "step_length": 0.2,
        "base_radius": 0.02,
    }
    assert gen.lsystem(**kw, seed=1) == gen.lsystem(**kw, seed=1)
    assert any(gen.lsystem(**kw, seed=s) != gen.lsystem(**kw, seed=1) for s in (2, 3, 4))


# ---- turtle interpretation ----------------------------------------------------------------------
def test_turtle_merged_side_branch():
    t = gen.lsystem(
        "F[+F]F", {}, 0, angle_deg=30.0, step_length=0.5, length_ratio=0.8, merge_segments=True
    )
    assert t.names == ("s0", "s1")
    s0, s1 = t.branches
    assert s0.length == pytest.approx(1.0) and s1.length == pytest.approx(0.4)
    assert (
        s1.parent == "s0"
        and s1.attach == pytest.approx(0.5)
        and s1.angle_deg == pytest.approx(30.0)
    )
    assert s1.azimuth_deg == 0.0


def test_turtle_separate_segments():
    t = gen.lsystem("F[+F]F", {}, 0, angle_deg=30.0, step_length=0.5, merge_segments=False)
    assert [(b.name, b.parent, b.attach) for b in t.branches] == [
        ("s0", None, 1.0),
        ("s1", "s0", 1.0),
        ("s2", "s0", 1.0),
    ]
    assert [b.angle_deg for b in t.branches] == pytest.approx([0.0, 30.0, 0.0])


def _planar_turtle(cmds, delta_deg, step):
    """Independent 2-D turtle in the bending plane: endpoints of every drawn F."""
    x = np.zeros(2)
    th, stack, pts = 0.0, [], []
    for ch in cmds:
        if ch == "F":
            x = x + step * np.array([math.cos(th), math.sin(th)])
            pts.append(x)
        elif ch in "+-":
            th += math.radians(delta_deg) * (1 if ch == "+" else -1)
        elif ch == "[":
            stack.append((x, th))
        elif ch == "]":
            x, th = stack.pop()
    return np.array(pts)


@pytest.mark.parametrize("merge", [True, False])
def test_turtle_planar_matches_independent_turtle(merge):
    cmds = gen.rewrite("X", {"X": "F[+X][-X]FX", "F": "F"}, 3)
    delta, step = 22.0, 0.1
    t = gen.lsystem(
        cmds, {}, 0, angle_deg=delta, step_length=step, merge_segments=merge, leaf_radius=0.002
    )
    tips = np.array(list(_tips(t).values()))[:, [0, 2]]  # bending plane is x-z
    ref = _planar_turtle(cmds, delta, step)
    # every branch tip is a turtle endpoint, and every turtle endpoint lies on some branch
    d = np.linalg.norm(tips[:, None, :] - ref[None, :, :], axis=2)
    assert d.min(axis=1).max() < 1e-12
    frames = world_frames(t)
    on_branch = []
    for p in ref:
        best = np.inf
        for n, (o, r) in frames.items():
            s = (np.array([p[0], 0.0, p[1]]) - o) @ r[:, 0]
            off = np.linalg.norm(np.array([p[0], 0.0, p[1]]) - o - s * r[:, 0])
            if -1e-12 <= s <= t.branch(n).length + 1e-12:
                best = min(best, off)
        on_branch.append(best)
    assert max(on_branch) < 1e-12
    if not merge:
        assert len(t.branches) == cmds.count("F")


def test_turtle_3d_commands_closed_form():
    dl, rl = 35.0, 60.0
    d, r = math.radians(dl), math.radians(rl)
    # '&' turns out of the bending plane about z: direction (cos d, sin d, 0)
    t = gen.lsystem("F&F", {}, 0, angle_deg=dl, step_length=1.0)
    np.testing.assert_allclose(
        world_frames(t)["s1"][1][:, 0], [math.cos(d), math.sin(d), 0.0], atol=1e-12
    )
    # roll then turn: rot_x(r) @ rot_y(-d) @ e_x, stored as azimuth r and angle d
    t = gen.lsystem("F[/+F]", {"/": "/"}, 0, angle_deg=dl, step_length=1.0)
    s1 = t.branch("s1")
    assert (s1.azimuth_deg, s1.angle_deg) == pytest.approx((dl, dl))
    t = gen.lsystem("F//+++F", {}, 0, angle_deg=rl / 2, step_length=1.0)  # roll 60, turn 90
    np.testing.assert_allclose(
        world_frames(t)["s1"][1][:, 0], [0.0, -math.sin(r), math.cos(r)], atol=1e-12
    )
    # '-' is a negative angle (not azimuth 180), a pure roll merges into the same branch
    t = gen.lsystem("F-F", {}, 0, angle_deg=dl, step_length=1.0)
    assert (t.branch("s1").azimuth_deg, t.branch("s1").angle_deg) == pytest.approx((0.0, -dl))
    assert len(gen.lsystem("F/F", {}, 0, angle_deg=dl, step_length=1.0).branches) == 1
    # a turn after a roll inside the branch: the tip direction is still the turtle's
    t = gen.lsystem("F[+/+F]", {}, 0, angle_deg=dl, step_length=1.0)
    h = (
        np.array(
            [[math.cos(d), 0, -math.sin(d)], [0, 1, 0], [math.sin(d), 0, math.cos(d)]]
        )  # rot_y(-d)
        @ np.array(
            [[1, 0, 0], [0, math.cos(d), -math.sin(d)], [0, math.sin(d), math.cos(d)]]
        )  # rot_x(d)
        @ np.array([math.cos(d), 0, math.sin(d)])
    )  # rot_y(-d) @ e_x
    np.testing.assert_allclose(world_frames(t)["s1"][1][:, 0], h, atol=1e-12)


def test_turtle_errors():
    with pytest.raises(ConfigError, match=r"'\]'"):
        gen.lsystem("F]F", {}, 0)
    with pytest.raises(ConfigError, match=r"'\['"):
        gen.lsystem("F[F", {}, 0)
    with pytest.raises(ConfigError, match="draws nothing"):
        gen.lsystem("+-X", {}, 0)
    with pytest.raises(ConfigError, match="second root"):
        gen.lsystem("[F]F", {}, 0)


def test_lsystem_pipe_radii():
    cmds = "F[+F][-F[+F]F]F"
    for merge in (True, False):
        t = gen.lsystem(
            cmds, {}, 0, angle_deg=30.0, step_length=0.5, merge_segments=merge, base_radius=0.05
        )
        assert t.branches[0].radius == pytest.approx(0.05, rel=1e-12)
        n_tips = 0
        for b in t.branches:
            kids = [t.branch(c) for c in t.children(b.name)]
            free_tip = not any(k.attach == 1.0 for k in kids)
            n_tips += free_tip
            leaf = sum(k.radius**2 for k in kids) + (
                t.branches[0].radius ** 2 / 4 if free_tip else 0.0
            )
            assert b.radius**2 == pytest.approx(leaf, rel=1e-12)
        assert n_tips == 4  # four drawn tips: the pipe count at the root
    t = gen.lsystem(cmds, {}, 0, angle_deg=30.0, step_length=0.5, leaf_radius=0.01)
    assert t.branches[0].radius == pytest.approx(0.01 * 2.0, rel=1e-12)  # sqrt(4 tips) * leaf
    with pytest.raises(ConfigError, match="hint"):
        gen.lsystem("FFFF", {}, 0, step_length=0.01, merge_segments=False, base_radius=0.05)


def test_lsystem_default_grasp_is_farthest_leaf():
    t = gen.lsystem("F[+FF]F", {}, 0, angle_deg=20.0, step_length=0.5)
    tips = _tips(t)
    leaves = [n for n in t.names if not t.children(n)]
    assert t.grasp_branch == max(leaves, key=lambda n: np.linalg.norm(tips[n]))


# ---- all generated trees load in MuJoCo ---------------------------------------------------------
GENERATED = {
    "chain": lambda: gen.chain(4, 0.4, 0.015, [0, 10, -10, 20], [0, 30, 0, 0]),
    "fractal": lambda: gen.fractal(3, 2, azimuths_deg=(0, 90), base_pitch_deg=60.0),
    "fractal3": lambda: gen.fractal(2, 3, area_fractions=(0.5, 0.3, 0.2)),
    "lsystem": lambda: gen.lsystem(
        "X", {"X": "F[+X][-X]F[&X]X", "F": "FF"}, 3, step_length=0.05, base_radius=0.03
    ),
    "lsystem-stochastic": lambda: gen.lsystem(
        "X",
        {"X": [(0.4, "F[/+X]F[\\-X]X"), (0.6, "F[&X]F[^X]X")], "F": "FF"},
        3,
        step_length=0.08,
        base_radius=0.03,
        merge_segments=False,
        seed=7,
    ),
    "explicit": lambda: gen.explicit(
        [
            {"name": "a", "length": 1.0, "radius": 0.03},
            {
                "name": "b",
                "parent": "a",
                "length": 0.5,
                "radius": 0.02,
                "attach": 0.4,
                "fixed": True,
            },
            {"name": "c", "parent": "b", "length": 0.3, "radius": 0.01, "angle_deg": 40.0},
        ]
    ),
}


@pytest.mark.parametrize("kind", sorted(GENERATED))
def test_generated_trees_load_in_mujoco(kind):
    tree = GENERATED[kind]()
    m = mujoco.MjModel.from_xml_string(to_mjcf(tree))
    assert m.nbody == len(tree.branches) + 1
    assert m.njnt == sum(not b.fixed for b in tree.branches)
    np.testing.assert_allclose(
        m.body_mass[1:].sum(),
        sum(tree.density * math.pi * b.radius**2 * b.length for b in tree.branches),
        rtol=1e-8,
    )


# ---- recorded settings --------------------------------------------------------------------------
def test_describe_generate_round_trip(tmp_path):
    cfg = gen.describe(
        "lsystem",
        axiom="X",
        rules={"X": [(0.5, "F[+X]X"), (0.5, "F[-X]X")]},
        iterations=3,
        step_length=0.1,
        base_radius=0.02,
        seed=5,
        base_position=(0, 0, 1),
        bounds=Bounds((1.0, 9.0)),
    )
    assert (
        cfg["kind"] == "lsystem" and cfg["angle_deg"] == 25.0 and cfg["base_position"] == [0, 0, 1]
    )
    tree = gen.generate(cfg)
    assert tree == gen.lsystem(
        "X",
        {"X": [(0.5, "F[+X]X"), (0.5, "F[-X]X")]},
        3,
        step_length=0.1,
        base_radius=0.02,
        seed=5,
        base_position=(0, 0, 1),
        bounds=Bounds((1.0, 9.0)),
    )
    # plain data: survives YAML, then rebuilds the same tree
    assert gen.generate(yaml.safe_load(yaml.safe_dump(cfg))) == tree
    path = tmp_path / "g.yaml"
    assert gen.dump_generated(cfg, path) == tree
    assert load_tree(path) == tree
    assert yaml.safe_load(path.read_text())["generator"] == cfg
    with pytest.raises(ConfigError, match="unknown kind"):
        gen.describe("bonsai")
    with pytest.raises(ConfigError, match="depht"):
        gen.generate({"kind": "fractal", "depht": 2})


def test_builtin_fractal_example_is_generated():
    path = EXAMPLES / "fractal.yaml"
    raw = yaml.safe_load(path.read_text())
    assert raw["generator"]["kind"] == "fractal"
    assert raw["generator"]["depth"] == 2 and raw["generator"]["branching"] == 2
    assert load_tree(path) == gen.generate(raw["generator"])
