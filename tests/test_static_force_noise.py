"""Load-cell noise read through each pull's compliance (``make_problem(noise_force=...)``, the
static model): the likelihood against scipy's normal density with the compliance and the noise
composed by hand, and the force-noise estimate from a force signal."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from treeinfer.errors import ConfigError
from treeinfer.inference import make_problem
from treeinfer.static import force_noise_estimate, model_rollout
from treeinfer.trajectories import Trajectory
from treeinfer.tree import Branch, make_tree


def _tree():
    return make_tree(
        [Branch("a", None, 0.2, 0.006), Branch("b", "a", 0.2, 0.005)],
        grasp_branch="b",
        levels=2,
        parameters=("kp",),
        pull_direction="horizontal",
    )


def test_force_noise_likelihood_matches_scipy():
    tree = _tree()
    rng = np.random.default_rng(0)
    t = 0.5 * np.arange(40)
    trajs = [
        Trajectory(t, f, 1e-3 * f * k + 1e-4 * rng.standard_normal(40), source=f"{k}.csv")
        for k, f in ((1.0, 0.02 * np.arange(40)), (3.0, 0.01 * np.arange(40)))
    ]
    p = make_problem(
        tree, trajs, nn_prior=False, likelihood="gaussian", model_kind="static", noise_force=0.05
    )
    assert p.labels == ("Kp[b]", "Kp[a]", "sigma_x") and p.settings["force_noise"] == 0.05
    theta = np.array([[np.log(2.0), np.log(5.0), np.log(2e-4)], [0.5, 1.5, np.log(5e-4)]])
    got = np.asarray(p.log_likelihood(theta))
    tau = np.asarray(model_rollout(p.sim, p.model, theta[:, :2], p.obs.force).tau, float)
    f = np.asarray(p.obs.force, float)
    x = np.asarray(p.obs.displacement, float)
    for i in range(2):
        ref = 0.0
        for b in range(2):
            c = np.linalg.lstsq(f[b][:, None], tau[i, b], rcond=None)[0][0]  # m/N
            sd = np.hypot(np.exp(theta[i, 2]), 0.05 * c)
            ref += stats.norm(tau[i, b], sd).logpdf(x[b]).sum()
        assert got[i] == pytest.approx(ref, rel=2e-4)
    # one meaning of --noise-force: the same "P%" gives P% of the largest recorded force here
    q = make_problem(
        tree, trajs, nn_prior=False, likelihood="gaussian", model_kind="static", noise_force="5%"
    )
    assert q.settings["force_noise"] == pytest.approx(0.05 * np.abs(p.obs.force).max())
    # a dynamic model that is not the paper's (stiffness only) has neither force-noise term
    short = [Trajectory(0.01 * np.arange(20), tr.force[:20], tr.displacement[:20]) for tr in trajs]
    with pytest.raises(ConfigError, match="--noise-force: available for the paper's dynamic"):
        make_problem(
            tree,
            short,
            nn_prior=False,
            likelihood="gaussian",
            model_kind="dynamic",
            noise_force=0.05,
        )


def test_force_noise_estimate_of_a_noisy_ramp():
    rng = np.random.default_rng(1)
    t = 0.5 * np.arange(400)
    f = np.interp(t, [0, 50, 100, 200], [0, 2, 2, 0]) + 0.01 * rng.standard_normal(400)
    est = force_noise_estimate([Trajectory(t, f, np.zeros(400), source="x.csv")])
    assert est == pytest.approx(0.01, rel=0.15)
