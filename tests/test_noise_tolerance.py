"""The simulation step of a new run tied to the displacement noise (issue 27, section 5):
:func:`treeinfer.runs.problem.noise_tolerance` picks a tenth of the noise for a generative
likelihood, within [0.1 mm, 1 mm], and the step chosen for it stays within about a tenth of
the noise of an independent integration (tests/planar_chain.py: Lagrange's equations
integrated by scipy's DOP853)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from planar_chain import PlanarTree

from treeinfer.data import forces as F
from treeinfer.data.types import Observations
from treeinfer.model.likelihood import DEFAULT_KT
from treeinfer.runs.problem import noise_tolerance
from treeinfer.sim import DEFAULT_SIM_TOLERANCE, make_simulator, simulate
from treeinfer.tree.description import Bounds
from treeinfer.tree.generators import chain

DT = 0.01


def _obs(sigma: float, seed: int = 0) -> Observations:
    """Two smooth 3 s pulls with white displacement noise of std ``sigma`` (m)."""
    t = np.arange(300) * DT
    clean = np.stack([0.05 * np.sin(1.3 * t), 0.08 * (1 - np.cos(0.9 * t))])
    x = clean + sigma * np.random.default_rng(seed).standard_normal(clean.shape)
    f = np.stack([3.0 * np.sin(1.3 * t), 4.0 * (1 - np.cos(0.9 * t))])
    return Observations(f, x, np.zeros_like(x), np.ones(x.shape, bool), DT)


def _options(**kw):
    return {"likelihood": "gaussian", "kT": DEFAULT_KT, **kw}


def test_a_tenth_of_the_estimated_noise_within_its_bounds():
    obs = _obs(2e-3)
    assert noise_tolerance(_options(), obs) == pytest.approx(2e-4, rel=0.15)
    # a given noise level wins over the estimate
    assert noise_tolerance(_options(noise_displacement=5e-3), obs) == pytest.approx(5e-4)
    # never finer than the fixed default (a clean recording), never coarser than 1 mm
    assert noise_tolerance(_options(), _obs(1e-5)) == DEFAULT_SIM_TOLERANCE
    assert noise_tolerance(_options(noise_displacement=0.05), obs) == pytest.approx(1e-3)
    # the default likelihood (None) is generative; the paper's Boltzmann loss keeps its step
    assert noise_tolerance(_options(likelihood=None), obs) == pytest.approx(2e-4, rel=0.15)
    assert noise_tolerance(_options(likelihood="boltzmann"), obs) is None


def test_the_noise_step_is_within_a_tenth_of_the_noise_of_the_reference():
    """2 mm noise: tolerance 0.2 mm. The step chosen for it on a ramp-hold-release over the
    prior box is fewer substeps than the 0.1 mm default's, and its rollouts at a stiff and a
    soft corner of the box agree with the independent integration within 1.5 x 0.2 mm = 0.15
    sigma (measured: 0.25 mm at the soft corner, a few microns at the stiff one; the
    step-doubling estimate bounds the true error within 0.5-1.25 x at the box's own corner,
    tests/test_accuracy.py)."""
    tree = chain(
        2,
        [0.8, 0.6],
        [0.025, 0.015],
        angles_deg=[10.0, 15.0],
        grasp_fraction=0.9,
        bounds=Bounds(kp=(5.0, 500.0), kd=(0.05, 10.0)),
        base_pitch_deg=5.0,
    )
    prof = F.ramp_hold(6.0, 0.5, 0.5, 0.3, 3.0, DT, start=0.2)[None]
    tol = noise_tolerance(_options(noise_displacement=2e-3), _obs(2e-3))
    fine = make_simulator(tree, obs_dt=DT, forces=prof)
    sim = make_simulator(tree, obs_dt=DT, forces=prof, sim_tolerance=tol)
    assert sim.step_info["tolerance"] == pytest.approx(2e-4)
    assert sim.substeps < fine.substeps
    kp = np.array([[400.0, 400.0], [8.0, 8.0]])
    kd = np.array([[5.0, 5.0], [0.08, 0.08]])
    tau = np.asarray(simulate(sim, kp, kd, jnp.asarray(prof)).tau[:, 0])
    for i in range(2):
        expected = PlanarTree(tree, kp[i], kd[i]).rollout(prof[0], DT)
        assert np.max(np.abs(expected)) > 1e-3
        assert np.max(np.abs(tau[i] - expected)) < 1.5 * tol, (i, sim.substeps)
