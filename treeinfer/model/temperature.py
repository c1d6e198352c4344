"""Choosing the Boltzmann temperature kT from the noise (split from
:mod:`treeinfer.model.likelihood`, which re-exports every name; the docstring of
:mod:`treeinfer.model.boltzmann` derives the rule
``kT = sigma / sqrt(T) (1 + sqrt(2) dt omega2)``)."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ..data.trajectories import Observations
from ..errors import ConfigError
from . import noise


def check_kT(kT) -> float:
    try:
        kT = float(kT)
    except (TypeError, ValueError):
        raise ConfigError(f"kT: expected a positive number, got {kT!r}") from None
    if not math.isfinite(kT) or kT <= 0:
        raise ConfigError(f"kT: must be a finite positive number, got {kT}")
    return kT


def suggest_kT(sigma_displacement: float, n_steps: int, dt: float, omega2: float = 0.0) -> float:
    """Boltzmann temperature that matches the Gaussian measurement model's posterior width.

    ``kT = sigma / sqrt(T) * (1 + sqrt(2) * dt * omega2)`` (module docstring: equal curvature of
    ``-L_b / kT`` and of the Gaussian log-likelihood at the truth). Per trajectory loss; the same
    value for any number of trajectories.

    Args:
      sigma_displacement: m, white displacement-noise std.
      n_steps: samples T per trajectory. dt: s between samples.
      omega2: 1/s^2, mean squared velocity over mean squared displacement of the signal (the
        velocity term's share); 0 ignores the velocity term.
    """
    sigma = noise.check_sigma(sigma_displacement, "sigma_displacement")
    if int(n_steps) < 1 or not (dt > 0) or not (omega2 >= 0):
        raise ConfigError(
            f"suggest_kT: need n_steps >= 1, dt > 0, omega2 >= 0; got {n_steps}, {dt}, {omega2}"
        )
    return float(sigma / math.sqrt(int(n_steps)) * (1.0 + math.sqrt(2.0) * dt * omega2))


def signal_omega2(obs: Observations, sigma: float, lag: int = 5) -> float:
    """``omega2`` for :func:`suggest_kT` from data (1/s^2): mean squared velocity over mean squared
    displacement, noise power removed. Velocity is the lag-``lag`` central difference
    ``(x[t+k] - x[t-k]) / (2 k dt)`` (noise variance ``sigma^2 / (2 k^2 dt^2)``, k^2 times less
    than the 1-step difference), so the subtraction is stable. Clipped at 0."""
    x = np.asarray(obs.displacement, float)
    m = np.asarray(obs.mask, bool)
    k, dt = int(lag), float(obs.dt)
    if x.shape[-1] <= 2 * k:
        return 0.0
    v = (x[:, 2 * k :] - x[:, : -2 * k]) / (2 * k * dt)
    vm = m[:, 2 * k :] & m[:, : -2 * k]
    msv = float(np.mean(v[vm] ** 2)) - sigma**2 / (2 * k**2 * dt**2)
    msx = float(np.mean(x[m] ** 2)) - sigma**2
    if msx <= 0.0:
        return 0.0
    return max(msv, 0.0) / msx


class KTChoice(NamedTuple):
    """Result of :func:`auto_kT`: ``kT`` and what it was computed from (``describe()``)."""

    kT: float
    estimate: noise.NoiseEstimate
    n_steps: int
    dt: float
    omega2: float

    def describe(self) -> str:
        return (
            f"kT auto = {self.kT:.4g}: {self.estimate.describe()}; rule kT = sigma / sqrt(T) * "
            f"(1 + sqrt(2) dt omega2) with T = {self.n_steps}, dt = {self.dt:g} s, "
            f"omega2 = {self.omega2:.4g} 1/s^2 (velocity share from the data)"
        )


def auto_kT(data, sigma_displacement: float | None = None) -> KTChoice:
    """``kT = "auto"``: estimate the displacement noise (unless given) and apply :func:`suggest_kT`.

    ``T`` is the median number of real samples per trajectory. Raises ConfigError when the data
    are too short to estimate the noise (give ``sigma_displacement`` then)."""
    obs = noise.as_observations(data)
    if sigma_displacement is None:
        est = noise.estimate_displacement_noise(obs)
    else:
        s = noise.check_sigma(
            sigma_displacement, "noise_displacement", noise.displacement_range(obs)
        )
        est = noise.NoiseEstimate(s, 0, "given")
    n_steps = int(np.median(np.sum(np.asarray(obs.mask, bool), axis=-1)))
    om2 = signal_omega2(obs, est.sigma)
    kT = suggest_kT(est.sigma, n_steps, float(obs.dt), om2)
    return KTChoice(kT, est, n_steps, float(obs.dt), om2)
