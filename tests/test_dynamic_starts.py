"""The dynamic model's starts on a quasi-static pull with channels (issue 30, the worked static
pulling example from the command line): the force's rise time, the quasi-static judgement,
the pulls rebuilt from a problem, the static fit's columns mapped onto the dynamic layout, and
(slow) the static model's MAP seeding the dynamic fit near the truth on data from the
independent planar reference."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

import treeinfer as ti
from treeinfer.data.channels import Channel, NamedPoint
from treeinfer.data.types import Observations
from treeinfer.inference.static.dynamic_starts import (
    KD_LEVELS,
    dynamic_from_static,
    force_rise_time,
    quasi_static_pull,
    recordings,
    static_first_starts,
)
from treeinfer.sim.planar_reference import PlanarTree

KP, KD = np.array([40.0, 80.0]), np.array([0.3, 0.8])  # two_branch: child, parent
DT = 0.1


def test_force_rise_time_of_ramps_padding_and_rest():
    t = np.arange(0.0, 14.0, DT)
    slow = np.interp(t, [0, 1, 11, 14], [0, 0, 2000.0, 2000.0])  # 10 s ramp: 10-90% in 8 s
    fast = np.interp(t, [0, 1, 3, 14], [0, 0, -500.0, -500.0])  # 2 s ramp (sign is no matter)
    force = np.stack([slow, fast, np.zeros_like(t)])
    mask = np.ones_like(force, bool)
    assert force_rise_time(force, mask, DT) == pytest.approx(1.6, abs=DT + 1e-9)
    assert force_rise_time(force[[0, 2]], mask[[0, 2]], DT) == pytest.approx(8.0, abs=DT + 1e-9)
    # padding (mask False) is not the pull's: a step in the padding does not count
    padded = np.concatenate([slow, np.full(50, 9000.0)])[None]
    m = np.concatenate([np.ones(t.size, bool), np.zeros(50, bool)])[None]
    assert force_rise_time(padded, m, DT) == pytest.approx(8.0, abs=DT + 1e-9)
    assert force_rise_time(np.zeros((1, 5)), np.ones((1, 5), bool), DT) == math.inf


def _fake(labels, lower, upper, **kw):
    return SimpleNamespace(labels=tuple(labels), lower=np.asarray(lower, float),
                           upper=np.asarray(upper, float), **kw)  # fmt: skip


def test_static_columns_map_onto_the_dynamic_layout():
    static = _fake(["Kp[a]", "Kp[b]", "sigma_x", "sigma[c]"], [0] * 4, [1] * 4)
    dyn = _fake(["Kp[a]", "Kp[b]", "Kd[a]", "Kd[b]", "sigma_x", "sigma[c]", "other"],
                [0, 0, 2, 2, -9, -9, 0], [20, 20, 12, 12, 0, 0, 4])  # fmt: skip
    theta = np.array([[14.0, 15.0, -6.0, -8.0], [13.0, 25.0, -7.0, -12.0]])
    out = dynamic_from_static(dyn, static, theta)
    assert out.shape == (2 * len(KD_LEVELS), 7)
    np.testing.assert_allclose(out[:5, [0, 1, 4, 5]], np.tile(theta[0], (5, 1)))
    np.testing.assert_allclose(out[:5, 2], 2 + 10 * np.asarray(KD_LEVELS))  # across the box
    np.testing.assert_allclose(out[:, 2], out[:, 3])
    np.testing.assert_allclose(out[:, 6], 2.0)  # a column the static fit lacks: its centre
    np.testing.assert_allclose(out[5:, 1], 20.0)  # clipped into the dynamic box
    np.testing.assert_allclose(out[5:, 5], -9.0)


def _channel(recording, t, sensor="s"):
    return Channel(f"{sensor}_{recording}", "angle", recording, NamedPoint("child", fraction=0.5),
                   ("y",), t, np.zeros((t.size, 1)), sensor=sensor)  # fmt: skip


def test_pulls_rebuilt_from_the_problem_or_none():
    n = np.array([30, 20])
    mask = np.arange(30)[None] < n[:, None]
    force = np.where(mask, np.arange(30.0)[None] * [[1.0], [2.0]], 0.0)
    obs = Observations(force, force / 100, np.zeros_like(force), mask, DT)
    chans = (_channel("b.csv", 5.0 + DT * np.arange(20)), _channel("a.csv", DT * np.arange(30)))
    prob = SimpleNamespace(obs=obs, spec=SimpleNamespace(channels=chans))
    trajs = recordings(prob)
    assert [tr.source for tr in trajs] == ["a.csv", "b.csv"]  # rows in file-name order
    assert trajs[1].time[0] == pytest.approx(5.0) and trajs[1].n_steps == 20
    np.testing.assert_allclose(trajs[1].force, force[1, :20])
    # channels outlasting their row: the order guessed is wrong, no pulls
    bad = (_channel("b.csv", DT * np.arange(30)), _channel("a.csv", DT * np.arange(20)))
    assert recordings(SimpleNamespace(obs=obs, spec=SimpleNamespace(channels=bad))) is None
    one = (_channel("a.csv", DT * np.arange(30)),)  # a pull without channels
    assert recordings(SimpleNamespace(obs=obs, spec=SimpleNamespace(channels=one))) is None


@pytest.fixture(scope="module")
def tree():
    return ti.load_tree(ti.example_path("two_branch"))


def _pull(tree, ramp: float, seed: int = 0, channels: bool = True):
    """A pull along gravity ramped to 4 N in ``ramp`` s, held to 10 s, from the planar
    reference, with an inclinometer on the child (white noise 1 mrad)."""
    t = np.arange(0.0, 10.0 + 1e-9, DT)
    f = np.interp(t, [0.0, 0.5, 0.5 + ramp, 10.0], [0.0, 0.0, 4.0, 4.0])
    ref = PlanarTree(tree, KP, KD)
    q = ref.rollout_q(f, DT)
    rng = np.random.default_rng(seed)
    x = np.array([(ref.grasp_point(qk) - ref.grasp_point(q[0]))[2] for qk in q])
    traj = ti.Trajectory(t, f, -x + rng.normal(0, 1e-3, t.size), None, "pull.csv")
    tilt = np.array([ref.rotation(qk, q[0], "child") for qk in q])[:, [1]]
    ch = Channel("clino_pull", "angle", "pull.csv", NamedPoint("child", fraction=0.5), ("y",), t,
                 tilt + rng.normal(0, 1e-3, tilt.shape), sensor="clino")  # fmt: skip
    return ti.make_problem(tree, [traj], likelihood="gaussian", channels=channels and (ch,),
                           sim_tolerance=5e-4)  # fmt: skip


def test_quasi_static_pull_is_told_by_the_force_not_the_sampling(tree):
    slow = _pull(tree, 8.0)
    assert "quasi-static pull" in quasi_static_pull(slow)
    assert quasi_static_pull(_pull(tree, 0.5)) is None  # the same sampling, a quick pull
    assert quasi_static_pull(_pull(tree, 8.0, channels=False)) is None


@pytest.mark.slow  # the static model's MAP and Laplace fit: about a minute on two busy cores
def test_static_fit_seeds_the_dynamic_starts_near_the_truth(tree):
    problem = _pull(tree, 8.0)
    starts = static_first_starts(problem, seed=0)
    assert starts.shape == (8 * len(KD_LEVELS), problem.dim)
    kp = np.exp(starts[0, :2])  # the static MAP's stiffness, damping at its first level
    np.testing.assert_allclose(kp, KP, rtol=0.05)
    lo, hi = problem.lower[2:4], problem.upper[2:4]
    np.testing.assert_allclose(starts[:5, 2], lo[0] + np.asarray(KD_LEVELS) * (hi[0] - lo[0]))
    # the pipeline's fit from them: the dynamic MAP keeps the stiffness
    from treeinfer.inference.laplace import problem_laplace

    lap = problem_laplace(problem, seed=0, extra=starts)
    np.testing.assert_allclose(np.exp(lap.theta[:2]), KP, rtol=0.05)


def test_the_start_pipeline_takes_the_static_starts_else_its_own(monkeypatch):
    """``auto_start``'s generic path (a model with channels): the static seed when the hook
    gives one, the grasp-point fit's channel starts (the paper's model) when it does not."""
    import treeinfer.inference.start_pipeline as sp
    import treeinfer.inference.static.dynamic_starts as ds

    seen = {}

    def importance(problem, n, seed, extra=None):
        seen["extra"] = extra
        raise RuntimeError("stop here")

    monkeypatch.setattr(sp, "model_importance", importance)
    monkeypatch.setattr(sp, "channel_starts", lambda problem, seed, log: np.full((2, 2), 7.0))
    monkeypatch.setattr(ds, "static_first_starts", lambda problem, seed, log: np.ones((3, 2)))
    prob = SimpleNamespace(settings={"channels": [{}]}, model=None)
    with pytest.raises(RuntimeError, match="stop here"):
        sp._model_start(prob, 8, 0, lambda m: None)
    np.testing.assert_array_equal(seen["extra"], np.ones((3, 2)))
    monkeypatch.setattr(ds, "static_first_starts", lambda problem, seed, log: None)
    with pytest.raises(RuntimeError, match="stop here"):
        sp._model_start(prob, 8, 0, lambda m: None)
    np.testing.assert_array_equal(seen["extra"], np.full((2, 2), 7.0))


def test_a_static_model_that_cannot_be_built_leaves_the_pipeline_its_own_starts(tree):
    """``--noise-velocity`` (the paper's model only): the static fit is refused, the starts are
    None and the log says why, the run goes on."""
    problem = _pull(tree, 8.0)
    spec = problem.spec.replace(noise_velocity=0.01)
    problem = problem.__class__(**{**problem.__dict__, "spec": spec})
    said = []
    assert static_first_starts(problem, log=said.append) is None
    assert "could not be fitted" in said[-1] and "noise-velocity" in said[-1]
