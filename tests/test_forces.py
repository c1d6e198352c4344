"""Force profiles: each shape against its closed form written out independently here, the
spec parser's round trip and error messages, and the seeded profile sets."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from treeinfer.data import forces as F
from treeinfer.errors import ConfigError

DT = 0.01
DUR = 2.0
T = 200
t = np.arange(T) * DT


def test_n_steps_and_times():
    assert F.n_steps(DUR, DT) == T
    assert F.n_steps(0.3, 0.1) == 3  # 0.3 / 0.1 = 2.9999999999999996 in floats
    assert F.n_steps(1.0, 0.3) == 3  # floor: the last interval [0.6, 0.9) ends before 1.0
    np.testing.assert_array_equal(F.sample_times(DUR, DT), t)
    with pytest.raises(ConfigError, match="at least 3"):
        F.n_steps(0.02, DT)
    with pytest.raises(ConfigError, match="dt must be positive"):
        F.n_steps(1.0, 0.0)
    with pytest.raises(ConfigError, match="duration must be finite"):
        F.n_steps(float("inf"), DT)


def test_min_steps_matches_trajectory_files():
    from treeinfer.data.trajectories import MIN_ROWS

    assert F.MIN_STEPS == MIN_ROWS


def test_ramp_closed_form_and_monotonic():
    f = F.ramp(12.0, 0.5, DUR, DT, start=0.2)
    expected = 12.0 * np.clip((t - 0.2) / 0.5, 0.0, 1.0)
    assert f.shape == (T,)
    np.testing.assert_allclose(f, expected, atol=1e-12)
    assert np.all(f[t <= 0.2] == 0.0)
    assert np.all(f[t >= 0.7 + 1e-9] == 12.0)
    assert np.all(np.diff(f) >= 0)
    assert f.max() == 12.0


def test_ramp_longer_than_duration_is_cut():
    f = F.ramp(10.0, 4.0, DUR, DT)
    np.testing.assert_allclose(f, 10.0 * t / 4.0, atol=1e-12)
    assert f.max() < 10.0


def _hold_reference(peak, r, h, rel, start):
    """Closed form of ramp-hold-release, segment by segment."""
    out = np.zeros_like(t)
    up = (t >= start) & (t < start + r)
    out[up] = peak * (t[up] - start) / r
    top = (t >= start + r) & (t < start + r + h)
    out[top] = peak
    down = (t >= start + r + h) & (t < start + r + h + rel)
    out[down] = peak * (1.0 - (t[down] - start - r - h) / rel)
    return out


@pytest.mark.parametrize("hold", [0.6, 0.0])
def test_ramp_hold_closed_form_and_segments(hold):
    peak, r, rel, start = 15.0, 0.5, 0.4, 0.1
    f = F.ramp_hold(peak, r, hold, rel, DUR, DT, start=start)
    np.testing.assert_allclose(f, _hold_reference(peak, r, hold, rel, start), atol=1e-9)
    rise = (t >= start) & (t <= start + r)
    fall = (t >= start + r + hold) & (t <= start + r + hold + rel)
    assert np.all(np.diff(f[rise]) > 0)
    assert np.all(np.diff(f[fall]) < 0)
    assert np.all(f[t > start + r + hold + rel + 1e-9] == 0.0)  # rest again
    if hold:
        assert np.all(f[(t >= start + r) & (t <= start + r + hold)] == peak)
        assert f.max() == peak


def test_ramp_release_is_hold_without_hold():
    np.testing.assert_array_equal(
        F.ramp_release(8.0, 0.3, 0.5, DUR, DT, 0.2), F.ramp_hold(8.0, 0.3, 0.0, 0.5, DUR, DT, 0.2)
    )


def test_smooth_step_closed_form_and_flat_ends():
    peak, rise, start = 5.0, 0.4, 0.3
    f = F.smooth_step(peak, rise, DUR, DT, start)
    s = np.clip((t - start) / rise, 0, 1)
    np.testing.assert_allclose(f, peak * (3 * s**2 - 2 * s**3), atol=1e-12)
    assert np.all(np.diff(f) >= 0)
    slope = np.diff(f) / DT
    max_slope = 1.5 * peak / rise  # the smoothstep's slope at mid-rise
    assert slope.max() <= max_slope + 1e-9
    i0, i1 = round(start / DT), round((start + rise) / DT)
    # slope ~ 0 at both ends of the rise (a linear ramp would have peak / rise there)
    assert abs(slope[i0]) < 0.1 * peak / rise and abs(slope[i1 - 1]) < 0.1 * peak / rise


@pytest.mark.parametrize(
    "call, field",
    [
        (lambda: F.ramp(10, -1.0, DUR, DT), "ramp_time"),
        (lambda: F.ramp(10, 0.0, DUR, DT), "ramp_time"),
        (lambda: F.ramp(float("nan"), 1.0, DUR, DT), "peak"),
        (lambda: F.ramp(10, 1.0, DUR, DT, start=-0.1), "start"),
        (lambda: F.ramp(10, 1.0, DUR, DT, start=DUR), "start"),
        (lambda: F.ramp_hold(10, 0.5, -0.1, 0.5, DUR, DT), "hold_time"),
        (lambda: F.ramp_hold(10, 0.5, 0.5, 0.0, DUR, DT), "release_time"),
        (lambda: F.smooth_step(10, 0.0, DUR, DT), "rise_time"),
    ],
)
def test_shape_argument_errors_name_the_field(call, field):
    with pytest.raises(ConfigError, match=field):
        call()


def test_piecewise_linear_checks_knots():
    with pytest.raises(ConfigError, match="strictly increasing"):
        F.piecewise_linear([0.0, 0.5, 0.5], [0, 1, 2], DUR, DT)
    with pytest.raises(ConfigError, match="equally long"):
        F.piecewise_linear([0.0, 0.5], [0.0], DUR, DT)


# ---- specs ----------------------------------------------------------------------------------
def test_from_spec_matches_direct_calls():
    np.testing.assert_array_equal(
        F.from_spec("ramp:peak=20,ramp=1.0", DUR, DT), F.ramp(20, 1.0, DUR, DT)
    )
    np.testing.assert_array_equal(
        F.from_spec(" HOLD : peak=15, ramp=0.5, hold=1.0, release=0.5, start=0.1 ", DUR, DT),
        F.ramp_hold(15, 0.5, 1.0, 0.5, DUR, DT, start=0.1),
    )
    np.testing.assert_array_equal(
        F.from_spec("release:peak=3,ramp=0.2,release=0.3", DUR, DT),
        F.ramp_release(3, 0.2, 0.3, DUR, DT),
    )
    np.testing.assert_array_equal(
        F.from_spec("step:peak=4,rise=0.2,start=1", DUR, DT), F.smooth_step(4, 0.2, DUR, DT, 1.0)
    )


def test_parse_spec_values():
    ps = F.parse_spec("hold:peak=15,ramp=0.5,hold=1.0,release=0.5")
    assert ps == F.ProfileSpec("hold", {"peak": 15.0, "ramp": 0.5, "hold": 1.0, "release": 0.5})


@settings(max_examples=50, deadline=None)
@given(
    kind=st.sampled_from(sorted(F.SPEC_KEYS)),
    values=st.lists(st.floats(1e-6, 1e6, allow_nan=False), min_size=5, max_size=5),
)
def test_format_spec_round_trips_exactly(kind, values):
    params = dict(zip(F.SPEC_KEYS[kind], values))
    assert F.parse_spec(F.format_spec(kind, **params)) == F.ProfileSpec(kind, params)


@pytest.mark.parametrize(
    "spec, pattern",
    [
        ("wiggle:peak=1", r"unknown kind 'wiggle'"),
        ("ramp:peak=20,ramp=1,hold=2", r"unknown key 'hold' for kind 'ramp'"),
        ("ramp:peak=20", r"missing key\(s\) ramp"),
        ("hold:peak=1,ramp=1", r"missing key\(s\) hold, release"),
        ("ramp:peak=abc,ramp=1", r"key 'peak' must be a number, got 'abc'"),
        ("ramp:peak=1,peak=2,ramp=1", r"key 'peak' given twice"),
        ("ramp:peak20,ramp=1", r"expected key=value, got 'peak20'"),
        ("ramp:peak=inf,ramp=1", r"key 'peak' must be finite"),
        ("ramp", r"missing key\(s\) peak, ramp"),
        ("", r"expected 'kind:key=value"),
    ],
)
def test_parse_spec_errors(spec, pattern):
    with pytest.raises(ConfigError, match=pattern):
        F.parse_spec(spec)


def test_from_spec_range_error_quotes_the_spec():
    with pytest.raises(ConfigError, match=r"'ramp:peak=1,ramp=-2'.*ramp_time"):
        F.from_spec("ramp:peak=1,ramp=-2", DUR, DT)


# ---- seeded sets ----------------------------------------------------------------------------
def test_profile_set_shapes_peaks_and_kinds():
    lo, hi = 2.0, 8.0
    specs = F.random_specs("mixed", 6, 1.0, (lo, hi), seed=3)
    assert [F.parse_spec(s).kind for s in specs] == ["ramp", "hold"] * 3
    p = F.profile_set("mixed", 6, 1.0, DT, (lo, hi), seed=3)
    assert p.shape == (6, 100)
    np.testing.assert_array_equal(p, np.stack([F.from_spec(s, 1.0, DT) for s in specs]))
    peaks = np.array([F.parse_spec(s).params["peak"] for s in specs])
    assert np.all((peaks >= lo) & (peaks <= hi))
    np.testing.assert_array_equal(p.max(axis=1), peaks)  # every shape reaches and holds its peak
    assert np.all(p[:, 0] == 0.0)  # every pull starts from rest
    assert np.all(p[1::2, -1] == 0.0)  # ramp-hold-release ends released
    assert np.all(p[0::2, -1] == peaks[0::2])  # ramps end held
    assert len(set(peaks)) == 6  # varied


@pytest.mark.parametrize("kind", F.SET_KINDS)
def test_profile_set_seed_reproducibility(kind):
    a = F.profile_set(kind, 4, 1.0, DT, seed=7)
    b = F.profile_set(kind, 4, 1.0, DT, seed=7)
    c = F.profile_set(kind, 4, 1.0, DT, seed=8)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    g1, g2 = np.random.default_rng(5), np.random.default_rng(5)
    np.testing.assert_array_equal(
        F.profile_set(kind, 3, 1.0, DT, seed=g1), F.profile_set(kind, 3, 1.0, DT, seed=g2)
    )
    if kind != "mixed":
        assert {F.parse_spec(s).kind for s in F.random_specs(kind, 3, 1.0, seed=1)} == {kind}


@pytest.mark.parametrize(
    "kwargs, pattern",
    [
        ({"kind": "zigzag"}, "unknown kind 'zigzag'"),
        ({"n": 0}, "n must be an integer >= 1"),
        ({"peak_range": (5.0, 1.0)}, "low <= high"),
        ({"peak_range": (1.0,)}, "two numbers"),
        ({"duration": -1.0}, "duration must be positive"),
    ],
)
def test_random_specs_errors(kwargs, pattern):
    with pytest.raises(ConfigError, match=pattern):
        F.random_specs(**kwargs)
