"""Observation channels with every model (issue 30, section 2): the static model's channels (the
kinematics of each force sample's equilibrium) and the dynamic model's with a pull direction and
per-pull branches, both against the independent planar Lagrangian reference (scipy), and
make_problem building channel terms for them."""

import math

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import root

import treeinfer as ti
from treeinfer.data.channels import Channel, NamedPoint
from treeinfer.inference.static import model_for
from treeinfer.inference.static.channels import model_features
from treeinfer.sim import observe as ob
from treeinfer.sim.planar_reference import PlanarTree

KP, KD = np.array([40.0, 80.0]), np.array([0.3, 0.8])  # tree.inferred order: child, parent
A = math.radians(25.0)
DIRECTION = np.array([math.cos(A), 0.0, -math.sin(A)])  # a cable 25 deg below horizontal


@pytest.fixture(scope="module")
def tree():
    return ti.load_tree(ti.example_path("two_branch"))


def _static_reference(ref: PlanarTree, force: float) -> np.ndarray:
    """q of the static equilibrium under ``force`` (no speed: the acceleration vanishes)."""
    sol = root(lambda q: ref.acceleration(q, np.zeros(ref.nv), force), ref.q_rest, tol=1e-13)
    assert sol.success
    return sol.x


def test_static_channels_match_planar_equilibria(tree):
    sim = ti.make_simulator(tree, 0.1, accuracy="coarse")
    model = model_for(tree, "static", direction=DIRECTION)
    forces = np.array([[0.0, 1.0, 2.5, 4.0]])
    feats = (
        ob.feature_for(sim, "position", "child", 0.5),
        ob.feature_for(sim, "angle", "child", 0.5),
        ob.feature_for(sim, "angle", "parent", 0.5),
    )
    theta = model.layout.theta(KP, KD)[None]
    got, ok = model_features(sim, model, theta, forces, feats)
    got = np.asarray(got)[0, 0]  # [T, F, 3]
    assert bool(np.asarray(ok).all())
    ref = PlanarTree(tree, KP, KD, direction=DIRECTION)
    rest_marker = ref.point(ref.q_rest, "child", 0.5)
    for k, f in enumerate(forces[0]):
        q = _static_reference(ref, f)
        np.testing.assert_allclose(got[k, 0], ref.point(q, "child", 0.5) - rest_marker, atol=2e-5)
        np.testing.assert_allclose(got[k, 1], ref.rotation(q, ref.q_rest, "child"), atol=5e-5)
        np.testing.assert_allclose(got[k, 2], ref.rotation(q, ref.q_rest, "parent"), atol=5e-5)
    assert abs(got[-1, 1, 1]) > 0.05  # the pull turns the child by a few degrees


def test_dynamic_channels_with_direction_and_per_pull_branches(tree):
    """Pull 0 on the child at 0.9 along the cable, pull 1 on the parent at 0.7 straight down."""
    dt = 0.02
    force = ti.data.forces.from_spec("hold:peak=4,ramp=0.4,hold=0.4,release=0.3", 1.4, dt)
    forces = np.stack([force, 0.8 * force])
    dirs = np.stack([DIRECTION, [0.0, 0.0, -1.0]])
    sim = ti.make_simulator(tree, dt, forces=forces, sim_tolerance=2e-5)
    model = model_for(tree, "dynamic")._replace(direction=dirs, grasp_branch=("child", "parent"))
    feats = (
        ob.feature_for(sim, "position", "child", 1.0),
        ob.feature_for(sim, "angle", "parent", 0.5),
    )
    theta = model.layout.theta(KP, KD)[None]
    got, ok = model_features(sim, model, theta, forces, feats, np.array([0.9, 0.7]))
    got = np.asarray(got)[0]
    assert bool(np.asarray(ok).all())
    for b, (branch, frac) in enumerate([("child", 0.9), ("parent", 0.7)]):
        ref = PlanarTree(tree, KP, KD, grasp_fraction=frac, grasp_branch=branch,
                         direction=dirs[b])  # fmt: skip
        q = ref.rollout_q(forces[b], dt)
        tip = np.array([ref.point(qk, "child", 1.0) for qk in q])
        tilt = np.array([ref.rotation(qk, q[0], "parent") for qk in q])
        assert np.abs(tip - tip[0]).max() > 0.03
        np.testing.assert_allclose(got[b, :, 0], tip - tip[0], atol=2e-4)
        np.testing.assert_allclose(got[b, :, 1], tilt, atol=3e-4)


@pytest.mark.parametrize("kind", ["static", "dynamic"])
def test_make_problem_with_channels_for_a_pull_direction(tree, kind):
    """The channels' term is built for the static model and for a dynamic model pulled along
    a cable (refused before); its log-likelihood peaks near the truth."""
    dt = 0.1 if kind == "static" else 0.02
    t = np.arange(0, 1.2, dt)
    force = np.interp(t, [0, 0.6, 1.2], [0, 4, 4])
    ref = PlanarTree(tree, KP, KD, direction=DIRECTION)
    if kind == "static":
        qs = np.array([_static_reference(ref, f) for f in force])
        rest = ref.q_rest
    else:
        qs = ref.rollout_q(force, dt)
        rest = qs[0]
    tau = np.array([(ref.grasp_point(q) - ref.grasp_point(rest)) @ DIRECTION for q in qs])
    tilt = np.array([ref.rotation(q, rest, "child") for q in qs])[:, [1]]
    rng = np.random.default_rng(3)
    tr = ti.Trajectory(t, force, tau + rng.normal(0, 1e-3, t.size), None, "p0.csv")
    ch = Channel("tilt", "angle", "p0.csv", NamedPoint("child", fraction=0.5), ("y",), t,
                 tilt + rng.normal(0, 1e-3, tilt.shape))  # fmt: skip
    p = ti.make_problem(tree, [tr], model_kind=kind, direction=DIRECTION, channels=(ch,),
                        noise_force=None)  # fmt: skip
    assert p.labels[-1] == "sigma[tilt]" and p.model is not None
    assert ("Kd[child]" in p.labels) == (kind == "dynamic")  # the static model: stiffness only
    gains = np.log(KP) if kind == "static" else np.log(np.concatenate([KP, KD]))
    th = np.concatenate([gains, np.log([1e-3, 1e-3])])[None]
    off = th.copy()
    off[0, 0] += 0.3  # Kp[child] x 1.35
    ll = np.asarray(p.log_likelihood(jnp.asarray(np.concatenate([th, off]), jnp.float32)))
    assert ll[0] > ll[1] + 20


def test_kfold_scores_the_held_out_folds_channels(tree, tmp_path):
    """runs.folds.fold_channel_metrics: the held-out pull's channel (from the data folder's
    channels.yaml) in the fold's metrics, covered by a posterior at the truth and not by one
    with a stiffness 1.5x off."""
    from collections import namedtuple

    from treeinfer.data.channel_files import write_channels
    from treeinfer.runs.folds import fold_channel_metrics

    dt = 0.1
    t = np.arange(0, 1.5, dt)
    ref = PlanarTree(tree, KP, KD, direction=DIRECTION)
    rng = np.random.default_rng(5)
    trajs, chans = [], []
    for b, peak in enumerate([3.0, 4.0]):
        force = np.interp(t, [0, 1.0, 1.5], [0, peak, peak])
        qs = np.array([_static_reference(ref, f) for f in force])
        tau = np.array([(ref.grasp_point(q) - ref.c_rest) @ DIRECTION for q in qs])
        tilt = np.array([ref.rotation(q, ref.q_rest, "child") for q in qs])[:, [1]]
        trajs.append(ti.Trajectory(t, force, tau + rng.normal(0, 1e-3, t.size), None,
                                   f"p{b}.csv"))  # fmt: skip
        chans.append(
            Channel(
                f"tilt_{b}",
                "angle",
                f"p{b}.csv",
                NamedPoint("child", fraction=0.5),
                ("y",),
                t,
                tilt + rng.normal(0, 1e-3, tilt.shape),
                sensor="tilt",
            )
        )
    write_channels(tmp_path, chans)
    problem = ti.make_problem(tree, trajs[:1], model_kind="static", direction=DIRECTION,
                              channels=tuple(chans[:1]), noise_force=None)  # fmt: skip
    assert problem.labels[-1] == "sigma[tilt]"
    post = namedtuple("Post", "theta log_density")
    theta = np.concatenate([np.log(KP), np.log([1e-3, 1e-3])])
    cloud = theta + 0.01 * np.random.default_rng(0).standard_normal((32, theta.size))
    good = fold_channel_metrics(problem, post(cloud, np.zeros(32)), trajs[1:], problem.model,
                                None, tmp_path)  # fmt: skip
    assert list(good["channels"]) == ["tilt_1"]  # the held-out pull's channel only
    assert good["channels"]["tilt_1"]["band"] == "predictive"
    assert good["channel_pct_outside"] < 20.0
    off = cloud.copy()
    off[:, 0] += np.log(1.5)
    bad = fold_channel_metrics(problem, post(off, np.zeros(32)), trajs[1:], problem.model,
                               None, tmp_path)  # fmt: skip
    assert bad["channel_pct_outside"] > 40.0
    assert fold_channel_metrics(problem, post(cloud, np.zeros(32)), trajs[1:], problem.model,
                                None, None) == {}  # fmt: skip


def test_predict_run_takes_any_number_of_channel_noise_columns(tree):
    """A run with four sensors has 2R + 1 + 4 columns: the training fit and evaluate simulate
    its gain columns only (rollout.predict allows at most three noise columns)."""
    from treeinfer.evaluation.predictive import predict_run

    sim = ti.make_simulator(tree, 0.02, accuracy="coarse")
    forces = ti.data.forces.profile_set("mixed", n=1, duration=0.6, dt=0.02, seed=1)
    gains = np.log(np.concatenate([KP, KD]))
    theta = gains + 0.01 * np.random.default_rng(0).standard_normal((8, 4))
    wide = np.concatenate([theta, np.full((8, 5), np.log(1e-3))], axis=1)
    a = predict_run(sim, theta, forces)
    b = predict_run(sim, wide, forces)
    np.testing.assert_array_equal(np.asarray(a.tau), np.asarray(b.tau))
