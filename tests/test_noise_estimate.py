"""Noise estimation on quantised and upsampled recordings (issue 27, item 3), against
independent references: the realised error of a simulated quantised Gaussian process, and
streams built at a known native rate and then repeated or interpolated by a known factor."""

from __future__ import annotations

import math

import numpy as np
import pytest

from treeinfer.data.noise_estimate import (
    detect_upsampling,
    estimate_white_noise,
    quantisation_step,
)
from treeinfer.data.trajectories import Trajectory
from treeinfer.errors import ConfigError
from treeinfer.model import noise
from treeinfer.model.force_noise import estimate_force_noise, resolve_noise_force


def _pull(t, amp=0.05, omega=8.0, zeta=0.3):
    """A smooth damped step response (m), like a branch pulled by a ramp."""
    wd = omega * math.sqrt(1 - zeta**2)
    return amp * (
        1 - np.exp(-zeta * omega * t) * (np.cos(wd * t) + zeta * omega / wd * np.sin(wd * t))
    )


def _rows(sigma, n=4, T=301, dt=0.01, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(T) * dt
    clean = np.stack([_pull(t, amp=0.03 + 0.01 * b) for b in range(n)])
    return t, clean, clean + sigma * rng.standard_normal(clean.shape)


def _plain_mad(x):
    """The estimator before issue 27 (MAD of all second differences / sqrt 6), for contrast."""
    d2 = np.diff(x, n=2, axis=-1).ravel()
    return 1.4826 * np.median(np.abs(d2 - np.median(d2))) / math.sqrt(6)


# ---- quantisation ------------------------------------------------------------------------------
@pytest.mark.parametrize("q", [5e-4, 1e-4])
def test_quantised_sensor_is_floored_at_step_over_sqrt12(q):
    """A stepper-driven rig: displacement rounded to a grid of q with sensor noise far below
    q. The reference is the realised rounding error itself (recorded minus the smooth truth),
    whose std a uniform-on-a-step error makes q / sqrt(12): the estimate matches it to 15%."""
    _, clean, noisy = _rows(q / 20.0, seed=1)
    recorded = q * np.round(noisy / q)
    realised = float(np.std(recorded - clean))
    assert realised == pytest.approx(q / math.sqrt(12), rel=0.1)  # the reference's own sanity
    assert _plain_mad(recorded) < 0.5 * realised  # what the old estimator saw (or refused)
    est = estimate_white_noise(recorded)
    assert est.step == pytest.approx(q, rel=1e-6)
    assert est.sigma == pytest.approx(realised, rel=0.15)
    assert any("quantised" in n and "sqrt(12)" in n for n in est.notes)
    assert "quantised" in est.describe()


def test_quantised_noisy_sensor_keeps_its_own_noise():
    """Noise 3x the step: the estimate follows the total error (noise + rounding), not the floor."""
    q = 5e-4
    _, clean, noisy = _rows(3 * q, seed=2)
    recorded = q * np.round(noisy / q)
    realised = float(np.std(recorded - clean))
    est = estimate_white_noise(recorded)
    assert est.step is not None
    assert est.sigma == pytest.approx(realised, rel=0.15)


def test_quantisation_step_detection():
    rng = np.random.default_rng(3)
    grid = 0.25e-3 * np.cumsum(rng.integers(-2, 3, size=(3, 200)), axis=1) + 0.0123
    assert quantisation_step(list(grid)) == pytest.approx(0.25e-3, rel=1e-9)
    # a grid whose smallest step never occurs alone: every difference is 2 or 3 steps
    grid2 = 1e-3 * np.cumsum(rng.choice([-3, -2, 2, 3], size=(2, 200)), axis=1)
    assert quantisation_step(list(grid2)) == pytest.approx(1e-3, rel=1e-9)
    _, _, noisy = _rows(1e-3)
    assert quantisation_step(list(noisy)) is None


def test_a_noise_free_ramp_is_not_taken_for_a_quantised_recording():
    """A simulated ramp-hold-release force lies on a grid of its slope per sample but carries no
    rounding: no step is reported and the estimate is refused as noise-free (the default
    force-noise term is then off), where the same force rounded to 0.1 N is a quantised
    recording floored at 0.1 / sqrt(12)."""
    t = np.arange(80) * 0.01
    ramps = np.stack([p * np.clip(t / (0.1 + 0.1 * i), 0.0, 1.0) * (t < 0.45)
                      for i, p in enumerate((6.0, 3.0))])  # fmt: skip
    assert quantisation_step(list(ramps)) is None
    with pytest.raises(ConfigError, match="piecewise-linear"):
        estimate_white_noise(ramps, what="force", flag="--noise-force", unit="N")
    line = np.linspace(0.0, 6.0, 41)[None]  # float rounding in its second differences
    assert quantisation_step(list(line)) is None
    assert estimate_white_noise(line, what="force", unit="N").sigma < 1e-12
    noisy = ramps + 0.02 * np.random.default_rng(6).standard_normal(ramps.shape)
    est = estimate_white_noise(np.round(noisy, 1), what="force", flag="--noise-force", unit="N")
    assert est.step == pytest.approx(0.1, rel=1e-6)
    assert est.sigma >= 0.1 / math.sqrt(12) - 1e-12


# ---- upsampling --------------------------------------------------------------------------------
def _native(sigma, T_native=160, dt=0.02, n=3, seed=4):
    rng = np.random.default_rng(seed)
    t = np.arange(T_native) * dt
    clean = np.stack([_pull(t, amp=0.04 + 0.01 * b, omega=5.0) for b in range(n)])
    return t, clean + sigma * rng.standard_normal(clean.shape)


@pytest.mark.parametrize("factor", [2, 3, 4])
@pytest.mark.parametrize("kind", ["hold", "linear"])
def test_upsampled_stream_is_estimated_at_its_native_rate(kind, factor):
    """A 50 Hz stream with 2 mm noise written at factor x 50 Hz by repeating or linearly
    interpolating samples: the factor is found and the estimate is the native noise (10%)."""
    sigma = 2e-3
    t, native = _native(sigma)
    t_up = np.arange((len(t) - 1) * factor + 1) * (t[1] - t[0]) / factor
    if kind == "hold":
        up = np.repeat(native, factor, axis=1)[:, : len(t_up)]
    else:
        up = np.stack([np.interp(t_up, t, row) for row in native])
    up = up[:, 1:]  # the native samples need not start at index 0
    ref = estimate_white_noise(native).sigma  # the same estimator on the native stream
    assert ref == pytest.approx(sigma, rel=0.15)
    det = detect_upsampling(list(up))
    assert (det.factor, det.kind) == (factor, kind)
    est = estimate_white_noise(up)
    assert est.factor == factor
    assert est.sigma == pytest.approx(ref, rel=0.1)
    assert any("upsampled" in n and "native rate" in n for n in est.notes)
    if kind == "linear":  # issue 27: 1e-5 mm instead of 2 mm before
        assert _plain_mad(up) < 0.05 * sigma


def test_interpolated_stream_written_with_six_decimals_is_still_found():
    """A CSV rounds the interpolated values to 1 micron: second differences between knots are
    then rounding (+-1 micron), not zero; the phase test still finds the native samples."""
    t, native = _native(2e-3)
    t_up = np.arange((len(t) - 1) * 2 + 1) * (t[1] - t[0]) / 2
    up = np.round(np.stack([np.interp(t_up, t, r) for r in native]), 6)
    est = estimate_white_noise(up)
    assert est.factor == 2
    assert est.sigma == pytest.approx(2e-3, rel=0.2)


def test_native_streams_are_not_taken_for_upsampled():
    _, _, noisy = _rows(1e-3)
    assert detect_upsampling(list(noisy)).factor == 1
    est = estimate_white_noise(noisy)
    assert est.factor == 1 and est.step is None and not est.coarse
    assert est.sigma == pytest.approx(1e-3, rel=0.15)


# ---- too short, too coarse, forces -------------------------------------------------------------
def test_too_short_names_the_flag():
    _, _, noisy = _rows(1e-3, n=1, T=12)
    with pytest.raises(ConfigError, match="too short.*--noise-displacement"):
        estimate_white_noise(noisy)
    f = np.ones((1, 12)) + 1e-3 * np.random.default_rng(0).standard_normal((1, 12))
    trajs = [Trajectory(np.arange(12) * 0.01, f[0], noisy[0], None, "a.csv")]
    with pytest.raises(ConfigError, match="too short.*--noise-force"):
        estimate_force_noise(trajs)


def test_coarse_or_noise_free_recording_says_the_estimate_is_an_upper_bound():
    """Sampled at 0.1 s, the pull's own curvature dominates the second differences (their lag-1
    correlation is near +1, not -2/3): the estimate says so and names the flag."""
    t = np.arange(40) * 0.1
    x = np.stack([_pull(t, amp=0.05, omega=3.0)])
    est = estimate_white_noise(x)
    assert est.coarse
    assert any("upper bound" in n and "--noise-displacement" in n for n in est.notes)


def test_quantised_force_is_floored_and_auto_resolves():
    """A load cell read through an ADC with 0.01 N steps and noise below a step: --noise-force
    auto no longer refuses; the estimate is the realised rounding error (10%)."""
    t, _, _ = _rows(0.0)
    rng = np.random.default_rng(5)
    smooth = 5.0 * t / t[-1] + 0.3 * np.sin(2.0 * t)  # always moving: rounding ~ uniform
    force = smooth + 0.0005 * rng.standard_normal(t.shape)
    force = 0.01 * np.round(force / 0.01)
    x = _pull(t) + 1e-3 * rng.standard_normal(t.shape)
    trajs = [Trajectory(t, force, x, None, "a.csv")]
    est = estimate_force_noise(trajs)
    assert est.step == pytest.approx(0.01, rel=1e-6)
    realised = float(np.std(force - smooth))
    assert est.sigma == pytest.approx(realised, rel=0.1)
    sigma, rule = resolve_noise_force("auto", trajs)
    assert sigma == pytest.approx(est.sigma) and "quantised" in rule


def test_displacement_estimate_through_the_noise_module():
    """noise.estimate_displacement_noise is the same estimator on trajectories (masks honoured)."""
    t, _, noisy = _rows(2e-3)
    trajs = [Trajectory(t, np.ones_like(t), row, None, f"p{b}") for b, row in enumerate(noisy)]
    trajs.append(Trajectory(t[:100], np.ones(100), noisy[0, :100], None, "short"))
    est = noise.estimate_displacement_noise(trajs)
    assert est.sigma == pytest.approx(2e-3, rel=0.15)
    assert est.n_used == 4 * 299 + 98
