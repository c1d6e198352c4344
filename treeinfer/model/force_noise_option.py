"""The ``--noise-force`` option of :mod:`treeinfer.model.force_noise`: its validation, the
estimate of the recorded force's white noise from the data and its resolution to newtons. Split
from that module (which re-exports every name here) to keep it under the layout's 500 lines."""

from __future__ import annotations

import math

import numpy as np

from ..data.noise_estimate import estimate_white_noise
from ..data.trajectories import Observations
from ..errors import ConfigError
from .noise import MIN_NOISE_SAMPLES, NoiseEstimate, as_observations


def check_noise_force(value) -> float | str:
    """Validate ``--noise-force``: a positive number (N), ``"P%"`` (0 < P < 100) or ``"auto"``.

    Returns the number (float), the string ``"auto"``, or the normalised ``"P%"`` string.
    Raises :class:`ConfigError` naming ``noise_force`` for anything else (negative, zero,
    non-finite, a percentage >= 100)."""
    if isinstance(value, str):
        s = value.strip().lower()
        if s == "auto":
            return "auto"
        if s.endswith("%"):
            try:
                pct = float(s[:-1])
            except ValueError:
                raise ConfigError(
                    f"noise_force: expected a number (N), 'P%' or 'auto', got {value!r}"
                ) from None
            if not (math.isfinite(pct) and 0.0 < pct < 100.0):
                raise ConfigError(f"noise_force: a percentage must be in (0, 100), got {value!r}")
            return f"{pct:g}%"
        try:
            value = float(s)
        except ValueError:
            raise ConfigError(
                f"noise_force: expected a number (N), 'P%' or 'auto', got {value!r}"
            ) from None
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(
            f"noise_force: expected a number (N), 'P%' or 'auto', got {value!r}"
        ) from None
    if not math.isfinite(v) or v <= 0.0:
        raise ConfigError(
            f"noise_force (--noise-force): must be a finite positive number of newtons, got {v}"
        )
    return v


def _force_range(obs: Observations) -> float:
    f = np.asarray(obs.force, float)[np.asarray(obs.mask, bool)]
    return float(np.max(np.abs(f))) if f.size else 0.0


def estimate_force_noise(data, min_samples: int = MIN_NOISE_SAMPLES) -> NoiseEstimate:
    """White force-noise std (N) from the recorded forces' high-frequency residual.

    ``sigma_F = 1.4826 * median(|d2 - median(d2)|) / sqrt(6)``, ``d2`` the second differences
    of the recorded force at real samples: the estimator of
    :func:`treeinfer.model.noise.estimate_displacement_noise` applied to the force
    (:func:`treeinfer.data.noise_estimate.estimate_white_noise`: white noise of std s gives second
    differences of std ``sqrt(6) s``, a smooth pull's are tiny). A load cell read through an
    ADC is quantised: the estimate is then floored at ``step / sqrt(12)``; a force stream
    upsampled by repeating or interpolating samples is estimated at its native rate. The
    estimate's ``notes`` say which.

    Raises :class:`ConfigError` naming ``--noise-force`` when there are fewer than
    ``min_samples`` second differences ("too short to estimate") or when more than half of them
    are zero and the values lie on no grid (a noise-free, piecewise-linear force: the
    simulated profiles of ``treeinfer simulate`` without ``--noise-force``)."""
    obs = as_observations(data)
    try:
        return estimate_white_noise(
            obs.force, obs.mask, what="force", flag="--noise-force", unit="N",
            min_samples=min_samples,
        )  # fmt: skip
    except ConfigError as e:
        raise ConfigError(f"noise_force (--noise-force): {e}") from None


def resolve_noise_force(value, data) -> tuple[float, str]:
    """``--noise-force`` value -> (sigma_F in N, a one-line description).

    Numbers are newtons; ``"P%"`` is P% of the largest absolute recorded force of ``data``;
    ``"auto"`` estimates it (:func:`estimate_force_noise`). A sigma_F at or above the largest
    absolute recorded force is refused (a unit mistake: the pulls would be all noise)."""
    obs = as_observations(data)
    v = check_noise_force(value)
    peak = _force_range(obs)
    if v == "auto":
        est = estimate_force_noise(obs)
        notes = "".join(f"; {n}" for n in est.notes)
        sigma, how = est.sigma, f"estimated: {est.method}, n = {est.n_used}{notes}"
    elif isinstance(v, str):
        sigma, how = float(v[:-1]) / 100.0 * peak, f"{v} of the largest |force| {peak:.4g} N"
    else:
        sigma, how = v, "given"
    if not sigma < peak:
        raise ConfigError(
            f"noise_force (--noise-force): {sigma:g} N is not smaller than the largest recorded "
            f"force ({peak:g} N); check the units (newtons)"
        )
    return float(sigma), f"force noise sigma_F = {sigma:.4g} N ({how})"
