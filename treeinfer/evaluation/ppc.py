"""The fit verdict after inference: posterior predictive checks on the training data.

A run is judged by how its posterior predictive distribution (simulations of the posterior's
draws plus the inferred noise model) matches the data it was fitted to, never by where a noise
parameter falls in a box:

* **coverage** of the ``level`` (95%) predictive band: the share of training points outside
  it against the expected ``1 - level``. Too many outside, beyond what the sample's size and
  autocorrelation explain, is the only ``poor_fit`` of a generative run (exit 4): the bands the
  run reports do not hold its own data. Too few outside (bands wider than needed) is noted only.
* **standardised residuals**: the residual of each pull (data minus predictive mean) whitened
  by the Cholesky factor of its full predictive covariance (the draws' spread, the white noise
  sigma_x^2 I, and the errors-in-variables force-noise covariance or the AR(1) covariance where
  the model has one). These are the one-step prediction errors, in time order, i.i.d. standard
  normal under the model. Their mean (bias), standard deviation (noise under- or over-stated)
  and tails (share beyond 4: outliers, use ``--likelihood student_t``) give warnings.
* **autocorrelation** of the standardised residuals: the lag-1 correlation and a Ljung-Box
  statistic ``Q = n (n + 2) sum_k r_k^2 / (n - k)`` over lags 1..10 summed over pulls
  (``chi2`` with ``pulls x 10`` degrees of freedom under white residuals). Strongly
  autocorrelated residuals (lag-1 above :data:`ACF_WARN` and ``p < 1e-3``) mean the model
  misses something slow (unmodelled dynamics, drift, force noise left out): the warning
  "model misfit: residuals autocorrelated", not ``poor_fit`` unless coverage fails too. Ljung-Box
  by hand because statsmodels (which has ``acorr_ljungbox``) is not a treeinfer dependency;
  the formula is three lines and tested against a direct evaluation.

The Boltzmann likelihood (``--likelihood boltzmann``) has no noise model: its width is set by
the temperature kT, not by a noise, so the coverage of its band is not a calibration check and
never gives ``poor_fit``. What it can check: the share of the displacement's variance the
posterior-mean simulation explains (``explained_variance``; below :data:`EXPLAINED_POOR`: the
model does not explain the data, ``poor_fit``), and the residuals' autocorrelation against the
data's own high-frequency noise estimate (structure beyond noise: the warning above). With a
noise level (``--kT auto`` or ``--noise-displacement``) the coverage is reported as a warning.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

OUTSIDE_WARN, OUTSIDE_POOR = 2.0, 4.0  # share outside / (1 - level), e.g. 10% and 20% at 95%
COVERAGE_SE = 3.0  # ... and this many binomial standard errors (effective n) above 1 - level
SCALE_WARN = 2.0  # std of the standardised residuals above this (or below its inverse)
MEAN_WARN = 0.5  # |mean| of the standardised residuals above this (and 4 standard errors)
TAIL_Z, TAIL_SHARE = 4.0, 0.01  # share of |z| > 4 above 1% (a normal gives 6e-5)
ACF_WARN = 0.3  # lag-1 autocorrelation of the standardised residuals above this ...
LJUNG_BOX_P = 1e-3  # ... with a Ljung-Box p-value below this
LJUNG_BOX_LAGS = 10
EXPLAINED_WARN, EXPLAINED_POOR = 0.9, 0.5  # Boltzmann: share of variance explained
# relative jitter on the covariance diagonal before the Cholesky factor (the draws' covariance
# has rank < P and the force-noise one is low-rank: the white noise keeps it positive definite,
# the jitter only guards float rounding)
_JITTER = 1e-10


class PPCStats(NamedTuple):
    """Posterior predictive statistics of the training fit (see the module docstring).

    n: points. fraction_outside: share outside the band (None: unknown). z_mean, z_std,
    tail_share: of the standardised residuals. lag1: their pooled lag-1 autocorrelation.
    ljung_box, ljung_box_dof, ljung_box_p: the statistic, its degrees of freedom and p-value.
    n_effective: ``n (1 - lag1) / (1 + lag1)`` (lag1 clipped at 0), for standard errors.
    """

    n: int
    fraction_outside: float | None
    z_mean: float
    z_std: float
    tail_share: float
    lag1: float
    ljung_box: float
    ljung_box_dof: int
    ljung_box_p: float
    n_effective: float

    def as_dict(self) -> dict:
        return {k: (None if v is None else float(v)) for k, v in self._asdict().items()}


def _autocorr(z: np.ndarray, lags: int) -> np.ndarray:
    """Sample autocorrelations r_1..r_lags of one series (mean removed, biased estimator, as
    Box and Jenkins and Ljung-Box use)."""
    z = z - z.mean()
    den = float(z @ z)
    if den <= 0 or z.size <= lags:
        return np.zeros(lags)
    return np.array([float(z[k:] @ z[:-k]) / den for k in range(1, lags + 1)])


def ppc_stats(
    standardised: Sequence[np.ndarray],
    fraction_outside: float | None = None,
    lags: int = LJUNG_BOX_LAGS,
) -> PPCStats:
    """:class:`PPCStats` of standardised residuals, one 1-D array per pull (time order)."""
    from scipy.stats import chi2

    series = [np.asarray(z, float) for z in standardised if np.size(z) > lags + 1]
    allz = np.concatenate(series) if series else np.zeros(0)
    n = int(allz.size)
    if n == 0:
        nan = float("nan")
        return PPCStats(0, fraction_outside, nan, nan, nan, nan, nan, 0, nan, 0.0)
    q = num = den = 0.0
    for z in series:
        m = z.size
        r = _autocorr(z, lags)
        q += m * (m + 2) * float(np.sum(r**2 / (m - np.arange(1, lags + 1))))
        zc = z - z.mean()
        num += float(zc[1:] @ zc[:-1])
        den += float(zc @ zc)
    lag1 = num / den if den > 0 else 0.0
    dof = lags * len(series)
    rho = max(lag1, 0.0)
    return PPCStats(
        n,
        fraction_outside,
        float(allz.mean()),
        float(allz.std()),
        float(np.mean(np.abs(allz) > TAIL_Z)),
        float(lag1),
        float(q),
        int(dof),
        float(chi2.sf(q, dof)) if dof else float("nan"),
        float(max(1.0, n * (1.0 - rho) / (1.0 + rho))),
    )


def standardised_residuals(
    recorded,
    draws,
    mask=None,
    noise_variance=None,
    extra_covariance=None,
    valid=None,
) -> list[np.ndarray]:
    """One-step standardised residuals of each pull under its predictive distribution.

    Args:
      recorded: ``[B, T]`` data (m). draws: ``[P, B, T]`` simulations of the posterior draws.
      mask: ``[B, T]`` real samples. valid: ``[P]`` draws to use (stable).
      noise_variance: white noise variance (m^2): scalar or ``[P]`` (averaged over draws).
      extra_covariance: ``[B, T, T]`` (m^2) covariance the noise model adds beyond the white
        part (force noise, AR(1)), or None.

    Returns: per pull, ``L^-1 (x - mean)`` over its real samples, ``L`` the Cholesky factor of
    ``cov_p(draws) + noise_variance I + extra`` (``scipy.linalg.cholesky``)."""
    from scipy.linalg import cholesky, solve_triangular

    x = np.atleast_2d(np.asarray(recorded, float))
    tau = np.asarray(draws, float)
    if tau.ndim == 2:
        tau = tau[None]
    m = np.ones(x.shape, bool) if mask is None else np.asarray(mask, bool)
    if valid is not None:
        tau = tau[np.asarray(valid, bool)]
    tau = tau[np.all(np.isfinite(tau.reshape(len(tau), -1)), axis=1)]
    nv = 0.0 if noise_variance is None else float(np.mean(np.asarray(noise_variance, float)))
    out = []
    for b in range(x.shape[0]):
        idx = np.flatnonzero(m[b] & np.isfinite(x[b]))
        if idx.size < 2 or len(tau) == 0:
            continue
        tb = tau[:, b, idx]
        r = x[b, idx] - tb.mean(axis=0)
        cov = np.cov(tb, rowvar=False, ddof=1) if len(tb) > 1 else np.zeros((idx.size,) * 2)
        cov = np.atleast_2d(cov) + nv * np.eye(idx.size)
        if extra_covariance is not None:
            cov = cov + np.asarray(extra_covariance[b], float)[np.ix_(idx, idx)]
        scale = max(float(np.max(np.diag(cov))), 1e-300)
        cov = cov + _JITTER * scale * np.eye(idx.size)
        chol = cholesky(cov, lower=True)
        out.append(solve_triangular(chol, r, lower=True))
    return out


def ppc_findings(
    stats: PPCStats, level: float = 0.95, noise_model: bool = True
) -> tuple[list[str], list[str], dict]:
    """``(poor, warn, measures)`` from :class:`PPCStats` (module docstring). ``noise_model``
    False (Boltzmann): coverage is reported as a warning at most, never ``poor_fit``."""
    poor: list[str] = []
    warn: list[str] = []
    meas = {"ppc": stats.as_dict()}
    expected = 1.0 - level
    f = stats.fraction_outside
    if f is not None and math.isfinite(f):
        meas["fraction_outside"] = float(f)
        se = math.sqrt(expected * (1 - expected) / max(stats.n_effective, 1.0))
        significant = f > expected + COVERAGE_SE * se
        msg = (
            f"{f:.1%} of training points lie outside the {level:.0%} predictive band "
            f"(about {expected:.0%} expected)"
        )
        if f > OUTSIDE_POOR * expected and (significant or stats.n == 0):
            if noise_model:
                poor.append(msg + ": the bands do not hold the data they were fitted to")
            else:
                warn.append(
                    msg + ": the Boltzmann band's width is set by kT, not by a noise model; "
                    "use --likelihood gaussian for calibrated bands"
                )
        elif f > OUTSIDE_WARN * expected and (significant or stats.n == 0):
            warn.append(msg)
    if stats.n == 0:
        return poor, warn, meas
    if stats.lag1 > ACF_WARN and stats.ljung_box_p < LJUNG_BOX_P:
        warn.append(
            f"model misfit: residuals autocorrelated (lag-1 correlation {stats.lag1:.2f} of "
            f"the standardised residuals, Ljung-Box p = {stats.ljung_box_p:.2g}): the model "
            "misses something slow (unmodelled dynamics, drift, force noise: try --noise-force "
            "auto or --likelihood ar1)"
        )
    if noise_model:
        se_mean = 1.0 / math.sqrt(stats.n_effective)
        if abs(stats.z_mean) > MEAN_WARN and abs(stats.z_mean) > 4 * se_mean:
            side = "above" if stats.z_mean > 0 else "below"
            warn.append(
                f"the data lie systematically {side} the predictive mean (standardised "
                f"residuals average {stats.z_mean:+.2f}, 0 expected)"
            )
        if stats.z_std > SCALE_WARN or stats.z_std < 1.0 / SCALE_WARN:
            warn.append(
                f"standardised residuals have std {stats.z_std:.2f} (1 expected): the noise "
                f"model {'understates' if stats.z_std > 1 else 'overstates'} the scatter"
            )
        if stats.tail_share > TAIL_SHARE:
            warn.append(
                f"{stats.tail_share:.1%} of standardised residuals lie beyond {TAIL_Z:g} (a "
                "normal gives 0.006%): outliers; --likelihood student_t tolerates them"
            )
    return poor, warn, meas


ALIGN_MAX_SECONDS = 1.0  # shifts tried between the recording and the fit, each way
ALIGN_MIN_SAMPLES, ALIGN_MIN_SECONDS = 3, 0.03  # a shift below both is no finding
ALIGN_GAIN = 0.7  # the shifted fit's residual RMS below this share of the unshifted one's


def best_alignment(recorded, mean, mask=None, dt: float = 1.0) -> tuple[int, float]:
    """``(k, ratio)``: the shift ``k`` (samples; > 0: the recording comes later than the fit)
    minimising the pooled RMS of ``recorded[t] - mean[t - k]`` over the overlapping real
    samples, and that RMS over the unshifted one. A fit cannot absorb a clock offset between
    the force and the displacement stream (it simulates the displacement from the recorded
    force), so a recording that a shifted fit matches far better has its streams misaligned."""
    x = np.atleast_2d(np.asarray(recorded, float))
    mu = np.atleast_2d(np.asarray(mean, float))
    m = np.ones(x.shape, bool) if mask is None else np.atleast_2d(np.asarray(mask, bool))
    m = m & np.isfinite(x) & np.isfinite(mu)
    max_k = int(min(x.shape[1] // 4, round(ALIGN_MAX_SECONDS / dt))) if dt > 0 else 0

    def rms(k: int) -> float:
        num = cnt = 0.0
        for b in range(x.shape[0]):
            if k >= 0:
                a, c, w = x[b, k:], mu[b, : x.shape[1] - k], m[b, k:] & m[b, : x.shape[1] - k]
            else:
                a, c, w = x[b, :k], mu[b, -k:], m[b, :k] & m[b, -k:]
            r = (a - c)[w]
            num += float(r @ r)
            cnt += r.size
        return math.sqrt(num / cnt) if cnt else float("inf")

    base = rms(0)
    if not math.isfinite(base) or base <= 0 or max_k < 1:
        return 0, 1.0
    best_k, best = 0, base
    for k in range(-max_k, max_k + 1):
        v = rms(k)
        if v < best:
            best_k, best = k, v
    return best_k, best / base


def alignment_findings(recorded, mean, mask=None, dt: float = 1.0) -> tuple[list[str], dict]:
    """A warning when the recording matches the fit shifted in time much better (streams
    misaligned: a logger's lag, or time stamps of one stream offset), with the measure."""
    k, ratio = best_alignment(recorded, mean, mask, dt)
    meas = {"alignment_shift_s": k * dt, "alignment_rms_ratio": ratio}
    if abs(k) <= ALIGN_MIN_SAMPLES or abs(k) * dt <= ALIGN_MIN_SECONDS or ratio >= ALIGN_GAIN:
        return [], meas
    side = "later" if k > 0 else "earlier"
    return [
        f"streams misaligned: the recorded displacement matches the fit {abs(k) * dt:.3g} s "
        f"({abs(k)} samples) {side} with {1 - ratio:.0%} less residual: the displacement "
        "and force streams' clocks are probably offset (a logger's lag); align them and "
        "infer again"
    ], meas


def explained_variance(residuals, recorded, mask=None) -> float | None:
    """``1 - sum r^2 / sum (x - mean x)^2`` per pull, pooled (None without variation)."""
    r = np.asarray(residuals, float)
    x = np.asarray(recorded, float)
    m = np.ones(x.shape, bool) if mask is None else np.asarray(mask, bool)
    m = m & np.isfinite(r) & np.isfinite(x)
    ss_res = ss_tot = 0.0
    for b in range(x.shape[0]):
        xb, rb = x[b][m[b]], r[b][m[b]]
        if xb.size < 2:
            continue
        ss_res += float(rb @ rb)
        ss_tot += float(((xb - xb.mean()) ** 2).sum())
    return None if ss_tot <= 0 else 1.0 - ss_res / ss_tot
