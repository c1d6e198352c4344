"""Tests for treeinfer.tree.stem: the tapered-beam stand-in and the cantilever baseline."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_bvp

from treeinfer.data.import_csv import import_csv
from treeinfer.data.trajectories import read_trajectory
from treeinfer.errors import ConfigError
from treeinfer.tree.stem import (
    Stem,
    cantilever_displacement,
    compliance,
    fit_cantilever,
    push_recording,
    stem_tree,
    write_stem_logs,
)


def test_uniform_stem_is_the_textbook_cantilever():
    stem = Stem(base_diameter=0.008, tip_diameter=0.008)
    ei = float(stem.ei(0.0))
    for h in (0.1, 0.25, 0.4):
        assert compliance(stem, h) == pytest.approx(h**3 / (3 * ei), rel=1e-10)


def test_tapered_compliance_matches_solve_bvp():
    """Independent reference: w'' = F (h - z) / EI(z), w(0) = w'(0) = 0, on [0, h]."""
    stem = Stem()
    h, force = 0.3, 1.0

    def rhs(z, y):
        return np.vstack([y[1], force * (h - z) / stem.ei(z)])

    def bc(ya, yb):
        return np.array([ya[0], ya[1]])

    z = np.linspace(0, h, 200)
    sol = solve_bvp(rhs, bc, z, np.zeros((2, z.size)), tol=1e-10)
    assert sol.success
    assert compliance(stem, h) == pytest.approx(float(sol.sol(h)[0]), rel=1e-6)
    # a taper makes the stem softer than a uniform one of its base diameter
    assert compliance(stem, h) > h**3 / (3 * float(stem.ei(0.0)))


def test_push_and_logs_through_import_csv(tmp_path):
    stem = Stem()
    logs = write_stem_logs(tmp_path / "raw", stem, heights=(0.2,), seed=3)
    ((path, push),) = logs
    text = path.read_text().splitlines()
    assert text[0] == "millis,load_g,pos_mm"
    ms = np.array([int(line.split(",")[0]) for line in text[1:]])
    assert np.any(np.diff(ms) < 0)  # the counter wraps during the push
    res = import_csv(
        [path],
        tmp_path / "data",
        time="millis",
        force="load_g",
        displacement="pos_mm",
        units="time=ms,force=gf,displacement=mm",
        dt=0.5,
        tare=True,
        zero_displacement="contact",
        trim=True,
        grasp_branch="link1",
        grasp_distance=0.2 - stem.height / 3,
        direction="horizontal",
    )
    steps = res.steps[path.stem + ".csv"]
    assert any("wraps around" in s for s in steps) and any(s.startswith("tare") for s in steps)
    traj = read_trajectory(res.paths[0])
    # imported force/displacement follow the true beam law within the logger noise
    c = compliance(stem, 0.2)
    loaded = traj.force > 0.2 * traj.force.max()
    ratio = traj.displacement[loaded] / traj.force[loaded]
    assert np.median(ratio) == pytest.approx(c, rel=0.05)
    assert push.force.max() == pytest.approx(0.010 / c)


def test_cantilever_fit_recovers_ei():
    stem = Stem(base_diameter=0.008, tip_diameter=0.008)
    pushes = [push_recording(stem, h) for h in (0.1, 0.3)]
    ei = fit_cantilever([p.force for p in pushes], [p.displacement for p in pushes], [0.1, 0.3])
    assert ei == pytest.approx(float(stem.ei(0)), rel=1e-9)
    x = cantilever_displacement(pushes[0].force, 0.1, ei)
    np.testing.assert_allclose(x, pushes[0].displacement, atol=1e-12)


def test_stem_tree():
    tree = stem_tree(Stem(), n_links=3)
    assert tree.inferred == ("link2", "link1", "link0")
    assert tree.base_pitch_deg == 90.0
    assert sum(b.length for b in tree.branches) == pytest.approx(0.4)


def test_stem_tree_midpoint_hinges_and_branch_at_height():
    from treeinfer.tree.stem import branch_at_height

    stem = Stem()
    tree = stem_tree(stem, n_links=3, hinges="midpoints")
    seg = stem.height / 3
    assert tree.inferred == ("link2", "link1", "link0") and tree.branch("stub").fixed
    assert [b.length for b in tree.branches] == pytest.approx([seg / 2, seg, seg, seg / 2])
    assert branch_at_height(tree, 0.12) == ("link0", pytest.approx(0.12 - seg / 2))
    assert branch_at_height(tree, 0.36) == ("link2", pytest.approx(0.36 - 2.5 * seg))
    assert branch_at_height(stem_tree(stem), 0.24) == ("link1", pytest.approx(0.24 - seg))


def test_matched_hinges_uniform_stem_closed_form():
    """Uniform stem, pushes at a, 2a, 3a: pivots at 0.15a, 1.15a, 2.15a and, with
    c(h) = h^3 / 3EI, the triangular system for 1/K solved by hand, one row at a time."""
    from treeinfer.tree.stem import matched_hinges

    stem = Stem(base_diameter=0.008, tip_diameter=0.008)
    a, ei = 0.1, float(stem.ei(0.0))
    z, shape = matched_hinges(stem, (a, 2 * a, 3 * a))
    np.testing.assert_allclose(z, [0.15 * a, 1.15 * a, 2.15 * a], rtol=1e-12)
    c = np.array([1.0, 8.0, 27.0]) * a**3 / (3 * ei)
    f1 = c[0] / (0.85 * a) ** 2
    f2 = (c[1] - (1.85 * a) ** 2 * f1) / (0.85 * a) ** 2
    f3 = (c[2] - (2.85 * a) ** 2 * f1 - (1.85 * a) ** 2 * f2) / (0.85 * a) ** 2
    k = 1.0 / np.array([f1, f2, f3])
    np.testing.assert_allclose(shape, k / k.max(), rtol=1e-9)
    with pytest.raises(ConfigError, match="heights"):
        matched_hinges(stem, (0.2, 0.1))


def test_matched_chain_reproduces_the_tapered_beam_in_the_static_model():
    """The matched 3-hinge tree (``stem_tree(hinges="matched")``) in treeinfer's static model,
    its stiffness scale set from the beam's compliance at the lowest push alone, gives the
    tapered beam's compliance (scipy quadrature) at the two other push heights (small push;
    the stem's own weight softens it by ~1%)."""
    import jax.numpy as jnp

    from treeinfer.data.pulls import pull_direction
    from treeinfer.inference.static import static_rollout
    from treeinfer.sim import make_simulator
    from treeinfer.tree.stem import branch_at_height, matched_hinges

    stem, heights = Stem(), (0.12, 0.24, 0.36)
    tree = stem_tree(stem, hinges="matched", push_heights=heights)
    z, shape = matched_hinges(stem, heights)
    assert len(tree.inferred) == 3
    scale = (heights[0] - z[0]) ** 2 / shape[0] / compliance(stem, heights[0])
    kp = {f"link{k}": scale * shape[k] for k in range(3)}
    # equilibria take no time step: the stability step spares the default step's accuracy
    # probes (seconds of 2,000-substep rollouts)
    sim = make_simulator(tree, obs_dt=0.5, backend="fused", accuracy="coarse")
    # the three heights as three profiles of one call (each its own branch, point and direction)
    branches, fracs, dirs = [], [], []
    for h in heights:
        branch, dist = branch_at_height(tree, h)
        branches.append(branch)
        fracs.append(dist / tree.branch(branch).length)
        dirs.append(pull_direction(tree, branch, "horizontal"))
    assert len(set(branches)) == 3  # one push per link
    r = static_rollout(
        sim,
        jnp.asarray([[kp[n] for n in tree.inferred]]),
        np.tile([0.0, 0.005, 0.01], (3, 1)),
        np.asarray(fracs),
        np.asarray(dirs),
        tuple(branches),
        tree,
    )
    for b, h in enumerate(heights):
        got = float(r.tau[0, b, 2]) / 0.01
        assert abs(got) == pytest.approx(compliance(stem, h), rel=0.03)
