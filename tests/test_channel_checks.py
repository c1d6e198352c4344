"""The fit verdict's checks of observation channels (issue 30): per sensor coverage of the
training channel data, standardised residuals and their lag-1 autocorrelation, on channels
whose noise is known (white, too large, autocorrelated), with the numbers checked by hand."""

import numpy as np
import pytest
from scipy.stats import norm

from treeinfer.data.channels import Channel, NamedPoint
from treeinfer.evaluation.channel_bands import ChannelBand, run_channels
from treeinfer.evaluation.channel_checks import channel_verdict, sensor_checks
from treeinfer.evaluation.checks import FitVerdict

S, P, SIGMA = 400, 64, 1e-3


def _band(recorded, name="tilt_0", sensor="tilt", spread=1e-5, noisy=True, seed=0):
    """A ChannelBand of a channel whose truth is a ramp, the particles scattered about it by
    ``spread`` and the noise ``SIGMA``: its bands the exact normal quantiles."""
    rng = np.random.default_rng(seed)
    t = np.arange(S) * 0.1
    truth = (0.01 * t / t[-1])[:, None]
    draws = truth[None] + spread * rng.standard_normal((P, 1, 1))
    ch = Channel(name, "angle", "p.csv", NamedPoint("stem", fraction=0.5), ("y",), t,
                 recorded, sensor=sensor)  # fmt: skip
    half = norm.ppf(0.975) * np.sqrt(SIGMA**2 + spread**2)
    lo, hi = (truth - half, truth + half) if noisy else (None, None)
    sig = np.full(P, SIGMA) if noisy else None
    return ChannelBand(ch, t, recorded, draws.mean(0), draws.min(0), draws.max(0), lo, hi,
                       draws, sig)  # fmt: skip


def _truth():
    return (0.01 * np.arange(S) * 0.1 / ((S - 1) * 0.1))[:, None]


def test_white_noise_of_the_right_scale_passes():
    rng = np.random.default_rng(1)
    bands = [_band(_truth() + rng.normal(0, SIGMA, (S, 1)), f"tilt_{i}", seed=i) for i in range(2)]
    poor, warn, meas = sensor_checks(bands)
    assert poor == [] and warn == []
    m = meas["tilt"]
    assert m["channels"] == ["tilt_0", "tilt_1"] and m["band"] == "predictive"
    assert m["fraction_outside"] == pytest.approx(0.05, abs=0.025)
    assert m["ppc"]["z_std"] == pytest.approx(1.0, abs=0.1)
    assert abs(m["ppc"]["lag1"]) < 0.1


def test_noise_three_times_the_model_s_is_poor_fit():
    rng = np.random.default_rng(2)
    rec = _truth() + rng.normal(0, 3 * SIGMA, (S, 1))
    poor, warn, meas = sensor_checks([_band(rec)])
    # by hand: the share outside +-1.96 sigma of a 3 sigma noise is 2 P(Z > 0.653) = 0.51
    assert meas["tilt"]["fraction_outside"] == pytest.approx(2 * norm.sf(1.96 / 3), abs=0.06)
    assert poor and "channel tilt (angle at stem@0.5)" in poor[0]
    assert any("understates" in w for w in warn)


def test_autocorrelated_residuals_warn_with_their_lag1():
    rng = np.random.default_rng(3)
    e = np.zeros(S)
    for k in range(1, S):  # AR(1), rho 0.8, marginal std SIGMA: coverage stays about right
        e[k] = 0.8 * e[k - 1] + np.sqrt(1 - 0.64) * rng.normal(0, SIGMA)
    poor, warn, meas = sensor_checks([_band(_truth() + e[:, None])])
    lag1 = meas["tilt"]["ppc"]["lag1"]
    zc = (e - e.mean()) / SIGMA  # the residuals standardise to e / sigma (tiny spread)
    assert lag1 == pytest.approx(float(zc[1:] @ zc[:-1] / (zc @ zc)), abs=0.02)
    assert lag1 > 0.6
    assert any("autocorrelated" in w and "channel tilt" in w for w in warn)


def test_parameter_band_only_is_reported_not_judged():
    rng = np.random.default_rng(4)
    rec = _truth() + rng.normal(0, 10 * SIGMA, (S, 1))
    poor, warn, meas = sensor_checks([_band(rec, noisy=False)])
    assert poor == [] and meas["tilt"]["band"] == "parameter"


def test_channel_verdict_without_channels_is_unchanged():
    v = FitVerdict("ok", [], {})

    class P:
        spec = None

    assert channel_verdict(v, P(), None, None, []) == (v, [])


def test_run_channels_one_per_sensor_with_nan_values():
    settings = {"channels": [
        {"name": "m_000", "kind": "position", "link": "child", "fraction": 0.5,
         "distance": None, "components": ["x", "z"], "noise": None, "sensor": "m"},
        {"name": "m_001", "kind": "position", "link": "child", "fraction": 0.5,
         "distance": None, "components": ["x", "z"], "noise": None, "sensor": "m"},
        {"name": "tilt", "kind": "angle", "link": "parent", "fraction": None,
         "distance": 0.3, "components": ["y"], "noise": 0.002, "sensor": "tilt"},
    ]}  # fmt: skip
    chans = run_channels(settings, "new.csv", np.arange(5) * 0.02)
    assert [c.name for c in chans] == ["m", "tilt"]
    assert chans[0].values.shape == (5, 2) and np.isnan(chans[0].values).all()
    assert chans[1].noise == 0.002 and chans[1].point.distance == 0.3
    assert all(c.recording == "new.csv" for c in chans)
