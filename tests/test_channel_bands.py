"""Bands and metrics of observation channels (issue 30): a posterior concentrated at the truth
with the true noise covers ~95% of a fresh noisy channel; noise scales are found by name, then
by sensor point."""

import numpy as np
import pytest

import treeinfer as ti
from treeinfer.data.channels import Channel, NamedPoint
from treeinfer.evaluation.channel_bands import band_csv, channel_bands, plot_channel_bands
from treeinfer.sim import observe as ob

DT = 0.02
KP, KD = np.array([40.0, 80.0]), np.array([0.3, 0.8])


@pytest.fixture(scope="module")
def case():
    tree = ti.load_tree(ti.example_path("two_branch"))
    sim = ti.make_simulator(tree, DT, accuracy="coarse")
    forces = ti.data.forces.profile_set("mixed", n=2, duration=2.0, dt=DT, seed=3)
    t = np.arange(forces.shape[1]) * DT
    trajs = [ti.Trajectory(t, forces[b], 0 * t, None, f"p{b}.csv") for b in range(2)]
    specs = [ob.ChannelSpec("position", "child", 0.5, "xz", 1e-3)]
    chans = ob.synthetic_channels(sim, KP, KD, forces, ["p0.csv", "p1.csv"], specs,
                                  np.random.default_rng(0))  # fmt: skip
    return sim, trajs, chans


def test_truth_with_true_noise_covers_about_95_percent(case):
    sim, trajs, chans = case
    rng = np.random.default_rng(1)
    theta = np.column_stack(
        [np.log(KP) + 1e-3 * rng.normal(size=(16, 2)), np.log(KD) + 1e-3 * rng.normal(size=(16, 2)),
         np.full((16, 1), np.log(1e-3))]
    )  # fmt: skip
    assert {c.sensor for c in chans} == {"position_child_0.5"}  # one sensor on both pulls
    labels = ["Kp[child]", "Kp[parent]", "Kd[child]", "Kd[parent]", "sigma[position_child_0.5]"]
    bands = channel_bands(sim, theta, labels, chans, trajs)
    assert len(bands) == 2
    outside = np.mean([b.metrics()["pct_outside"] for b in bands])
    assert 2.0 < outside < 9.0  # 400 points, 95% band
    for b in bands:
        m = b.metrics()
        assert m["band"] == "predictive" and m["rmse"] == pytest.approx(1e-3, rel=0.2)
        assert b.lower.shape == b.recorded.shape == (len(b.time), 2)
        assert np.all(b.predictive_lower <= b.lower + 1e-9)
    text = band_csv(bands[0])
    assert text.splitlines()[0].startswith("time,x_recorded,x_mean,x_lower,x_upper")
    fig, axes = plot_channel_bands(bands)
    assert axes.size >= 4


def test_noise_found_by_sensor_point_then_parameter_band(case):
    sim, trajs, chans = case
    theta = np.array([[*np.log(KP), *np.log(KD), np.log(1e-3)]] * 4)
    labels = ["Kp[child]", "Kp[parent]", "Kd[child]", "Kd[parent]", "sigma[trained]"]
    settings = {"channels": [{"name": "trained", "kind": "position", "link": "child",
                              "fraction": 0.5, "distance": None, "noise": None}]}  # fmt: skip
    (b,) = channel_bands(sim, theta, labels, chans[:1], trajs, settings)
    assert b.predictive_lower is not None  # the run's channel at the same point
    other = chans[0]._replace(point=NamedPoint("child", fraction=0.6))
    (b,) = channel_bands(sim, theta, labels, (other,), trajs, settings)
    assert b.predictive_lower is None and b.metrics()["band"] == "parameter"
    assert isinstance(other, Channel)
