"""The API's default simulator (issue 27, section 4): ``make_simulator(tree)`` without forces
takes the accuracy-controlled step of ``infer`` on representative pulls, and is as close to the
independent planar reference (tests/planar_chain.py) as the one ``infer`` builds on the data's
forces; ``accuracy="coarse"`` keeps the stability step for speed studies."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from planar_chain import PlanarTree

from treeinfer.data import forces as F
from treeinfer.errors import ConfigError
from treeinfer.sim import DEFAULT_SIM_TOLERANCE, accuracy, make_simulator, simulate
from treeinfer.tree.description import Bounds
from treeinfer.tree.generators import chain

DT = 0.01


def _chain(n: int, kp_box=(5.0, 500.0)):
    return chain(
        n,
        [0.8, 0.6, 0.4][-n:],
        [0.025, 0.015, 0.01][-n:],
        angles_deg=[10.0, 15.0, -10.0][:n],
        grasp_fraction=0.9,
        bounds=Bounds(kp=kp_box, kd=(0.05, 10.0)),
        base_pitch_deg=5.0,
    )


def _unseen_pulls():
    """[2, 300] N: pulls that are NOT among the representative ones (other shapes and seeds)."""
    return np.stack(
        [
            F.ramp_hold(7.0, 0.4, 0.8, 0.2, 3.0, DT, start=0.3),
            F.smooth_step(5.0, 0.2, 3.0, DT, start=0.5),
        ]
    )


def test_default_is_accuracy_controlled_and_close_to_the_reference():
    """Without forces: the representative pulls choose the step; on unseen pulls the default is
    within 0.1 mm of the reference for soft and stiff gains, the coarse step is not."""
    tree = _chain(2)
    sim = make_simulator(tree, obs_dt=DT)
    coarse = make_simulator(tree, obs_dt=DT, accuracy="coarse")
    assert sim.step_info["method"] == "accuracy" and sim.step_info["forces"] == "representative"
    assert sim.step_info["estimated_error"] <= DEFAULT_SIM_TOLERANCE
    assert coarse.step_info["method"] == "stability"
    assert coarse.substeps == sim.step_info["stability_substeps"] < sim.substeps
    prof = _unseen_pulls()
    kp = np.array([[8.0, 16.0], [300.0, 400.0]])
    kd = np.array([[0.08, 0.16], [4.0, 5.0]])
    tau = np.asarray(simulate(sim, kp, kd, jnp.asarray(prof)).tau)
    tau_c = np.asarray(simulate(coarse, kp, kd, jnp.asarray(prof)).tau)
    worst, worst_c = 0.0, 0.0
    for i in range(len(kp)):
        ref = PlanarTree(tree, kp[i], kd[i])
        for b, f in enumerate(prof):
            expected = ref.rollout(f, DT)
            worst = max(worst, np.max(np.abs(tau[i, b] - expected)))
            worst_c = max(worst_c, np.max(np.abs(tau_c[i, b] - expected)))
    assert worst < 1e-4, worst
    assert worst_c > 2 * worst  # the check has teeth: the coarse step is measurably worse


def test_default_matches_what_infer_builds():
    """The representative step is at least as fine as the one chosen on these pulls' forces
    (what `infer` builds), within one refinement."""
    tree = _chain(3)
    prof = _unseen_pulls()
    api = make_simulator(tree, obs_dt=DT)
    cli = make_simulator(tree, obs_dt=DT, forces=prof)
    assert cli.step_info["forces"] == "given"
    assert api.substeps >= 0.5 * cli.substeps, (api.substeps, cli.substeps)


def test_accuracy_option_is_checked():
    tree = _chain(1)
    with pytest.raises(ConfigError, match="accuracy"):
        make_simulator(tree, obs_dt=DT, accuracy="fast")
    with pytest.raises(ConfigError, match="coarse"):
        make_simulator(tree, obs_dt=DT, accuracy="coarse", forces=_unseen_pulls())
    given = make_simulator(tree, obs_dt=DT, substeps=3)
    assert given.substeps == 3 and given.step_info["method"] == "given"


def test_representative_pulls_scale_with_stiffness():
    """The standard 2-8 N pulls for a tree they bend well; a box 100x stiffer gets pulls scaled
    to bend it by a tenth of its reach (the compliance is ~1/Kp: the scale ~ 100x the
    softer tree's shortfall)."""
    soft = make_simulator(_chain(2), obs_dt=DT, accuracy="coarse")
    stiff_tree = _chain(2, kp_box=(5e3, 5e4))
    stiff = make_simulator(stiff_tree, obs_dt=DT, accuracy="coarse")
    s_soft, s_stiff = accuracy.typical_peak_scale(soft), accuracy.typical_peak_scale(stiff)
    assert s_soft == 1.0
    assert s_stiff > 10.0
    # the compliance estimate against the reference's static sag at the box centre (linear)
    kp = np.sqrt(5e3 * 5e4) * np.ones(2)
    ref = PlanarTree(stiff_tree, kp, [10.0, 10.0])  # well damped: settles in 4 s
    sag = ref.rollout(np.full(400, 8.0 * s_stiff), DT)[-1]
    reach = np.linalg.norm(ref.grasp_point(ref.q_rest) - ref.base)
    assert 0.05 * reach < sag < 0.2 * reach, (sag, reach)
    peaks = np.max(accuracy.representative_forces(stiff), axis=1)
    base = np.max(accuracy.representative_forces(DT), axis=1)
    np.testing.assert_allclose(peaks, s_stiff * base)


def test_default_step_choice_is_cached(tmp_path, monkeypatch):
    """A second build of the same tree (a new process, say) reads the representative step
    choice from disk: no probes, no compile."""
    monkeypatch.setenv("TREEINFER_JAX_CACHE", str(tmp_path))
    tree = _chain(1)
    first = make_simulator(tree, obs_dt=DT)

    def boom(*a, **k):
        raise AssertionError("the probes ran although the choice was cached")

    monkeypatch.setattr(accuracy, "choose_substeps_for_accuracy", boom)
    again = make_simulator(tree, obs_dt=DT)
    assert again.substeps == first.substeps and again.step_info == first.step_info
    # choose_substeps_for_accuracy on an already refined simulator starts from its stable step
    monkeypatch.undo()
    s, err = accuracy.choose_substeps_for_accuracy(first, _unseen_pulls()[:1], 1e-3)
    assert s < first.substeps and err <= 1e-3
