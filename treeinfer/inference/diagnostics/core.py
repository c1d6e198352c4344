"""Core convergence diagnostics: ArviZ export, MCMC R-hat/ESS, SVGD plateau checks and the
warnings built from them (the package docstring gives the thresholds)."""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence

import numpy as np

from ...errors import ConfigError
from ...io.atomic import atomic_save
from . import arviz_compat

RHAT_MAX = 1.05
MIN_ESS_PER_CHAIN = 100.0
MAX_REL_RISE = 0.01
MAX_UNSTABLE_FRACTION = 0.1
WINDOW = 0.1  # last 10% of iterations
MAX_KSD_FALL = 0.1  # KSD still falling by more than 10% over the window: not converged


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
    """Wrap sampler output in ArviZ's container: an ``arviz.InferenceData`` on ArviZ 0.2x, an
    ``xarray.DataTree`` on 1.x (:mod:`treeinfer.inference.diagnostics.arviz_compat`; both read the
    same way).

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
      ``InferenceData`` / ``DataTree`` with group ``posterior`` (variable ``theta`` with dims
      ``(chain, draw, param)``) and, with ``log_density``, ``sample_stats``.
    """
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
    return arviz_compat.from_dict(
        {"theta": theta},
        sample_stats=stats,
        dims={"theta": ["param"]},
        coords={"param": names},
        attrs=all_attrs or None,
    )


def save_inference_data(idata, path) -> None:
    """Write ``idata`` to NetCDF (``netCDF4`` engine) atomically; read back with
    :func:`treeinfer.inference.diagnostics.arviz_compat.read_netcdf` (or ``arviz.from_netcdf``)."""
    with atomic_save(path) as tmp:
        arviz_compat.write_netcdf(idata, tmp)


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
            rhat = arviz_compat.rhat(idata, var_names=["theta"])["theta"].values
            ess_b = arviz_compat.ess(idata, "bulk", var_names=["theta"])["theta"].values
            ess_t = arviz_compat.ess(idata, "tail", var_names=["theta"])["theta"].values
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
        ``ksd``; its own length, e.g. without the initial state); adds ``ksd_final`` and
        ``ksd_rel_change`` over the window
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
                f"bandwidth_trace: expected shape ({n},) to match the log-density trace, "
                f"got {bw.shape}"
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
                f"{diag['n_excluded_chains']} of {P} chains have non-finite positions and were "
                "left out of the diagnostics"
            )
        if diag.get("n_unstable", 0) > max_unstable_fraction * P:
            msgs.append(
                f"{diag['n_unstable']} of {P} chains end on an unstable simulation "
                "(non-finite log density); "
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
                    f"{name}: R-hat {p['rhat']:.3f} > {rhat_max} - chains disagree; run longer "
                    "or check for multiple modes"
                )
            n_ch = max(diag["n_chains"], 1)
            for which in ("bulk", "tail"):
                ess = p[f"ess_{which}"]
                if np.isfinite(ess) and ess / n_ch < min_ess_per_chain:
                    msgs.append(
                        f"{name}: {which} ESS {ess:.0f} ({ess / n_ch:.1f} per chain) < "
                        f"{min_ess_per_chain:g} per chain"
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
                "(non-finite log density); check the prior range against the simulator's "
                "stability limit"
            )
        if diag.get("bandwidth_collapsed"):
            msgs.append(
                f"kernel bandwidth collapsed to {diag['bandwidth_final']:.3g} "
                f"(from {diag['bandwidth_initial']:.3g}): particles have merged and "
                "under-represent the posterior spread"
            )
    else:
        raise ConfigError(f"kind: expected 'mcmc' or 'svgd', got {kind!r}")
    return msgs
