"""Checks between a recording's streams (issue 28, section 3, "data that lie"): what the force
and the displacement must satisfy together whatever the tree's stiffness, so a mistake in one
stream shows without knowing the answer.

* **At rest, no load.** Displacement is measured from the branch's rest position under no load,
  so while the branch still rests before the pull (the first samples, before the force rises)
  the force and the displacement are both zero up to their noise. A force well away from zero
  there, with the displacement at zero, is a load cell whose tare was not subtracted; a
  displacement well away from zero with no force is a rest position not subtracted (or a
  displacement offset). The existing ``rest`` check (:mod:`treeinfer.data.checks`) judges the
  first sample against a quarter of the range; this one judges the resting samples against
  their own noise, so a few centimetres of offset on a 30 cm pull do not pass.
* **Cause before effect.** A branch moves because it is pulled: the displacement responds to the
  force through a causal (low-pass) system, so it cannot leave its rest before the force does.
  A displacement that starts several samples ahead of the force means the streams' clocks are
  offset. (A displacement that starts late is not judged here: inertia and damping delay a
  branch's response by amounts only a fit can tell; the fit's residual checks see that.)

Noise levels come from :func:`treeinfer.data.noise_estimate.estimate_white_noise` (robust, from
second differences), so the thresholds scale with the sensor and a noisy recording raises no
false alarm. Each finding names the file and the column, what was seen and what was probably
meant; ``infer --allow-implausible-data`` goes past them.
"""

from __future__ import annotations

import numpy as np

from ..tree.plausibility import REST_FORCE, Finding

REST_WINDOW = 0.05  # share of the samples before the force first rises that is "at rest" ...
REST_WINDOW_MIN = 5  # ... but at least this many samples
REST_NOISE_SIGMAS, REST_RANGE_SHARE = 4.0, 0.02  # "the force has not moved yet": within these
OFFSET_SIGMAS = 6.0  # a resting value this many noise standard errors from zero is an offset
DISP_OFFSET_MIN = 0.005  # m; and at least this much (a rest position within 5 mm is fine)
DISP_OFFSET_SHARE = 0.05  # ... and this share of the displacement's range
LEAD_SAMPLES = 3  # displacement ahead of the force by more than this many samples ...
LEAD_SECONDS = 0.03  # ... and this many seconds: the clocks are offset
ONSET_SHARE = 0.1  # a stream "leaves its rest" at this share of its range ...
MAX_ONSET_SHARE = 0.3  # ... raised above the noise, up to this share (noisier: not judged)
SMOOTH_SECONDS = 0.05  # moving average applied to both streams before timing their onsets


def _noise(values: np.ndarray) -> float:
    from ..errors import ConfigError
    from .noise_estimate import estimate_white_noise

    try:
        return float(estimate_white_noise(np.asarray(values, float)[None]).sigma)
    except ConfigError:  # too short or constant: the spread of the increments instead
        d = np.diff(np.asarray(values, float))
        return float(np.median(np.abs(d - np.median(d))) * 1.4826 / np.sqrt(2)) if d.size else 0.0


def rest_samples(force: np.ndarray) -> int:
    """How many leading samples are at rest: up to where the force first leaves its starting
    level by more than its noise (four standard deviations, and 2% of its range), and at most
    :data:`REST_WINDOW` of the recording. A pull that starts at once has none."""
    f = np.asarray(force, float)
    frange = float(np.ptp(f))
    if frange <= 0:
        return 0
    level = max(REST_NOISE_SIGMAS * _noise(f), REST_RANGE_SHARE * frange)
    moved = np.flatnonzero(np.abs(f - f[0]) > level)
    first = int(moved[0]) if moved.size else f.size
    return int(min(first, max(REST_WINDOW_MIN, int(REST_WINDOW * f.size))))


def rest_offsets(name: str, force, displacement) -> list[Finding]:
    """Force or displacement away from zero while the branch rests (module docstring)."""
    f = np.asarray(force, float)
    x = np.asarray(displacement, float)
    n = rest_samples(f)
    if n < 3:
        return []  # the pull starts at once: no resting samples to judge
    sf, sx = _noise(f), _noise(x)
    f0, x0 = float(np.median(f[:n])), float(np.median(x[:n]))
    # standard error of a median of n samples ~ 1.25 sigma / sqrt(n)
    ef, ex = 1.25 * sf / np.sqrt(n), 1.25 * sx / np.sqrt(n)
    fmax, xrange = float(np.max(np.abs(f))), float(np.ptp(x))
    out = []
    x_rests = abs(x0) <= max(OFFSET_SIGMAS * ex, DISP_OFFSET_MIN, DISP_OFFSET_SHARE * xrange)
    if x_rests and abs(f0) > max(OFFSET_SIGMAS * ef, REST_FORCE * fmax):
        out.append(
            Finding(
                "error",
                name,
                "force-offset",
                f"column force: {f0:.3g} N over the first {n} samples, while the displacement "
                f"is still at rest ({x0:.3g} m): a force that moves nothing is an offset; the "
                "load cell's tare was probably not subtracted (subtract the resting force, or "
                "--tare on import-csv)",
            )
        )
    elif abs(f0) <= max(OFFSET_SIGMAS * ef, REST_FORCE * fmax) and abs(x0) > max(
        OFFSET_SIGMAS * ex, DISP_OFFSET_MIN, DISP_OFFSET_SHARE * xrange
    ):
        out.append(
            Finding(
                "error",
                name,
                "displacement-offset",
                f"column displacement: {x0:.3g} m over the first {n} samples while no force acts "
                f"(noise {sx:.2g} m): displacement must be measured from the branch's rest "
                "position; subtract the resting value (a position logged in world coordinates, "
                "or an offset?)",
            )
        )
    return out


def _onset(values: np.ndarray, share: float) -> int | None:
    """First sample where ``values`` leave their starting level by ``share`` of their range;
    None if they never do."""
    v = np.asarray(values, float)
    base = float(np.median(v[:3]))
    moved = np.flatnonzero(np.abs(v - base) > share * float(np.ptp(v)))
    return int(moved[0]) if moved.size else None


TIMING_SIGMAS = 4.0  # ... and this many standard deviations of the two onsets' timing noise


SLOPE_SECONDS = 0.2  # half-width of the window the crossing's slope is fitted over


def _timing_sd(v: np.ndarray, idx: int, sigma: float, w: int) -> float:
    """Samples: the standard deviation of a crossing time at ``idx`` caused by noise ``sigma``
    on ``v``, ``sigma / slope``: on a slow ramp, noise moves the crossing by many samples.

    The slope is a least-squares line over ``w`` samples each side, not the difference of the
    two ends: a FIRST crossing of a noisy signal happens where the noise is up, and there the
    end-to-end difference over a few samples is steep by chance. On a 2.3 s ramp to 2.4 N with
    3.3 mm displacement noise (SBC data set 45 of experiments/sbc_default.py, simulated by
    treeinfer itself) that made the jitter 4x too small and the check refused the data as
    "displacement 0.16 s before the force"."""
    lo, hi = max(idx - w, 0), min(idx + w, len(v) - 1)
    if hi - lo < 2:
        return float("inf")
    t = np.arange(lo, hi + 1, dtype=float)
    slope = abs(float(np.polyfit(t, np.asarray(v[lo : hi + 1], float), 1)[0]))
    return float(sigma / slope) if slope > 0 else float("inf")


def lead_of_displacement(name: str, force, displacement, dt: float) -> list[Finding]:
    """The displacement leaving rest before the force does (module docstring): clocks offset.

    Onsets, not a cross-correlation: a branch's own inertia and damping delay its response by a
    good part of a second, so a correlation peak cannot tell a logger's lag from the dynamics;
    but a response cannot START before its cause, whatever the tree. At a tenth of each
    stream's range, a quasi-static response crosses together with the force and any dynamics
    only later (an overshoot makes the range larger, a lag later still)."""
    f = np.asarray(force, float)
    x = np.asarray(displacement, float)
    if f.size < 10 or dt <= 0:
        return []
    # the same centred moving average on both streams (no relative shift): the noise of single
    # samples would otherwise inflate each range and time each crossing by chance
    w = max(1, int(round(SMOOTH_SECONDS / dt)))
    if f.size < 4 * w:
        return []
    kern = np.ones(w) / w
    sf, sx = _noise(f) / np.sqrt(w), _noise(x) / np.sqrt(w)
    f = np.convolve(f, kern, mode="valid")
    x = np.convolve(x, kern, mode="valid")
    frange, xrange = float(np.ptp(f)), float(np.ptp(x))
    if frange <= 0 or xrange <= 0:
        return []
    # one share of the range for both streams (clear of six noise sigmas in each), so that a
    # quasi-static response crosses it together with the force whatever the noise
    share = max(ONSET_SHARE, 6.0 * sf / frange, 6.0 * sx / xrange)
    if share >= MAX_ONSET_SHARE:
        return []  # too noisy to time an onset
    tf, tx = _onset(f, share), _onset(x, share)
    if tf is None or tx is None or tf < 3:
        return []  # no clear onset, or the pull was already under way at the first sample
    lead = tf - tx
    # noise times each crossing only to within sigma / slope: a 2% force noise on a slow ramp
    # moved the force's onset by 3-4 samples (a false alarm on an independent simulator's pull)
    ws = max(w, int(round(SLOPE_SECONDS / dt)))
    jitter = TIMING_SIGMAS * float(np.hypot(_timing_sd(f, tf, sf, ws), _timing_sd(x, tx, sx, ws)))
    if lead <= max(LEAD_SAMPLES, LEAD_SECONDS / dt, jitter):
        return []
    return [
        Finding(
            "error",
            name,
            "stream-lag",
            f"column displacement leaves its rest {lead * dt:.3g} s ({lead} samples) BEFORE the "
            f"force rises (displacement at {tx * dt:.3g} s, force at {tf * dt:.3g} s): a branch "
            "cannot move before it is pulled, so the two streams' clocks are offset; align them "
            "(shift the displacement later by that much) before inferring",
        )
    ]


def stream_checks(name: str, force, displacement, dt: float) -> list[Finding]:
    """Every check of this module on one recording."""
    return rest_offsets(name, force, displacement) + lead_of_displacement(
        name, force, displacement, dt
    )
