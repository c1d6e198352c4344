"""A tree converted from a QSM simulates as a hand-written tree of the same joints does.

The converter once welded the rest of the tree on as extra jointless bodies and turned hinges
with welded connectors: the sapling's 8-joint chain had 18 bodies and the fused simulator's
first compile took many CPU-minutes (docs/qsm.md). These checks are structural, not timed: one
body per joint, and the fused step's traced program no larger than that of the same links
written by hand (without the lumped masses) by more than a small factor."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from qsm_fixtures import BASE, sapling, write_simpleforest
from test_qsm_shared import FILES, GRASP, QSM_DIR

from treeinfer.sim import fused as hd
from treeinfer.sim import make_simulator, simulate
from treeinfer.sim.reference import simulate_reference
from treeinfer.tree import make_tree, tree_from_qsm
from treeinfer.tree.export import to_mjmodel
from treeinfer.tree.types import rot_x

# The fused step's program (StableHLO lines of one step) for a converted tree, over that of
# the same links without lumps or twists: 1.00 on the fixture and 1.14 on the TreeQSM sapling
# (a full inertia per lumped link); the converter with welded bodies gave 1.24 and 2.12.
MAX_PROGRAM_RATIO = 1.2


def _step_lines(tree) -> int:
    """StableHLO lines of one fused step of ``tree`` (traced and lowered, not compiled)."""
    m = to_mjmodel(tree)
    t = hd.from_mjmodel(m)
    nv = t.nv

    def step(q, v, kp):
        out = hd.step(
            t, q, v, list(kp), [0.1] * nv, [0.0] * nv, 1e-3, m.nbody - 1,
            (0.1, 0.0, 0.0), (0.0, 0.0, -1.0), (0.01, 0.0, 0.0),
        )  # fmt: skip
        return jnp.stack([jnp.asarray(x) for x in out.qvel])

    z = jnp.zeros(nv)
    return jax.jit(step).lower(z, z, z).as_text().count("\n")


def _by_hand(tree):
    """The same links (frames, twists included) as a hand-written tree: no lumps."""
    branches = [dataclasses.replace(b, lump=None) for b in tree.branches]
    return make_tree(
        branches,
        grasp_branch=tree.grasp_branch,
        grasp_fraction=tree.grasp_fraction,
        inferred=list(tree.inferred),
        base_pitch_deg=tree.base_pitch_deg,
        base_yaw_deg=tree.base_yaw_deg,
    )


def _check_model_size(tree) -> None:
    m = to_mjmodel(tree)
    assert m.nbody == m.njnt + 1  # one body per joint, plus the world
    assert not any(b.fixed for b in tree.branches)
    assert any(b.lump is not None for b in tree.branches)  # the rest of the tree is there
    assert _step_lines(tree) <= MAX_PROGRAM_RATIO * _step_lines(_by_hand(tree))


def _leaning_fixture(tmp_path):
    """The fixture sapling leaning 20 degrees sideways: twisted hinges and 3-D lumps."""
    t = sapling()
    rot = rot_x(math.radians(20.0))
    for key in ("start", "end"):
        t[key] = BASE + (t[key] - BASE) @ rot.T
    path = write_simpleforest(tmp_path / "leaning.csv", t)
    grasp = BASE + rot @ np.array([0.7, 0.0, 1.0])
    return tree_from_qsm(path, grasp_point=tuple(grasp), joint_spacing=0.5).tree


def test_a_converted_fixture_is_one_body_per_joint_and_rolls_out_as_mujoco(tmp_path):
    tree = _leaning_fixture(tmp_path)
    assert any(b.twist_deg != 0.0 for b in tree.branches)
    _check_model_size(tree)
    sim = make_simulator(tree, accuracy="coarse")
    assert sim.backend == "fused" and sim.mj_model.nbody == len(tree.branches) + 1
    lo, hi = tree.bounds_array()
    r = tree.n_inferred
    kp, kd = np.sqrt(lo[:r] * hi[:r]), np.sqrt(lo[r:] * hi[r:])
    force = np.concatenate([np.linspace(0.0, 20.0, 15), np.full(10, 20.0)])
    out = simulate(sim, jnp.asarray(kp)[None], jnp.asarray(kd)[None], jnp.asarray(force)[None])
    assert bool(out.stable.all())
    tau = np.asarray(out.tau[0, 0], float)
    ref, _ = simulate_reference(sim, kp, kd, force)  # plain MuJoCo C, float64
    assert ref[-1] > 1e-4  # the pull moves the grasp point
    np.testing.assert_allclose(tau, ref, atol=2e-3 * np.abs(ref).max())


@pytest.mark.skipif(
    QSM_DIR is None,
    reason="the shared QSMs (../shared/data/qsm, or $TREEINFER_SHARED_DATA/qsm) are absent",
)
@pytest.mark.parametrize("name", sorted(FILES.values()))
def test_a_shared_sapling_chain_builds_a_simulator_of_one_body_per_joint(name):
    res = tree_from_qsm(QSM_DIR / name, grasp_point=GRASP, joint_spacing=0.5)
    tree = res.tree
    assert len(tree.branches) == res.report["links"] == 8
    _check_model_size(tree)
    sim = make_simulator(tree, accuracy="coarse")
    assert sim.backend == "fused" and sim.mj_model.nbody == 9
    # a short rollout in plain MuJoCo (the fused program's compile is left to the benchmarks)
    lo, hi = tree.bounds_array()
    r = tree.n_inferred
    tau, _ = simulate_reference(
        sim, np.sqrt(lo[:r] * hi[:r]), np.sqrt(lo[r:] * hi[r:]), np.full(20, 5.0)
    )
    assert np.all(np.isfinite(tau)) and 0 < tau[-1] < 0.05
