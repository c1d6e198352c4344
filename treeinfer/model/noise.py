"""Measurement-noise models: residual densities, noise estimation from data, checks.

The generative measurement model (``--likelihood gaussian`` / ``student_t``) says

    recorded displacement[b, t] = simulated displacement tau[b, t](theta) + e[b, t],
    e[b, t] i.i.d. ~ Normal(0, sigma_x)          (gaussian)
                  or StudentT(df, 0, sigma_x)    (student_t, heavy tails)

over the real (masked-in) samples of every trajectory. Log densities come from
``numpyro.distributions`` (``Normal``, ``StudentT``), so the constants and the heavy-tail
algebra are a well-kept library's, not ours.

When to use which:

* ``gaussian`` (default): simulated recordings, or real ones whose residuals look white and
  without outliers. With ``sigma_x`` inferred, 95% predictive bands then cover ~95% of points.
* ``ar1``: white noise of std sigma_x PLUS a stationary AR(1) component of std sigma_c and
  lag-1 correlation rho (``c[t] = rho c[t-1] + sqrt(1 - rho^2) sigma_c xi[t]``), its exact
  likelihood by a scalar Kalman filter (:func:`ar1_white_log_prob`). Use it when residuals are
  slow (correlated in time): drift, unmodelled slow dynamics (for known force noise prefer
  ``gaussian`` with ``--noise-force``, below). sigma_c
  and rho are always inferred; a point's marginal noise std is ``sqrt(sigma_x^2 + sigma_c^2)``
  (what the predictive band uses).
* ``student_t`` (``df = 4`` by default): real recordings with outliers (a slipping gripper,
  a tracking glitch) or visible model error. A few large residuals then cost ``log`` of their
  size instead of their square, so they do not drag the gains. ``sigma_x`` is the t scale; the
  residual standard deviation is ``sigma_x * sqrt(df / (df - 2))`` (df > 2). Residuals that
  are correlated in time (slow drift) are not modelled by it; the posterior is then too
  narrow by about sqrt(correlation length in samples); see "Force noise" below.

Force noise (decision: an errors-in-variables term, ``--noise-force``, :mod:`treeinfer.
force_noise`): the simulator is driven by the *recorded* force, so force noise reaches the
residual only through the branch's mechanical low-pass, as a SLOW displacement error. Measured
on the built-in 2-branch tree (``tests/test_likelihood.py::
test_force_noise_enters_through_displacement``): 2% white force noise moves the simulated
displacement by ~1.7-1.9 mm rms at 10 ms (~4.5 mm at 20 ms) with lag-1 autocorrelation
0.95-0.99. Treating the noise-free force as B x T latent variables would cost two black-box
simulations per latent per gradient: not feasible. Instead the force noise is marginalised in
closed form after linearising the simulation in the force: the residual of each pull is
``MVN(0, sigma_F^2 J J^T + sigma_x^2 I)`` with ``J`` the exact forward-mode Jacobian of the
simulated displacement in the recorded force, taken once at a reference parameter (the MAP);
see :mod:`treeinfer.model.force_noise` for why this and not the alternatives.

Without ``--noise-force`` (the default, behaviour unchanged) inferring sigma_x absorbs the force
noise's variance: the fitted sigma_x exceeds the displacement noise, but the slow, growing error
is not white: the 95% predictive bands of unseen noisy pulls hold 90.5-97.4% of points
depending on the data set, and the gains' posterior is up to 4x too narrow
(``experiments/README.md``, "Force noise"). The noise estimator below does not see force noise
(it is in the simulation, not in the recording, and it is low-frequency); ``--noise-force auto``
estimates it from the recorded force instead. ``ar1`` models a slow residual too, but a
stationary one; the force-induced error is not stationary (zero at t = 0, growing with the
response).

The velocity term is off by default: recorded velocity is usually differentiated from the
noisy displacement (noise std ``sigma_x / (sqrt(2) dt)``, i.e. ~70x sigma_x at 10 ms, and
correlated with the displacement noise), so it adds no information and would count the
same noise twice. Give ``sigma_v`` only for an independently measured velocity.

Noise estimation (:func:`estimate_displacement_noise`): white noise of std sigma gives second
differences ``x[t+1] - 2 x[t] + x[t-1]`` of std ``sqrt(6) sigma``; a smooth pull's second
differences are tiny at 10 ms sampling (acceleration x dt^2). The robust scale (MAD / 0.6745)
of the second differences over all real samples, divided by sqrt(6), estimates sigma; the
median ignores the few samples at force kinks. On noise-free data it returns the (small)
signal curvature instead of 0 (an upper bound, flagged ``coarse``). Quantised values are
floored at step / sqrt(12) and upsampled streams are estimated at their native rate
(:mod:`treeinfer.data.noise_estimate`). The estimate only seeds the sampler's start and ``--kT
auto``; it is NOT the prior's centre.

The noise scale's prior (:func:`noise_scale_prior`, :class:`NoisePrior`): weakly informative
over decades. ``log sigma_x`` is flat from the sensor's resolution (``step / sqrt(12)`` of a
quantised recording, else 1 micron) up to the range of the recorded displacement, with a
steep tail below (sigma cannot be below the sensor's resolution) and a soft one above. A
clean recording (sigma settles at the model error, ~0.1 mm) and a noisy one (mm) fit with the
same prior and no flags; the "box" of the sigma column that samplers, start searches and the
straggler check see is this prior's flat part, so a posterior cannot leave it unless sigma is
below the sensor's resolution or above everything it recorded.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from ..data.noise_estimate import MIN_NOISE_SAMPLES, NoiseEstimate, estimate_white_noise
from ..data.trajectories import Observations, Trajectory, stack_trajectories
from ..errors import ConfigError

__all__ = [
    "DEFAULT_STUDENT_T_DF",
    "KINDS",
    "MIN_NOISE_SAMPLES",
    "NOISE_FLAGS",
    "NOISE_KINDS",
    "SIGMA_PRIOR_SCALE",
    "RESOLUTION_FLOOR",
    "NoiseEstimate",
    "NoisePrior",
    "as_observations",
    "check_df",
    "check_kind",
    "check_sigma",
    "estimate_displacement_noise",
    "log_sigma_prior",
    "noise_distribution",
    "noise_scale_prior",
    "residual_log_prob",
    "standard_quantile",
]

KINDS = ("boltzmann", "gaussian", "student_t", "ar1")  # every likelihood choice
NOISE_KINDS = ("gaussian", "student_t", "ar1")  # the generative ones (have a noise model)
# Prior on the AR(1) component's lag-1 correlation: logit(rho) ~ Normal(LOC, SCALE),
# centred on rho = 0.9 (a slow error at 10-20 ms sampling) and broad (95%: rho in 0.1-0.999).
RHO_PRIOR_LOC = math.log(0.9 / 0.1)
RHO_PRIOR_SCALE = 2.0
DEFAULT_STUDENT_T_DF = 4.0
# Scale of calibrate's (SBC's) proper prior Normal(log centre, scale) on log sigma_x
# (:func:`log_sigma_prior`, which SBC draws data sets from); inference uses the flat-over-decades
# :class:`NoisePrior` instead.
SIGMA_PRIOR_SCALE = 1.5
# the prior's lower end when the data show no quantisation step: 1 micron, below any pull rig's
# displacement sensor (encoders, motion capture, cable potentiometers: 10 micron - 1 mm)
RESOLUTION_FLOOR = 1e-6


# --------------------------------------------------------------------------- checks


def check_kind(kind: str) -> str:
    if kind not in KINDS:
        raise ConfigError(f"likelihood: expected one of {', '.join(KINDS)}, got {kind!r}")
    return kind


def check_df(df) -> float:
    try:
        df = float(df)
    except (TypeError, ValueError):
        raise ConfigError(f"student_t_df: expected a number > 2, got {df!r}") from None
    if not math.isfinite(df) or df <= 2.0:
        raise ConfigError(f"student_t_df: must be finite and > 2 (finite variance), got {df}")
    return df


# config fields and the command-line flags that set them (named together in errors)
NOISE_FLAGS = {
    "noise_displacement": "--noise-displacement",
    "noise_velocity": "--noise-velocity",
    "noise_force": "--noise-force",
}


def _field_label(field: str) -> tuple[str, str]:
    """(the name an error shows, the unit) for a noise setting's ``field``."""
    flag = NOISE_FLAGS.get(field)
    bare = field.lstrip("-").replace("-", "_")
    unit = "m/s" if "velocity" in bare else "N" if "force" in bare else "m"
    return (f"{field} ({flag})" if flag else field), unit


def check_sigma(
    value,
    field: str,
    data_range: float | None = None,
    *,
    allow_zero: bool = False,
    what: str = "the whole range of the recorded data",
) -> float:
    """A noise standard deviation: finite, > 0 (>= 0 with ``allow_zero``: "no noise") and (with
    ``data_range``) not above ``what`` (a sigma larger than everything the sensor recorded is a
    unit mistake).

    Raises :class:`ConfigError` naming ``field`` and, for a config field, its flag (e.g.
    ``noise_displacement (--noise-displacement)``), with the unit (m, m/s or N)."""
    label, unit = _field_label(field)
    units = {"m": "metres", "m/s": "m/s", "N": "newtons"}[unit]
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{label}: expected a positive number ({units}), got {value!r}") from None
    if not math.isfinite(v) or v < 0.0 or (v == 0.0 and not allow_zero):
        need = "a finite number >= 0" if allow_zero else "a finite positive number"
        raise ConfigError(f"{label}: must be {need} ({units}), got {v:g}")
    if data_range is not None and v > data_range:
        raise ConfigError(
            f"{label}: {v:g} {unit} is larger than {what} ({data_range:g} {unit}); check the "
            f"units ({units})"
        )
    return v


def as_observations(data) -> Observations:
    """Trajectories (sequence) or :class:`Observations` -> :class:`Observations`."""
    if isinstance(data, Observations):
        return data
    if isinstance(data, Trajectory):
        data = [data]
    if isinstance(data, Sequence) and data and all(isinstance(t, Trajectory) for t in data):
        return stack_trajectories(list(data))
    raise ConfigError("trajectories: expected a list of Trajectory or an Observations batch")


def displacement_range(obs: Observations) -> float:
    """max - min of the recorded displacement over real samples (m)."""
    x = np.asarray(obs.displacement, float)[np.asarray(obs.mask, bool)]
    return float(np.max(x) - np.min(x)) if x.size else 0.0


# --------------------------------------------------------------------------- estimation


def estimate_displacement_noise(data, min_samples: int = MIN_NOISE_SAMPLES) -> NoiseEstimate:
    """White displacement-noise std (m) from the high-frequency residual of the recordings.

    ``sigma = 1.4826 * median(|d2 - median(d2)|) / sqrt(6)`` with ``d2`` the second differences
    ``x[t+1] - 2 x[t] + x[t-1]`` of every trajectory at real (masked-in) samples only, computed
    at the stream's native rate when it was upsampled (repeated or interpolated samples) and
    floored at ``step / sqrt(12)`` when the values are quantised
    (:func:`treeinfer.data.noise_estimate.estimate_white_noise`; the estimate's ``notes`` say
    which).

    Args:
      data: list of :class:`Trajectory` or an :class:`Observations` batch.
      min_samples: fewest second differences accepted.

    Raises:
      ConfigError: fewer than ``min_samples`` second differences ("too short to estimate"), or
        mostly zero second differences with no quantisation grid (constant data); the message
        names ``--noise-displacement``.
    """
    obs = as_observations(data)
    return estimate_white_noise(
        obs.displacement,
        obs.mask,
        what="displacement",
        flag="--noise-displacement",
        unit="m",
        min_samples=min_samples,
    )


# --------------------------------------------------------------------------- the sigma prior


class NoisePrior(NamedTuple):
    """The weakly-informative prior of an inferred noise scale (m), over decades.

    ``log sigma`` is uniform on ``[log floor, log ceiling]`` with Gaussian tails of std
    ``lower_tail`` below and ``upper_tail`` above (a smoothed box, normalised):

    * ``floor``: the sensor's resolution: ``step / sqrt(12)`` when the recording is quantised on
      a grid of ``step`` (detected from the data), else :data:`RESOLUTION_FLOOR` (1 micron);
    * ``ceiling``: the range of the recorded displacement (a noise larger than everything the
      sensor recorded is not a noise);
    * ``lower_tail = 0.5 / sqrt(n)`` (n real samples): the likelihood of a noise-free record
      pulls ``log sigma`` down by n nats per e-fold, so a tail this steep holds sigma within a
      factor ``exp(0.25)`` of the floor; a sigma below the sensor's resolution is not physical.
    * ``upper_tail = 1`` (a factor e): soft, the data always pull sigma below the range.

    Nothing in between is preferred: a clean recording (sigma at the model error, ~0.1 mm) and a
    noisy one (several mm) sit in the same flat part. ``rule`` says where the floor came from.
    """

    floor: float
    ceiling: float
    lower_tail: float
    upper_tail: float
    rule: str

    @property
    def log_bounds(self) -> tuple[float, float]:
        """``(log floor, log ceiling)``: the prior box of the ``log sigma`` column."""
        return math.log(self.floor), math.log(self.ceiling)

    def log_prob(self, log_sigma):
        """``log p(log sigma)`` (normalised; jnp, any shape)."""
        lo, hi = self.log_bounds
        s = jnp.asarray(log_sigma)
        below = jnp.maximum(lo - s, 0.0) / self.lower_tail
        above = jnp.maximum(s - hi, 0.0) / self.upper_tail
        norm = (hi - lo) + math.sqrt(math.pi / 2.0) * (self.lower_tail + self.upper_tail)
        return -0.5 * (below**2 + above**2) - math.log(norm)

    def describe(self, name: str = "sigma_x") -> str:
        return (
            f"log {name} flat from {self.floor * 1e3:.3g} mm ({self.rule}) to "
            f"{self.ceiling * 1e3:.3g} mm (the data's range)"
        )


def noise_scale_prior(data, estimate: NoiseEstimate | None = None, floor: float | None = None):
    """:class:`NoisePrior` for ``data`` (trajectories or :class:`Observations`).

    ``estimate``: the data's :func:`estimate_displacement_noise` (its quantisation ``step`` sets
    the floor); None: estimated here when possible. ``floor``: the sensor's resolution (m) if
    known (overrides both)."""
    obs = as_observations(data)
    ceiling = displacement_range(obs)
    if not ceiling > 0:
        raise ConfigError(
            "trajectories: the recorded displacement does not vary: no noise scale to infer"
        )
    if floor is not None:
        floor, rule = check_sigma(floor, "noise floor", ceiling), "given"
    else:
        if estimate is None:
            try:
                estimate = estimate_displacement_noise(obs)
            except ConfigError:
                estimate = None
        step = None if estimate is None else estimate.step
        if step is not None:
            floor, rule = (
                step / math.sqrt(12.0),
                f"quantisation step {step * 1e3:.3g} mm / sqrt(12)",
            )
        else:
            floor, rule = RESOLUTION_FLOOR, "resolution floor"
    floor = min(floor, ceiling / 100.0)  # at least two decades between the ends
    n = int(np.sum(np.asarray(obs.mask, bool)))
    return NoisePrior(floor, ceiling, 0.5 / math.sqrt(max(n, 1)), 1.0, rule)


# --------------------------------------------------------------------------- densities


def noise_distribution(kind: str, scale, df: float = DEFAULT_STUDENT_T_DF):
    """The zero-mean residual distribution of ``kind`` with ``scale`` (m) as numpyro object."""
    import numpyro.distributions as dist

    if kind == "gaussian":
        return dist.Normal(0.0, scale)
    if kind == "student_t":
        return dist.StudentT(df, 0.0, scale)
    raise ConfigError(f"noise model: expected one of {', '.join(NOISE_KINDS)}, got {kind!r}")


def residual_log_prob(residual, scale, kind: str = "gaussian", df: float = DEFAULT_STUDENT_T_DF):
    """Elementwise ``log p(residual)`` (nats) under the noise model; shapes broadcast."""
    return noise_distribution(kind, scale, df).log_prob(residual)


def standard_quantile(q: float, kind: str = "gaussian", df: float = DEFAULT_STUDENT_T_DF) -> float:
    """``q``-quantile of the unit-scale noise distribution (a Python float, from scipy)."""
    import scipy.stats

    if kind == "gaussian":
        return float(scipy.stats.norm.ppf(q))
    if kind == "student_t":
        return float(scipy.stats.t.ppf(q, df))
    raise ConfigError(f"noise model: expected one of {', '.join(NOISE_KINDS)}, got {kind!r}")


def ar1_white_log_prob(residual, mask, sigma_w, sigma_c, rho):
    """Exact log-density (nats) of residuals = white N(0, sigma_w) + AR(1) (sigma_c, rho).

    Args:
      residual: ``[N, B, T]`` m. mask: ``[B, T]`` bool (padding skipped: the filter predicts
        through it without an update). sigma_w, sigma_c: ``[N]`` m. rho: ``[N]`` in (-1, 1).

    Returns ``[N]``: sum over trajectories of ``sum_t log N(v_t; 0, S_t)`` with the Kalman
    innovations ``v_t`` and their variances ``S_t`` (prediction error decomposition). A
    hand-written scalar Kalman filter (a ``lax.scan`` over T) because no installed library offers
    a batched, masked one in JAX; the per-step densities are numpyro ``Normal``s, and the test
    checks the total against ``scipy.stats.multivariate_normal`` with the dense covariance.
    """
    import jax
    import numpyro.distributions as dist

    r = jnp.moveaxis(jnp.asarray(residual), -1, 0)  # [T, N, B]
    m_t = jnp.moveaxis(jnp.asarray(mask, bool), -1, 0)[:, None, :]  # [T, 1, B]
    sw2 = (jnp.asarray(sigma_w) ** 2)[:, None]
    sc2 = (jnp.asarray(sigma_c) ** 2)[:, None]
    rho = jnp.asarray(rho)[:, None]
    q = (1.0 - rho**2) * sc2

    def step(carry, x):
        mean, var, total = carry
        rt, mt = x
        mp, vp = rho * mean, rho**2 * var + q
        s = vp + sw2
        v = rt - mp
        lp = dist.Normal(0.0, jnp.sqrt(s)).log_prob(v)
        k = vp / s
        mean = jnp.where(mt, mp + k * v, mp)
        var = jnp.where(mt, (1.0 - k) * vp, vp)
        return (mean, var, total + jnp.where(mt, lp, 0.0)), None

    n, b = r.shape[1], r.shape[2]
    zero = jnp.zeros((n, b), r.dtype)
    # stationary start: predicting from (mean 0, var sc2) gives var rho^2 sc2 + q = sc2
    (_, _, total), _ = jax.lax.scan(step, (zero, zero + sc2, zero), (r, m_t))
    return jnp.sum(total, axis=-1)


def log_sigma_prior(center: float, scale: float = SIGMA_PRIOR_SCALE):
    """A proper prior on ``log sigma_x``: ``Normal(log center, scale)`` (numpyro). Used by
    ``calibrate`` (SBC draws sigma_x from it); inference uses :func:`noise_scale_prior`.

    Returns ``logp(log_sigma [N]) -> [N]``."""
    import numpyro.distributions as dist

    center = check_sigma(center, "noise prior centre")
    d = dist.Normal(math.log(center), float(scale))

    def logp(log_sigma):
        return d.log_prob(jnp.asarray(log_sigma))

    return logp
