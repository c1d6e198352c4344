"""Convergence diagnostics and ArviZ export for sampler output on plain arrays.

* MCMC-type samplers (Metropolis-Hastings, SGLD, SGHMC) run ``P`` independent
  particles; each particle is treated as one chain, so ArviZ's rank-normalised
  split R-hat and bulk/tail ESS (Vehtari et al. 2021) apply directly.
* SVGD / NNSVGD particles interact and are not Markov chains; R-hat/ESS do not
  apply. Their diagnostics are the log-density plateau and the kernel
  bandwidth.

Thresholds (all overridable in :func:`convergence_warnings`):
R-hat > 1.05 (looser than Vehtari et al.'s 1.01, which needs longer chains than
simulator-based runs usually afford; 1.1 is the classical Gelman-Rubin cut);
bulk or tail ESS below 100 per chain (Vehtari et al. 2021: total ESS at least
100 x number of chains); SVGD mean log-density still rising by more than 1%
over the last 10% of iterations; bandwidth collapsed to its floor; more than
10% of particles with an unstable (non-finite) simulation.

Beyond those (issue 11): :func:`find_stragglers` flags stuck particles (log density far
below the bulk, or far outside the prior box) with counts and warnings, and
:func:`reinit_stragglers` / :class:`ReinitStragglers` / :func:`drop_stragglers` are the
remedies; :func:`kernel_stein_discrepancy` (IMQ kernel, standardised particles) and
:func:`moment_change` measure SVGD convergence, :class:`ConvergenceCriterion` stops a run
early; :func:`mcmc_draws` / :func:`mcmc_summary` summarise MCMC runs from the post-warm-up
trace of all chains; :func:`prior_edge_mass` warns when posterior mass piles up at a box edge.

ArviZ is imported lazily (it is slow to import and prints a FutureWarning
about its coming 1.0 refactor, which we silence).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ._io import atomic_save
from .errors import ConfigError

__all__ = [
    "ConvergenceCriterion",
    "ReinitStragglers",
    "StragglerReport",
    "chi2_gap",
    "convergence_warnings",
    "drop_stragglers",
    "find_stragglers",
    "kernel_stein_discrepancy",
    "mcmc_diagnostics",
    "mcmc_draws",
    "mcmc_summary",
    "moment_change",
    "prior_edge_mass",
    "reinit_stragglers",
    "save_inference_data",
    "straggler_mask",
    "svgd_diagnostics",
    "to_inference_data",
]

RHAT_MAX = 1.05
MIN_ESS_PER_CHAIN = 100.0
MAX_REL_RISE = 0.01
MAX_UNSTABLE_FRACTION = 0.1
WINDOW = 0.1  # last 10% of iterations
MAX_KSD_FALL = 0.1  # KSD still falling by more than 10% over the window: not converged


def _arviz():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        import arviz

    return arviz


def _labels(labels: Sequence[str] | None, d: int) -> list[str]:
    names = [f"theta[{i}]" for i in range(d)] if labels is None else [str(x) for x in labels]
    if len(names) != d:
        raise ConfigError(f"labels: expected {d} parameter names, got {len(names)}")
    if len(set(names)) != d:
        raise ConfigError(f"labels: names must be unique, got {names}")
    return names


# --------------------------------------------------------------------------- ArviZ export


def to_inference_data(
    samples,
    labels: Sequence[str] | None = None,
    *,
    log_density=None,
    sampler: str | None = None,
    attrs: dict | None = None,
):
    """Wrap sampler output in an :class:`arviz.InferenceData`.

    Args:
      samples: either an MCMC trace ``[n_iter, P, D]`` (each particle is one
        chain: ``chain = P``, ``draw = n_iter``), or final particles ``[P, D]``
        (SVGD / NNSVGD: stored as ONE chain whose ``draw`` axis holds the ``P``
        particles; they are draws from the approximation, not a Markov chain,
        so do not read R-hat/ESS off it).
      labels: ``D`` parameter names (e.g. ``"Kp[branch1]"``); any string works,
        they are coordinates of the ``param`` dimension.
      log_density: optional ``[n_iter, P]`` (trace) or ``[P]`` (particles) log
        posterior density, stored as ``sample_stats.lp`` (ArviZ's name).
      sampler: name stored in the ``sampler`` attribute of the file and posterior.
      attrs: extra attributes (strings/numbers) for the whole InferenceData.

    Returns:
      ``InferenceData`` with group ``posterior`` (variable ``theta`` with dims
      ``(chain, draw, param)``) and, with ``log_density``, ``sample_stats``.
    """
    az = _arviz()
    x = np.asarray(samples, dtype=float)
    if x.ndim == 3:
        theta = np.swapaxes(x, 0, 1)  # [P, n_iter, D]: chain = particle
        lp_shape = x.shape[:2]
    elif x.ndim == 2:
        theta = x[None]  # [1, P, D]: one "chain" of particle draws
        lp_shape = x.shape[:1]
    else:
        raise ConfigError(
            f"samples: expected [n_iter, P, D] trace or [P, D] particles, got shape {x.shape}"
        )
    names = _labels(labels, x.shape[-1])
    stats = None
    if log_density is not None:
        lp = np.asarray(log_density, dtype=float)
        if lp.shape != lp_shape:
            raise ConfigError(
                f"log_density: expected shape {lp_shape} to match samples, got {lp.shape}"
            )
        stats = {"lp": np.swapaxes(lp, 0, 1) if lp.ndim == 2 else lp[None]}
    all_attrs = dict(attrs or {})
    if sampler is not None:
        all_attrs["sampler"] = str(sampler)
    idata = az.from_dict(
        posterior={"theta": theta},
        sample_stats=stats,
        dims={"theta": ["param"]},
        coords={"param": names},
        attrs=all_attrs or None,
    )
    for group in idata.groups():
        idata[group].attrs.update(all_attrs)
    return idata


def save_inference_data(idata, path) -> None:
    """Write ``idata`` to NetCDF (``netCDF4`` engine) atomically; read back with ``arviz.from_netcdf``."""
    with atomic_save(path) as tmp:
        idata.to_netcdf(str(tmp), engine="netcdf4")


# --------------------------------------------------------------------------- MCMC


def mcmc_diagnostics(
    trace,
    labels: Sequence[str] | None = None,
    *,
    burn_in: float = 0.5,
    log_density=None,
) -> dict:
    """R-hat and bulk/tail ESS per parameter, each particle one chain.

    Args:
      trace: ``[n_iter, P, D]`` positions of ``P`` independent chains.
      labels: ``D`` parameter names.
      burn_in: fraction of the first iterations discarded (0.5 = first half,
        the Gelman et al. convention).
      log_density: optional ``[n_iter, P]``; chains whose log density is
        non-finite at the last iteration (stuck in an unstable region) are
        counted as unstable.

    Chains with any non-finite position after burn-in are left out of all
    statistics and counted in ``n_excluded_chains``.

    Returns:
      ``{"parameters": {label: {"rhat", "ess_bulk", "ess_tail", "mean", "sd"}},
      "n_chains", "n_draws", "n_burn_in", "n_excluded_chains", "n_unstable",
      "rhat_max", "ess_bulk_min", "ess_tail_min", "ess_bulk_min_per_chain",
      "ess_tail_min_per_chain"}`` (plain floats/ints; NaN where undefined,
      e.g. constant chains).
    """
    az = _arviz()
    x = np.asarray(trace, dtype=float)
    if x.ndim != 3:
        raise ConfigError(f"trace: expected shape [n_iter, P, D], got {x.shape}")
    if not 0.0 <= burn_in < 1.0:
        raise ConfigError(f"burn_in: expected a fraction in [0, 1), got {burn_in}")
    n_iter, P, D = x.shape
    names = _labels(labels, D)
    k = math.floor(burn_in * n_iter)
    kept = x[k:]
    if kept.shape[0] < 4:
        raise ConfigError(
            f"trace: only {kept.shape[0]} iterations left after burn-in ({n_iter} recorded, "
            f"burn_in={burn_in}); need at least 4 for split R-hat"
        )
    good = np.all(np.isfinite(kept), axis=(0, 2))
    n_unstable = 0
    if log_density is not None:
        lp = np.asarray(log_density, dtype=float)
        if lp.shape != (n_iter, P):
            raise ConfigError(
                f"log_density: expected shape {(n_iter, P)} to match trace, got {lp.shape}"
            )
        n_unstable = int(np.sum(~np.isfinite(lp[-1])))
    out = {
        "n_chains": int(good.sum()),
        "n_draws": int(kept.shape[0]),
        "n_burn_in": k,
        "n_excluded_chains": int(P - good.sum()),
        "n_unstable": n_unstable,
        "n_particles": P,
    }
    params = {}
    if good.sum() >= 2:
        idata = to_inference_data(kept[:, good], names)
        with warnings.catch_warnings():
            warnings.simplefilter(
                "ignore", RuntimeWarning
            )  # constant chains: NaN, reported as such
            rhat = az.rhat(idata, var_names=["theta"])["theta"].values
            ess_b = az.ess(idata, var_names=["theta"], method="bulk")["theta"].values
            ess_t = az.ess(idata, var_names=["theta"], method="tail")["theta"].values
        flat = kept[:, good].reshape(-1, D)
        for i, name in enumerate(names):
            params[name] = {
                "rhat": float(rhat[i]),
                "ess_bulk": float(ess_b[i]),
                "ess_tail": float(ess_t[i]),
                "mean": float(flat[:, i].mean()),
                "sd": float(flat[:, i].std(ddof=1)),
            }
    out["parameters"] = params

    def agg(key, fn):
        v = np.array([p[key] for p in params.values()], dtype=float)
        return float(fn(v)) if v.size and not np.all(np.isnan(v)) else float("nan")

    out["rhat_max"] = agg("rhat", np.nanmax)
    out["ess_bulk_min"] = agg("ess_bulk", np.nanmin)
    out["ess_tail_min"] = agg("ess_tail", np.nanmin)
    n_ch = max(out["n_chains"], 1)
    out["ess_bulk_min_per_chain"] = out["ess_bulk_min"] / n_ch
    out["ess_tail_min_per_chain"] = out["ess_tail_min"] / n_ch
    return out


# --------------------------------------------------------------------------- SVGD


def svgd_diagnostics(
    log_density_trace,
    bandwidth_trace=None,
    *,
    window: float = WINDOW,
    bandwidth_floor: float | None = None,
    ksd_trace=None,
) -> dict:
    """Plateau and bandwidth checks for SVGD / NNSVGD runs.

    Args:
      log_density_trace: ``[n, P]`` log posterior density of each particle per
        recorded iteration; non-finite entries (unstable simulations) are left
        out of the mean and counted.
      bandwidth_trace: optional ``[n]`` RBF kernel bandwidth per iteration.
      window: trailing fraction of iterations examined (0.1 = last 10%).
      bandwidth_floor: the smallest bandwidth the run allows, if it clamps one.
      ksd_trace: optional ``[m]`` kernelized Stein discrepancy per iteration (SVGD info
        ``ksd``; its own length, e.g. without the initial state); adds ``ksd_final`` and ``ksd_rel_change`` over the window
        (``(k_end - k_start) / k_start``; clearly negative = still converging).

    Returns (plain floats/ints/bools):
      ``mean_log_density`` ``[start, end]`` of the window and ``rel_change``:
      ``(m_end - m_start) / max(|m_start|, 1)`` (denominator at least 1 nat, so
      a log density near 0 does not blow it up); positive = still rising.
      ``n_unstable_final`` / ``frac_unstable_final``: particles with a
      non-finite log density at the last iteration. With a bandwidth trace:
      ``bandwidth_initial``, ``bandwidth_final``, ``bandwidth_min``,
      ``bandwidth_rel_change`` over the window (``(b_end - b_start)/b_start``),
      ``bandwidth_ratio`` (final / initial) and ``bandwidth_collapsed``: at the
      floor (within 0.1%) if ``bandwidth_floor`` is given, else final below
      1e-3 x the largest bandwidth seen, or zero/non-finite.
    """
    ld = np.asarray(log_density_trace, dtype=float)
    if ld.ndim != 2 or ld.shape[0] < 2:
        raise ConfigError(f"log_density_trace: expected shape [n >= 2, P], got {ld.shape}")
    if not 0.0 < window <= 1.0:
        raise ConfigError(f"window: expected a fraction in (0, 1], got {window}")
    n, P = ld.shape
    start = n - 1 - max(1, math.ceil(window * n))
    start = max(start, 0)
    fin = np.isfinite(ld)
    with np.errstate(invalid="ignore"):
        mean = np.where(fin, ld, 0.0).sum(1) / fin.sum(1)
    m0, m1 = float(mean[start]), float(mean[-1])
    out = {
        "n_iter": n,
        "n_particles": P,
        "window_start": start,
        "mean_log_density_start": m0,
        "mean_log_density_final": m1,
        "rel_change": (m1 - m0) / max(abs(m0), 1.0)
        if np.isfinite(m0) and np.isfinite(m1)
        else float("nan"),
        "n_unstable_final": int(P - fin[-1].sum()),
        "frac_unstable_final": float(1.0 - fin[-1].mean()),
    }
    if bandwidth_trace is not None:
        bw = np.asarray(bandwidth_trace, dtype=float)
        if bw.shape != (n,):
            raise ConfigError(
                f"bandwidth_trace: expected shape ({n},) to match the log-density trace, got {bw.shape}"
            )
        b0, b1, bmax = float(bw[start]), float(bw[-1]), float(np.nanmax(bw))
        if bandwidth_floor is not None:
            collapsed = b1 <= bandwidth_floor * (1.0 + 1e-3)
        else:
            collapsed = not (np.isfinite(b1) and b1 > 1e-3 * bmax)
        out.update(
            bandwidth_initial=float(bw[0]),
            bandwidth_final=b1,
            bandwidth_min=float(np.nanmin(bw)),
            bandwidth_rel_change=(b1 - b0) / b0 if b0 != 0 else float("nan"),
            bandwidth_ratio=b1 / float(bw[0]) if bw[0] != 0 else float("nan"),
            bandwidth_collapsed=bool(collapsed),
        )
    if ksd_trace is not None:
        k = np.asarray(ksd_trace, dtype=float)
        if k.ndim != 1 or k.size < 2:
            raise ConfigError(f"ksd_trace: expected shape [m >= 2], got {k.shape}")
        ks = max(k.size - 1 - max(1, math.ceil(window * k.size)), 0)  # its own window
        k0, k1 = float(k[ks]), float(k[-1])
        out.update(ksd_final=k1, ksd_rel_change=(k1 - k0) / k0 if k0 > 0 else float("nan"))
    return out


# --------------------------------------------------------------------------- warnings


def convergence_warnings(
    diag: dict,
    kind: str,
    *,
    rhat_max: float = RHAT_MAX,
    min_ess_per_chain: float = MIN_ESS_PER_CHAIN,
    max_rel_rise: float = MAX_REL_RISE,
    max_unstable_fraction: float = MAX_UNSTABLE_FRACTION,
    max_ksd_fall: float = MAX_KSD_FALL,
) -> list[str]:
    """Human-readable warnings for a diagnostics dict; empty list = nothing to report.

    Args:
      diag: output of :func:`mcmc_diagnostics` (``kind="mcmc"``) or
        :func:`svgd_diagnostics` (``kind="svgd"``).
      rhat_max: warn when R-hat exceeds this (default 1.05).
      min_ess_per_chain: warn when bulk or tail ESS / number of chains is below this.
      max_rel_rise: warn when the SVGD mean log density rose by more than this
        fraction over the diagnostics window.
      max_unstable_fraction: warn when more than this share of particles is unstable.
      max_ksd_fall: warn when the SVGD KSD fell by more than this fraction over the window.
    """
    msgs: list[str] = []
    if kind == "mcmc":
        P = max(diag.get("n_particles", diag["n_chains"]), 1)
        if diag["n_excluded_chains"]:
            msgs.append(
                f"{diag['n_excluded_chains']} of {P} chains have non-finite positions and were left out of the diagnostics"
            )
        if diag.get("n_unstable", 0) > max_unstable_fraction * P:
            msgs.append(
                f"{diag['n_unstable']} of {P} chains end on an unstable simulation (non-finite log density); "
                "check the prior range against the simulator's stability limit"
            )
        if diag["n_chains"] < 2:
            msgs.append("fewer than 2 usable chains: R-hat cannot be computed")
        for name, p in diag["parameters"].items():
            if not np.isfinite(p["rhat"]):
                msgs.append(
                    f"{name}: R-hat undefined (chains constant; were any proposals accepted?)"
                )
            elif p["rhat"] > rhat_max:
                msgs.append(
                    f"{name}: R-hat {p['rhat']:.3f} > {rhat_max} - chains disagree; run longer or check for multiple modes"
                )
            n_ch = max(diag["n_chains"], 1)
            for which in ("bulk", "tail"):
                ess = p[f"ess_{which}"]
                if np.isfinite(ess) and ess / n_ch < min_ess_per_chain:
                    msgs.append(
                        f"{name}: {which} ESS {ess:.0f} ({ess / n_ch:.1f} per chain) < {min_ess_per_chain:g} per chain"
                        " - estimates are noisy; run longer"
                    )
    elif kind == "svgd":
        rc = diag["rel_change"]
        if np.isfinite(rc) and rc > max_rel_rise:
            msgs.append(
                f"mean log density still rising: +{100 * rc:.1f}% over the last iterations "
                f"(from iteration {diag['window_start']}) - not converged; run more iterations"
            )
        elif not np.isfinite(rc):
            msgs.append(
                "mean log density undefined near the end of the run (all particles unstable?)"
            )
        krc = diag.get("ksd_rel_change", float("nan"))
        if np.isfinite(krc) and krc < -max_ksd_fall:
            msgs.append(
                f"kernelized Stein discrepancy still falling: {100 * krc:.0f}% over the last "
                "iterations - particles still moving towards the posterior; run more iterations"
            )
        P = max(diag["n_particles"], 1)
        if diag["frac_unstable_final"] > max_unstable_fraction:
            msgs.append(
                f"{diag['n_unstable_final']} of {P} particles end on an unstable simulation "
                "(non-finite log density); check the prior range against the simulator's stability limit"
            )
        if diag.get("bandwidth_collapsed"):
            msgs.append(
                f"kernel bandwidth collapsed to {diag['bandwidth_final']:.3g} "
                f"(from {diag['bandwidth_initial']:.3g}): particles have merged and under-represent the posterior spread"
            )
    else:
        raise ConfigError(f"kind: expected 'mcmc' or 'svgd', got {kind!r}")
    return msgs


# --------------------------------------------------------------------------- stragglers
#
# A straggler is a particle stuck far from the bulk: its log density is far below the others'
# (robust z-score, median/MAD, so the stuck particles themselves do not inflate the scale) or it
# sits far outside the prior box. SVGD's repulsion and Adam's per-particle step size can leave
# such particles behind for the whole run; summaries over all particles then inherit them (the
# issue-11 case: 7 of 32 particles at log p ~ -296 with Kd 219-394 for a box [0.05, 10]).

Z_MAX = 5.0  # robust z below -Z_MAX: straggler (5 MADs: a Gaussian bulk has P(z < -5) ~ 3e-7)
FALSE_ALARM = 1e-3  # ... and further below the median than exact posterior draws go (see below)
MAX_BOX_EXCESS = 0.5  # ... or farther outside the box than this share of its width (5 x the
#                       default smoothed-box tail width, 0.1 of the width: prior density e^-12.5
#                       of the box's; mass merely piling at an edge is prior_edge_mass's job)
_MAD_TO_SD = 1.4826  # MAD of a normal distribution x 1.4826 = its standard deviation


class StragglerReport(NamedTuple):
    """Result of :func:`find_stragglers` (host numpy arrays and plain values).

    mask: [P] bool, particle is a straggler (any of the three reasons below).
    low_density: [P] bool, robust z-score of log p below ``-z_max`` and ``min_gap`` nats below
      the median. nonfinite: [P] bool, log p not finite (failed simulation).
    outside_box: [P] bool, farther than ``max_box_excess`` box widths outside the box in some
      coordinate.
    robust_z: [P] ``(log p - median) / (1.4826 MAD)`` (NaN for non-finite log p).
    box_excess: [P] largest distance outside the box over coordinates, in box widths (0 inside).
    n_stragglers, n_particles: counts. warnings: human-readable lines (empty: none found).
    """

    mask: np.ndarray
    low_density: np.ndarray
    nonfinite: np.ndarray
    outside_box: np.ndarray
    robust_z: np.ndarray
    box_excess: np.ndarray
    n_stragglers: int
    n_particles: int
    warnings: list


def chi2_gap(dim: int, n_particles: int, false_alarm: float = FALSE_ALARM) -> float:
    """Nats below the median log density that exact draws from a Gaussian posterior in ``dim``
    dimensions reach with probability ``false_alarm`` among ``n_particles``.

    Near a mode, ``2 (log p_max - log p) ~ chi2_dim``, i.e. ``Gamma(dim / 2)`` in nats: its
    exponential lower tail is much longer than a median/MAD z-score assumes (a 5-MAD cut alone
    flags 5-10% of runs of 32 exact draws at D = 4-12). Returns
    ``Gamma(dim/2).ppf(1 - false_alarm / n_particles) - Gamma(dim/2).median()``.
    """
    from scipy.stats import gamma

    k = dim / 2.0
    return float(gamma.ppf(1.0 - false_alarm / max(n_particles, 1), k) - gamma.median(k))


def straggler_mask(
    log_density,
    theta,
    lower,
    upper,
    *,
    z_max: float = Z_MAX,
    min_gap: float | None = None,
    max_box_excess: float = MAX_BOX_EXCESS,
):
    """Jittable core of :func:`find_stragglers`: ``(mask, low, nonfinite, outside, z, excess)``.

    Args:
      log_density: [P] log posterior density (nats). theta: [P, D] particles (theta units).
      lower, upper: [D] prior box (theta units).
      min_gap: nats below the median a low-density straggler must also be; None (default):
        :func:`chi2_gap` for these D and P.
    All outputs are [P] jax arrays. With fewer than 3 finite particles no particle is
    flagged for low density (a median of two says nothing about which one is stuck).
    """
    ld = jnp.asarray(log_density)
    x = jnp.asarray(theta)
    if min_gap is None:
        min_gap = chi2_gap(x.shape[-1], x.shape[0])
    lo, hi = jnp.asarray(lower, x.dtype), jnp.asarray(upper, x.dtype)
    fin = jnp.isfinite(ld)
    n_fin = jnp.sum(fin)
    # median / MAD over the finite entries (nanmedian ignores the NaNs we put in)
    ldn = jnp.where(fin, ld, jnp.nan)
    med = jnp.nanmedian(ldn)
    mad = jnp.nanmedian(jnp.abs(ldn - med))
    # scale floored at min_gap / z_max: a bulk of near-identical particles would give MAD ~ 0
    scale = jnp.maximum(_MAD_TO_SD * mad, min_gap / z_max)
    z = (ldn - med) / scale
    low = fin & (z < -z_max) & (ld < med - min_gap) & (n_fin >= 3)
    width = hi - lo
    excess = jnp.max(jnp.maximum(jnp.maximum(lo - x, x - hi), 0.0) / width, axis=-1)
    outside = excess > max_box_excess
    mask = low | ~fin | outside
    return mask, low, ~fin, outside, z, excess


def find_stragglers(
    log_density,
    theta,
    lower,
    upper,
    *,
    labels: Sequence[str] | None = None,
    z_max: float = Z_MAX,
    min_gap: float | None = None,
    max_box_excess: float = MAX_BOX_EXCESS,
) -> StragglerReport:
    """Find stuck / straggler particles among final particles.

    Args:
      log_density: [P] log posterior density of each particle (nats; -inf/NaN = failed).
      theta: [P, D] particles (theta units: natural log of Kp, Kd in treeinfer).
      lower, upper: [D] prior box in theta units.
      labels: D parameter names used in the warnings.
      z_max: flag log densities with robust z-score below ``-z_max`` (median/MAD) ...
      min_gap: ... that are also at least this many nats below the median (None:
        :func:`chi2_gap`, farther than exact draws from a Gaussian posterior go but in one
        of ~1000 runs).
      max_box_excess: flag particles farther outside the box than this share of its width.

    Returns:
      :class:`StragglerReport`; its ``warnings`` say how many, why, and the range of the
      stragglers' log density against the bulk's.
    """
    ld = np.asarray(log_density, dtype=float)
    x = np.asarray(theta, dtype=float)
    if ld.ndim != 1 or x.ndim != 2 or x.shape[0] != ld.shape[0]:
        raise ConfigError(
            f"find_stragglers: expected log_density [P] and theta [P, D], got {ld.shape} and "
            f"{x.shape}"
        )
    lo = np.broadcast_to(np.asarray(lower, dtype=float), x.shape[1:])
    hi = np.broadcast_to(np.asarray(upper, dtype=float), x.shape[1:])
    if not np.all(hi > lo):
        raise ConfigError(f"find_stragglers: need lower < upper, got {lo} and {hi}")
    for nm, v in (("z_max", z_max), ("min_gap", min_gap), ("max_box_excess", max_box_excess)):
        if v is not None and not (np.isfinite(v) and v >= 0):
            raise ConfigError(f"find_stragglers: {nm} must be a finite number >= 0, got {v!r}")
    names = _labels(labels, x.shape[1])
    out = straggler_mask(ld, x, lo, hi, z_max=z_max, min_gap=min_gap, max_box_excess=max_box_excess)
    mask, low, nonfin, outside, z, excess = (np.asarray(a) for a in out)
    P = ld.shape[0]
    msgs = []
    bulk = ~mask & np.isfinite(ld)
    if low.any():
        bulk_txt = f"{ld[bulk].min():.4g} ... {ld[bulk].max():.4g}" if bulk.any() else "none"
        msgs.append(
            f"{int(low.sum())} of {P} particles are stuck: log density {ld[low].min():.4g} ... "
            f"{ld[low].max():.4g} against {bulk_txt} for the rest (robust z < -{z_max:g}); "
            "summaries over all particles include them - re-initialise them during warm-up, "
            "drop them, or run longer"
        )
    if outside.any():
        d = np.argmax(np.maximum(np.maximum(lo - x, x - hi), 0.0) / (hi - lo), axis=1)
        worst = [names[i] for i in sorted(set(d[outside].tolist()))]
        msgs.append(
            f"{int(outside.sum())} of {P} particles lie more than {max_box_excess:g} box widths "
            f"outside the prior box (up to {excess[outside].max():.2f} widths; in "
            f"{', '.join(worst)}): the prior's smooth tails let them drift"
        )
    if nonfin.any():
        msgs.append(
            f"{int(nonfin.sum())} of {P} particles have a non-finite log density "
            "(unstable simulation)"
        )
    return StragglerReport(
        mask=mask,
        low_density=low,
        nonfinite=nonfin,
        outside_box=outside,
        robust_z=z,
        box_excess=excess,
        n_stragglers=int(mask.sum()),
        n_particles=P,
        warnings=msgs,
    )


def reinit_stragglers(rng_key, theta, mask, jitter: float = 0.1):
    """Move straggler particles next to randomly chosen good ones (pure, jittable).

    Each particle with ``mask`` True is replaced by a uniformly drawn particle with ``mask``
    False plus Gaussian jitter of ``jitter`` x the good particles' per-coordinate standard
    deviation (so the copies do not coincide with their source: SVGD's kernel would glue
    them). With no good particle, or none flagged, ``theta`` is returned unchanged.

    Args:
      rng_key: JAX key. theta: [P, D]. mask: [P] bool. jitter: >= 0, share of the bulk's spread.
    Returns:
      [P, D] new particles (same dtype).
    """
    x = jnp.asarray(theta)
    mask = jnp.asarray(mask, bool)
    good = ~mask
    n_good = jnp.sum(good)
    k_pick, k_noise = jax.random.split(rng_key)
    p = good / jnp.maximum(n_good, 1)
    idx = jax.random.choice(k_pick, x.shape[0], shape=(x.shape[0],), p=p)
    g = good[:, None]
    mean = jnp.sum(jnp.where(g, x, 0.0), 0) / jnp.maximum(n_good, 1)
    var = jnp.sum(jnp.where(g, jnp.square(x - mean), 0.0), 0) / jnp.maximum(n_good - 1, 1)
    noise = jax.random.normal(k_noise, x.shape, x.dtype) * jitter * jnp.sqrt(var)
    new = x[idx] + noise
    return jnp.where(mask[:, None] & (n_good > 0), new, x)


def drop_stragglers(theta, log_density, mask):
    """Particles without the stragglers: ``(theta [P', D], log_density [P'])`` as numpy."""
    keep = ~np.asarray(mask, bool)
    return np.asarray(theta)[keep], np.asarray(log_density)[keep]


class ReinitStragglers(NamedTuple):
    """Warm-up remedy for :func:`treeinfer.samplers.run`: after every chunk ending at or before
    iteration ``until``, stragglers (as :func:`straggler_mask` with these thresholds and the
    box ``lower``/``upper`` [D]) are moved next to good particles (:func:`reinit_stragglers`)
    and their sampler state is re-initialised; the others' state is untouched."""

    until: int
    lower: Any
    upper: Any
    z_max: float = Z_MAX
    min_gap: float | None = None
    max_box_excess: float = MAX_BOX_EXCESS
    jitter: float = 0.1


# --------------------------------------------------------------------------- Stein discrepancy
#
# Kernelized Stein discrepancy (Liu, Lee & Jordan 2016; Gorham & Mackey 2017) with the inverse
# multiquadric kernel k(x, y) = (c^2 + |x - y|^2)^beta, beta = -1/2, which (unlike the RBF)
# detects non-convergence in the tails (Gorham & Mackey, Theorem 8). Written here because no
# maintained JAX implementation exists (BlackJAX has none; its users ask for one); the closed
# form of the Stein kernel below is checked against autodiff of k in tests/test_convergence.py.
# Particles are standardised per coordinate first (x' = (x - m) / s, grad' = s * grad, the same
# log density in the new coordinates), so the kernel's unit length means "one posterior sd" in
# every coordinate whatever the parameter units.


def kernel_stein_discrepancy(
    theta, grad, *, c: float = 1.0, beta: float = -0.5, standardise: bool = True
):
    """IMQ kernelized Stein discrepancy of particles against the target whose score they carry.

    Args:
      theta: [P, D] particles. grad: [P, D] gradient of the target log density at them
        (uphill; exactly what SVGD states hold). Rows with a non-finite value are left out.
      c, beta: IMQ kernel ``(c^2 + r^2)^beta`` with ``c > 0`` and ``-1 < beta < 0``.
      standardise: measure in per-coordinate standardised units (default).
    Returns:
      scalar KSD = sqrt of the V-statistic ``mean_ij u_p(x_i, x_j)`` (>= 0, jax array, same
      units as a score times a standard deviation: dimensionless after standardising). For
      particles drawn from the target it is ``O(P^-1/2)``; it does not go to 0 for a fixed
      number of SVGD particles, so read its plateau, not its value.
    """
    x = jnp.asarray(theta)
    g = jnp.asarray(grad, x.dtype)
    ok = jnp.all(jnp.isfinite(x), -1) & jnp.all(jnp.isfinite(g), -1)
    w = ok.astype(x.dtype)
    n = jnp.maximum(jnp.sum(w), 1.0)
    x = jnp.where(ok[:, None], x, 0.0)
    g = jnp.where(ok[:, None], g, 0.0)
    if standardise:
        m = jnp.sum(x * w[:, None], 0) / n
        s = jnp.sqrt(jnp.sum(jnp.square(x - m) * w[:, None], 0) / jnp.maximum(n - 1, 1.0))
        s = jnp.where(s > 0, s, 1.0)
        x = (x - m) / s
        g = g * s
    d = x.shape[-1]
    r = x[:, None, :] - x[None, :, :]  # [P, P, D], r_ij = x_i - x_j
    r2 = jnp.sum(r * r, -1)
    q = c * c + r2
    gg = g @ g.T
    # u(x, y) = s_x.s_y k + s_x.grad_y k + s_y.grad_x k + tr(grad_x grad_y k)
    r_dot = jnp.einsum("ijd,jd->ij", r, g) - jnp.einsum("ijd,id->ij", r, g)  # r.(s_y - s_x)
    u = (
        gg * q**beta
        + 2 * beta * q ** (beta - 1) * r_dot
        - 2 * beta * d * q ** (beta - 1)
        - 4 * beta * (beta - 1) * r2 * q ** (beta - 2)
    )
    v = jnp.sum(u * w[:, None] * w[None, :]) / (n * n)
    return jnp.sqrt(jnp.maximum(v, 0.0))


def moment_change(previous, current) -> float:
    """Largest change of the particles' per-coordinate mean and spread between two snapshots.

    ``max_d max(|m1 - m0| / s1, |log(s1 / s0)|)`` over finite rows of ``previous`` and
    ``current`` ([P, D] each; the particles need not correspond): the mean shift in units
    of the current standard deviation, and the relative change of the spread. 0 = no change.
    """
    a, b = np.asarray(previous, float), np.asarray(current, float)
    a = a[np.all(np.isfinite(a), 1)]
    b = b[np.all(np.isfinite(b), 1)]
    if len(a) < 2 or len(b) < 2:
        return float("inf")
    m0, m1 = a.mean(0), b.mean(0)
    s0, s1 = a.std(0, ddof=1), b.std(0, ddof=1)
    tiny = 1e-12
    with np.errstate(divide="ignore", invalid="ignore"):
        shift = np.abs(m1 - m0) / np.maximum(s1, tiny)
        spread = np.abs(np.log(np.maximum(s1, tiny) / np.maximum(s0, tiny)))
    return float(np.max(np.maximum(shift, spread)))


class ConvergenceCriterion(NamedTuple):
    """Stop rule for :func:`treeinfer.samplers.run` (``stop_when=``), checked between chunks.

    Converged when, at a chunk end at or after ``min_iterations``: the particles' moments
    changed by less than ``moment_tol`` (:func:`moment_change`, in posterior sds) since the
    previous check, and, when the sampler records ``ksd`` (SVGD/NNSVGD), the mean KSD of the
    last ``window`` iterations differs from that of the ``window`` before by less than
    ``ksd_rtol`` (relative). Checks run at chunk ends, so ``chunk_size`` (default 100) sets how
    often; pick a smaller chunk (e.g. 25) for finer stopping.
    """

    min_iterations: int = 50
    moment_tol: float = 0.05
    ksd_rtol: float = 0.05
    window: int = 20

    def __call__(self, iteration: int, positions, previous_positions, diagnostics: dict):
        """``'converged: ...'`` (a reason) or None. positions, previous_positions: [P, D]."""
        if iteration < self.min_iterations or previous_positions is None:
            return None
        dm = moment_change(previous_positions, positions)
        if not dm < self.moment_tol:
            return None
        reason = f"converged at iteration {iteration}: moments changed by {dm:.3g} sd"
        ksd = diagnostics.get("ksd")
        if ksd is not None:
            k = np.asarray(ksd, float)
            w = self.window
            if k.size < 2 * w:
                return None
            k0, k1 = np.nanmean(k[-2 * w : -w]), np.nanmean(k[-w:])
            rel = abs(k1 - k0) / max(abs(k0), 1e-12)
            if not rel < self.ksd_rtol:
                return None
            reason += f", KSD {k1:.3g} changed by {100 * rel:.1f}% over {w} iterations"
        return reason


# --------------------------------------------------------------------------- MCMC draws


def mcmc_draws(trace_positions, warmup, thin: int = 1, log_density=None):
    """Posterior draws of an MCMC trace: all chains, warm-up discarded, thinned.

    Args:
      trace_positions: [S, C, D] recorded positions (S trace entries of C chains; treeinfer's
        ``RunResult.trace_positions``, entry 0 being the initial state on fresh runs).
      warmup: trace entries discarded at the start: an int (count) or a float in [0, 1)
        (share of S, e.g. 0.5 = the first half, as :func:`mcmc_diagnostics` ``burn_in``).
      thin: keep every ``thin``-th entry after the warm-up (>= 1).

      log_density: optional [S, C] log density of the trace entries.

    Returns:
      [N, D] draws, N = C x ceil((S - warmup) / thin) minus rows with a non-finite
      coordinate (chains stuck in an unstable region); ordered entry by entry, chains within.
      With ``log_density``: ``(draws [N, D], log_density [N])``.
    """
    x = np.asarray(trace_positions, dtype=float)
    if x.ndim != 3:
        raise ConfigError(f"trace_positions: expected shape [S, C, D], got {x.shape}")
    k = _warmup_count(warmup, x.shape[0])
    if isinstance(thin, bool) or not isinstance(thin, (int, np.integer)) or thin < 1:
        raise ConfigError(f"thin: expected a positive integer, got {thin!r}")
    kept = x[k::thin]
    if kept.shape[0] == 0:
        raise ConfigError(
            f"mcmc_draws: nothing left after a warm-up of {k} of {x.shape[0]} trace entries"
        )
    draws = kept.reshape(-1, x.shape[2])
    ok = np.all(np.isfinite(draws), axis=1)
    if log_density is None:
        return draws[ok]
    ld = np.asarray(log_density, dtype=float)
    if ld.shape != x.shape[:2]:
        raise ConfigError(f"log_density: expected shape {x.shape[:2]}, got {ld.shape}")
    return draws[ok], ld[k::thin].reshape(-1)[ok]


def _warmup_count(warmup, n: int) -> int:
    if isinstance(warmup, bool):
        raise ConfigError(f"warmup: expected a count or a fraction, got {warmup!r}")
    if isinstance(warmup, (int, np.integer)):
        if not 0 <= warmup < n:
            raise ConfigError(f"warmup: expected 0 <= warmup < {n} trace entries, got {warmup}")
        return int(warmup)
    w = float(warmup)
    if not 0.0 <= w < 1.0:
        raise ConfigError(f"warmup: a fraction must lie in [0, 1), got {warmup!r}")
    return math.floor(w * n)


def mcmc_summary(
    trace_positions,
    labels: Sequence[str] | None = None,
    *,
    warmup=0.5,
    thin: int = 1,
    log_density=None,
) -> dict:
    """Post-warm-up draws and their R-hat / ESS, for summary.json / particles.csv / evaluate.

    Returns ``{"draws": [N, D] (mcmc_draws), "diagnostics": mcmc_diagnostics(...) on the
    post-warm-up trace (unthinned: thinning only discards information for R-hat/ESS),
    "warmup": entries discarded, "thin": thin, "n_draws": N}``.
    """
    x = np.asarray(trace_positions, dtype=float)
    draws = mcmc_draws(x, warmup, thin)
    k = _warmup_count(warmup, x.shape[0]) if x.ndim == 3 else 0
    diag = mcmc_diagnostics(x, labels, burn_in=k / x.shape[0], log_density=log_density)
    return {
        "draws": draws,
        "diagnostics": diag,
        "warmup": k,
        "thin": int(thin),
        "n_draws": int(draws.shape[0]),
    }


# --------------------------------------------------------------------------- prior edge

MAX_EDGE_SHARE = 0.1  # warn when more than 10% of the particles sit beyond one edge of the box


def prior_edge_mass(
    theta, lower, upper, *, labels: Sequence[str] | None = None, max_share: float = MAX_EDGE_SHARE
) -> dict:
    """Posterior mass piling up at (or beyond) a prior-box edge.

    The smoothed box prior is flat inside ``[lower, upper]`` and has Gaussian tails outside;
    mass beyond an edge means the data push against the box: the interval is then set by the
    tail width (``--prior-tail``), not by the data.

    Args:
      theta: [P, D] particles or draws (theta units). lower, upper: [D] box.
      max_share: warn when the share beyond one edge of a parameter exceeds this.
    Returns:
      ``{"parameters": {label: {"below": share below lower, "above": share above upper}},
      "warnings": [...]}`` (shares over finite rows).
    """
    x = np.asarray(theta, dtype=float)
    if x.ndim != 2:
        raise ConfigError(f"prior_edge_mass: theta must be [P, D], got {x.shape}")
    x = x[np.all(np.isfinite(x), 1)]
    lo = np.broadcast_to(np.asarray(lower, float), x.shape[1:])
    hi = np.broadcast_to(np.asarray(upper, float), x.shape[1:])
    names = _labels(labels, x.shape[1])
    params, msgs = {}, []
    n = max(len(x), 1)
    for i, name in enumerate(names):
        below = float(np.sum(x[:, i] < lo[i]) / n)
        above = float(np.sum(x[:, i] > hi[i]) / n)
        params[name] = {"below": below, "above": above}
        for side, share, edge in (("lower", below, lo[i]), ("upper", above, hi[i])):
            if share > max_share:
                msgs.append(
                    f"{name}: {100 * share:.0f}% of the posterior lies beyond the {side} edge of "
                    f"the prior box ({math.exp(edge):.4g} in natural units): the data push "
                    "against the box, so this interval reflects the prior's tail width "
                    "(--prior-tail); widen the box if the value is physically possible"
                )
    return {"parameters": params, "warnings": msgs}
