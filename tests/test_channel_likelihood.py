"""The channels' generative likelihood (issue 30): each channel's Gaussian term against a
hand computation (numpy interpolation, scipy's normal density), and make_problem's use of it."""

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import norm

import treeinfer as ti
from treeinfer.data.channels import Channel, NamedPoint
from treeinfer.errors import ConfigError
from treeinfer.model.channels import channel_layout, channel_log_likelihood
from treeinfer.sim import observe as ob

DT = 0.02
KP, KD = np.array([40.0, 80.0]), np.array([0.3, 0.8])


@pytest.fixture(scope="module")
def case():
    tree = ti.load_tree(ti.example_path("two_branch"))
    sim = ti.make_simulator(tree, DT, accuracy="coarse")
    forces = ti.data.forces.profile_set("mixed", n=2, duration=1.2, dt=DT, seed=1)
    feats = (
        ob.feature_for(sim, "position", "child", 0.5),
        ob.feature_for(sim, "angle", "parent", 1.0),
    )
    ro = ob.simulate_features(sim, KP[None], KD[None], forces, feats)
    rng = np.random.default_rng(0)
    t = np.arange(forces.shape[1]) * DT
    trajs = [
        ti.Trajectory(
            t, forces[b], np.asarray(ro.tau[0, b]) + rng.normal(0, 1e-3, t.size), None, f"p{b}.csv"
        )
        for b in range(2)
    ]
    tc = np.arange(0.013, 1.15, 1 / 33.0)  # 33 Hz, off the pulls' grid
    feat = np.asarray(ro.features[0])  # [B, T, F, 3]
    marker = np.stack([np.interp(tc, t, feat[1, :, 0, a]) for a in (0, 2)], -1)
    tilt = np.interp(tc, t, feat[0, :, 1, 1])[:, None]
    chans = (
        Channel("m", "position", "p1.csv", NamedPoint("child", fraction=0.5), ("x", "z"), tc,
                marker + rng.normal(0, 1e-3, marker.shape)),
        Channel("tilt", "angle", "p0.csv", NamedPoint("parent", distance=0.8), ("y",), tc,
                tilt + rng.normal(0, 2e-3, tilt.shape), noise=2e-3),
    )  # fmt: skip
    return tree, sim, forces, trajs, chans, feat, t


def test_log_likelihood_matches_hand_computation(case):
    tree, sim, forces, trajs, chans, _, t = case
    layout = channel_layout(sim, chans, ["p0.csv", "p1.csv"], [0.0, 0.0], forces.shape[1])
    assert layout.labels == ("sigma[m]",) and len(layout.features) == 2
    ll = channel_log_likelihood(sim, layout, forces)
    kp, kd, sig_m = np.array([50.0, 70.0]), np.array([0.4, 0.6]), 1.5e-3
    theta = np.array([[*np.log(kp), *np.log(kd), np.log(sig_m)]])
    got = float(ll(jnp.asarray(theta, jnp.float32))[0])
    # by hand: the simulated features at these gains, numpy's interpolation, scipy's density
    feats = (
        ob.feature_for(sim, "position", "child", 0.5),
        ob.feature_for(sim, "angle", "parent", 1.0),
    )
    f = np.asarray(ob.simulate_features(sim, kp[None], kd[None], forces, feats).features[0])
    m, tl = chans
    want = (
        sum(
            norm.logpdf(m.values[:, j], np.interp(m.time, t, f[1, :, 0, a]), sig_m).sum()
            for j, a in enumerate((0, 2))
        )
        + norm.logpdf(tl.values[:, 0], np.interp(tl.time, t, f[0, :, 1, 1]), 2e-3).sum()
    )
    assert got == pytest.approx(want, rel=2e-5, abs=0.05)


def test_make_problem_adds_channel_terms(case):
    tree, sim, forces, trajs, chans, _, _ = case
    p0 = ti.make_problem(tree, trajs, sim=sim, noise_force=None)
    p1 = ti.make_problem(tree, trajs, sim=sim, noise_force=None, channels=chans)
    assert p1.labels == p0.labels + ("sigma[m]",)
    assert p1.settings["channel_noise_columns"] == 1
    assert [c["name"] for c in p1.settings["channels"]] == ["m", "tilt"]
    th = np.array([*np.log(KP), *np.log(KD), np.log(1e-3)])
    theta = jnp.asarray(np.array([[*th, np.log(1e-3)]]), jnp.float32)
    layout = channel_layout(sim, chans, ["p0.csv", "p1.csv"], [0.0, 0.0], forces.shape[1])
    ch = float(channel_log_likelihood(sim, layout, forces)(theta)[0])
    base = float(p0.log_likelihood(theta[:, :-1])[0])
    assert float(p1.log_likelihood(theta)[0]) == pytest.approx(base + ch, rel=1e-5)
    far = theta.at[0, 2].add(0.7)  # Kd[child] x2
    assert float(p1.log_density(far)[0]) < float(p1.log_density(theta)[0]) - 5
    v, g = p1.value_and_grad(theta)
    assert np.all(np.isfinite(np.asarray(g))) and g.shape == theta.shape


def test_channels_need_a_generative_likelihood(case):
    tree, sim, _, trajs, chans, _, _ = case
    with pytest.raises(ConfigError, match="generative likelihood"):
        ti.make_problem(tree, trajs, sim=sim, likelihood="boltzmann", channels=chans)
    bad = chans[0]._replace(recording="p7.csv")
    with pytest.raises(ConfigError, match="'p7.csv', which is not in the data"):
        ti.make_problem(tree, trajs, sim=sim, noise_force=None, channels=(bad,))


def test_channels_of_one_sensor_share_a_noise_column(case):
    tree, sim, forces, trajs, chans, _, t = case
    m = chans[0]
    a = m._replace(name="m_a", sensor="cam")
    b = m._replace(name="m_b", sensor="cam", recording="p0.csv")
    layout = channel_layout(sim, (a, b), ["p0.csv", "p1.csv"], [0.0, 0.0], forces.shape[1])
    assert layout.labels == ("sigma[cam]",) and list(layout.column) == [0, 0]
    ll = channel_log_likelihood(sim, layout, forces)
    theta = np.array([[*np.log(KP), *np.log(KD), np.log(2e-3)]])
    got = float(ll(jnp.asarray(theta, jnp.float32))[0])
    each = [
        channel_log_likelihood(
            sim, channel_layout(sim, (c._replace(noise=2e-3),), ["p0.csv", "p1.csv"], [0.0, 0.0],
                                forces.shape[1]), forces)(jnp.asarray(theta[:, :4], jnp.float32))
        for c in (a, b)
    ]  # fmt: skip
    assert got == pytest.approx(float(each[0][0] + each[1][0]), rel=1e-5)


def test_channel_tolerance_is_a_tenth_of_each_channels_noise(case):
    from treeinfer.model.channels import TOLERANCE_FLOOR, channel_tolerance

    tree, _, _, _, chans, _, _ = case
    m, tilt = chans  # marker: noise estimated from its 1 mm noise; tilt: given 2 mrad
    assert channel_tolerance((tilt,), tree) == pytest.approx(0.1 * 2e-3 * 0.8)  # parent: 0.8 m
    # 1 mm noise; at 33 Hz the estimate also counts some of the marker's curvature
    assert 0.7e-4 < channel_tolerance((m,), tree) < 3e-4
    assert channel_tolerance((tilt._replace(noise=1e-6),), tree) == TOLERANCE_FLOOR
