"""The baseline for static pulling tests: a uniform Euler-Bernoulli cantilever on a rotational
root-plate spring, fitted by least squares to the same tilts.

The stem is clamped on a spring at the ground (root-plate compliance ``1/K``) and bends with a
constant ``EI``. The cable's horizontal component ``F cos a`` at height ``h`` gives the moment
``F cos a (h - z)`` at height ``z < h`` (the vertical component runs along the upright stem and
is dropped, as is self-weight), so the tilt at height ``z`` is, by integrating ``M / EI``,

    theta(z) = F cos a [ h / K + (h z - z^2 / 2) / EI ]     (z <= h)
    theta(z) = F cos a [ h / K + h^2 / (2 EI) ]              (z >= h: no moment above the cable)

linear in the two compliances ``c = (1/K, 1/EI)``. They are fitted to every recorded tilt of
every channel at once by non-negative least squares (``scipy.optimize.nnls``: a negative
compliance is no beam). A uniform beam ties the channels together: the ratio of the trunk's
to the root clino's tilt is at most ``g(z_trunk) / g(z_root)``, and real stems (taper, a
second stem, a clino above the sling) often exceed it.

:func:`fit_springs` is the second baseline, the analysis of the pulling-test literature: each
inclinometer's tilt is proportional to the moment at the ground, ``theta_c = M / K_c`` with
``M = F cos a h``, one least-squares slope through the origin per channel (no coupling, so it
follows each channel's mean slope, as the chain's two springs can). Neither baseline has a noise
model or an uncertainty.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = ["BeamFit", "beam_design", "beam_predict", "fit_beam", "fit_springs", "springs_predict"]


class BeamFit(NamedTuple):
    k_root: float  # N m/rad (inf when the fit puts all compliance in the stem)
    ei: float  # N m^2
    compliance: tuple[float, float]  # (1/K, 1/EI)
    rmse: float  # rad, on the fitted data


def beam_design(heights, sling_height: float, cable_angle: float, force) -> np.ndarray:
    """``[C, T, 2]``: the tilt per unit compliance (1/K, 1/EI) at each channel's height."""
    f = np.asarray(force, float) * np.cos(cable_angle)
    h = float(sling_height)
    rows = []
    for z in heights:
        z = min(float(z), h)
        rows.append(np.stack([f * h, f * (h * z - z * z / 2)], axis=-1))
    return np.stack(rows)


def fit_beam(heights, sling_height: float, cable_angle: float, force, tilt) -> BeamFit:
    """Least-squares compliances from ``tilt`` [C, T] rad (NaN = missing) under ``force`` [T] N."""
    from scipy.optimize import nnls

    a = beam_design(heights, sling_height, cable_angle, force)
    y = np.atleast_2d(np.asarray(tilt, float))
    ok = np.isfinite(y)
    aa, yy = a[ok], y[ok]
    scale = np.abs(aa).max(axis=0)  # columns of very different size (1/K vs 1/EI)
    scale[scale == 0] = 1.0
    c, _ = nnls(aa / scale, yy)
    c = c / scale
    rmse = float(np.sqrt(np.mean((aa @ c - yy) ** 2)))
    k = float(1 / c[0]) if c[0] > 0 else float("inf")
    ei = float(1 / c[1]) if c[1] > 0 else float("inf")
    return BeamFit(k, ei, (float(c[0]), float(c[1])), rmse)


def beam_predict(fit: BeamFit, heights, sling_height: float, cable_angle: float, force):
    """``[C, T]`` rad: the fitted beam's tilts under ``force``."""
    return beam_design(heights, sling_height, cable_angle, force) @ np.asarray(fit.compliance)


def fit_springs(sling_height: float, cable_angle: float, force, tilt) -> np.ndarray:
    """``[C]`` N m/rad: per channel, the moment at the ground over the tilt, ``K_c`` of
    ``theta_c = F cos a h / K_c`` by least squares through the origin (NaN = missing)."""
    m = np.asarray(force, float) * np.cos(cable_angle) * float(sling_height)
    y = np.atleast_2d(np.asarray(tilt, float))
    out = []
    for row in y:
        ok = np.isfinite(row)
        slope = float(np.sum(m[ok] * row[ok]) / np.sum(m[ok] ** 2))
        out.append(1 / slope if slope > 0 else float("inf"))
    return np.asarray(out)


def springs_predict(k, sling_height: float, cable_angle: float, force) -> np.ndarray:
    """``[C, T]`` rad: tilts of :func:`fit_springs`' springs under ``force``."""
    m = np.asarray(force, float) * np.cos(cable_angle) * float(sling_height)
    return m[None, :] / np.asarray(k, float)[:, None]
