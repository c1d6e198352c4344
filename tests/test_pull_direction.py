"""Pulls in any direction and at several grasp branches in one simulator call."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from planar_chain import PlanarTree

from treeinfer.data import forces as F
from treeinfer.data.direction import pull_direction
from treeinfer.errors import ConfigError
from treeinfer.examples import example_path
from treeinfer.sim import make_simulator, simulate
from treeinfer.sim.reference import simulate_reference
from treeinfer.tree.description import Bounds, load_tree, tree_from_dict, tree_to_dict, world_frames
from treeinfer.tree.generators import chain

DT = 0.02


@pytest.fixture(scope="module")
def two():
    tree = load_tree(example_path("two_branch"))
    return tree, make_simulator(tree, obs_dt=DT, substeps=8)


def test_pull_direction_spellings(two):
    tree, _ = two
    np.testing.assert_allclose(pull_direction(tree, "down"), [0, 0, -1])
    h = pull_direction(tree, "horizontal")
    axis = world_frames(tree)[tree.grasp_branch][1][:, 0]
    assert abs(h @ [0, 0, 1]) < 1e-12 and abs(h @ axis) < 1e-12
    assert np.linalg.norm(h) == pytest.approx(1.0)
    np.testing.assert_allclose(pull_direction(tree, [3.0, 0.0, -4.0]), [0.6, 0.0, -0.8])
    np.testing.assert_allclose(pull_direction(tree, "0,2,0"), [0.0, 1.0, 0.0])
    # a vertical stem: 'horizontal' is the base heading, in the stem's bending plane
    stem = chain(2, 0.5, 0.01, base_pitch_deg=90.0, base_yaw_deg=30.0)
    np.testing.assert_allclose(
        pull_direction(stem, "horizontal"), [np.cos(np.pi / 6), 0.5, 0.0], atol=1e-12
    )
    for bad in ("sideways", [0, 0, 0], [1, 2], "1,x,2", [np.nan, 0, 1]):
        with pytest.raises(ConfigError, match="direction"):
            pull_direction(tree, bad)


def test_sideways_push_matches_mujoco_c(two):
    """Horizontal pushes against plain MuJoCo stepping with the same direction, in one batched
    call: a diagonal one on the two-branch example (only its in-plane part bends the hinges),
    a diagonal downward one, and 'horizontal' (across the branch) on the three-branch example's
    side branch, whose hinge axis is vertical (it forks at 90 degrees azimuth)."""
    tree, sim = two
    forces = np.stack([F.ramp_hold(4.0, 0.3, 0.3, 0.2, 1.2, DT), F.ramp(3.0, 0.5, 1.2, DT)])
    dirs = np.stack([pull_direction(tree, [1.0, 0.5, 0.0]), pull_direction(tree, [1.0, 1.0, -1.0])])
    kp, kd = np.array([15.0, 8.0]), np.array([0.3, 0.1])
    out = simulate(sim, kp[None], kd[None], jnp.asarray(forces), direction=jnp.asarray(dirs))
    assert bool(out.stable.all())
    for b in range(2):
        expected, _ = simulate_reference(sim, kp, kd, forces[b], direction=dirs[b])
        assert np.max(np.abs(expected)) > 1e-3
        np.testing.assert_allclose(np.asarray(out.tau[0, b]), expected, atol=2e-5)
    # across a branch whose hinge axis is horizontal, a horizontal push bends nothing
    across = simulate(
        sim,
        kp[None],
        kd[None],
        jnp.asarray(forces[:1]),
        direction=pull_direction(tree, "horizontal"),
    )
    assert float(jnp.max(jnp.abs(across.tau))) < 1e-6
    d3 = tree_to_dict(load_tree(example_path("three_branch")))
    d3["grasp"] = {"branch": "side", "fraction": 0.8}
    d3["inference"] = {"joints": ["side", "branch0"]}
    side = tree_from_dict(d3)
    side_sim = make_simulator(side, obs_dt=DT, substeps=8)
    d = pull_direction(side, "horizontal")
    kp3, kd3 = np.array([40.0, 300.0]), np.array([0.3, 2.0])
    out3 = simulate(side_sim, kp3[None], kd3[None], jnp.asarray(forces[:1]), direction=d)
    expected, _ = simulate_reference(side_sim, kp3, kd3, forces[0], direction=d)
    assert np.max(np.abs(expected)) > 1e-3
    np.testing.assert_allclose(np.asarray(out3.tau[0, 0]), expected, atol=2e-5)
    # one direction for every profile broadcasts; 'down' is the default
    down = simulate(
        sim, kp[None], kd[None], jnp.asarray(forces), direction=pull_direction(tree, "down")
    )
    default = simulate(sim, kp[None], kd[None], jnp.asarray(forces))
    np.testing.assert_allclose(np.asarray(down.tau), np.asarray(default.tau), atol=1e-6)


def test_horizontal_push_on_a_vertical_stem_matches_the_lagrangian_reference():
    """In-plane horizontal push on a vertical three-link stem, at the default accuracy."""
    stem = chain(
        3,
        [0.3, 0.25, 0.2],
        [0.012, 0.01, 0.008],
        base_pitch_deg=90.0,
        grasp_fraction=0.8,
        bounds=Bounds(kp=(20.0, 60.0), kd=(0.05, 0.2)),
    )
    d = pull_direction(stem, "horizontal")
    force = F.ramp_hold(2.0, 0.4, 0.4, 0.3, 2.0, 0.01)[None]
    sim = make_simulator(stem, obs_dt=0.01, forces=force, direction=d)
    kp, kd = np.array([40.0, 30.0, 25.0]), np.array([0.1, 0.08, 0.06])
    tau = np.asarray(simulate(sim, kp[None], kd[None], jnp.asarray(force), direction=d).tau[0, 0])
    expected = PlanarTree(stem, kp, kd, direction=d).rollout(force[0], 0.01)
    assert np.max(np.abs(expected)) > 0.01
    assert np.max(np.abs(tau - expected)) < 1e-4


def test_profiles_grasp_different_branches_in_one_call():
    """Pulls at two branches (and fractions) in one call equal simulators built for each."""
    tree = load_tree(example_path("three_branch"))
    sim = make_simulator(tree, obs_dt=DT, substeps=4)
    forces = np.stack(
        [F.ramp(5.0, 0.4, 1.0, DT), F.ramp(8.0, 0.3, 1.0, DT), F.ramp(4.0, 0.5, 1.0, DT)]
    )
    branches = ["branch1", tree.grasp_branch, "branch1"]
    fracs = np.array([0.5, 1.0, 0.9])
    kp, kd = np.array([[80.0, 120.0, 300.0]]), np.array([[0.4, 0.8, 2.0]])
    run = jax.jit(lambda f, g: simulate(sim, kp, kd, f, g, grasp_branch=branches))
    out = run(jnp.asarray(forces), jnp.asarray(fracs))
    for b, name in enumerate(branches):
        own = make_simulator(tree.with_grasp(float(fracs[b]), name), obs_dt=DT, substeps=4)
        expected, _ = simulate_reference(own, kp[0], kd[0], forces[b])
        assert np.max(np.abs(expected)) > 2e-3
        np.testing.assert_allclose(np.asarray(out.tau[0, b]), expected, atol=1e-4)
        ref_here, _ = simulate_reference(sim, kp[0], kd[0], forces[b], fracs[b], grasp_branch=name)
        np.testing.assert_allclose(ref_here, expected, atol=1e-9)
    with pytest.raises(ConfigError, match="unknown branch"):
        simulate(sim, kp, kd, jnp.asarray(forces), grasp_branch="nope")
    with pytest.raises(ConfigError, match="3 force profiles"):
        simulate(sim, kp, kd, jnp.asarray(forces), grasp_branch=["branch1"])
