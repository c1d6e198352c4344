"""What :class:`treeinfer.inference.posterior.Posterior` knows about its run
(:class:`PosteriorContext`), its ArviZ data (natural units with units and the prior box as
attributes) and its figures (pair plot, trace). Below :mod:`treeinfer.inference.posterior`: it takes
the posterior as an argument.

ArviZ is reached only through :mod:`treeinfer.inference.diagnostics.arviz_compat` (ArviZ 0.2x and
1.x).
"""

from __future__ import annotations

import json
import math
from typing import Any, NamedTuple

import numpy as np

from ..errors import ConfigError, PosteriorError

UNITS = {
    "Kp": "N m/rad",
    "Kd": "N m s/rad",
    "sigma_x": "m",
    "sigma_c": "m",
    "rho": "",
    "sigma": "m or rad",  # an observation channel's noise (sigma[name]): its channel's SI unit
    "Kp_scale": "N m/rad",  # a taper tie's scale (treeinfer.inference.static.tied)
    "Kp_taper_ratio": "",  # a soft tie's Kp_j / (scale * taper_j)
}


DIAGNOSTICS_NOTE = {
    "mcmc": "R-hat and ESS over every chain's post-warm-up draws (rank-normalised split R-hat, "
    "ArviZ); R-hat below 1.05 and ESS above 100 per chain are the usual bars",
    "particles": "R-hat and ESS do not apply: SVGD/NNSVGD particles are one interacting set, not "
    "Markov chains (ArviZ would report draws = particles as one chain); judge convergence by the "
    "plateau of the log density and the kernel Stein discrepancy (summary.json 'diagnostics')",
    "importance": "R-hat and ESS of a trace do not apply: the rows are a systematic resample of "
    "PSIS-weighted importance draws; the weights' Pareto k_hat (below 0.7) and effective sample "
    "size judge them",
}


LEVEL = 0.95


class PosteriorContext(NamedTuple):
    """What a posterior knows about the run that produced it (None where unknown).

    tree, sim, model: the tree, its simulator at the data's time step, and the
      :class:`treeinfer.inference.static.Model` (None: the paper's dynamic model of [log Kp, log
      Kd]).
    lower, upper: [D] the prior box in theta (log) units; NaN for columns without a box.
    problem_settings: the problem's settings (likelihood, noise model, grasp fraction ...).
    stable: [P] particles whose training rollouts were stable. truth: [G] the true gains in
      natural units (a simulation's), G <= D. status / reasons: the run's fit verdict.
    path: the run folder. trace: ``positions [n, P, D]``, ``log_density [n, P]``,
      ``iterations [n]`` of the sampler. summary: summary.json. force_max: N, the largest
      |force| of the training data (predictions beyond :data:`FORCE_MARGIN` times it are refused).
    allow_poor_fit: sample from a run whose fit verdict is poor_fit anyway.
    """

    tree: Any = None
    sim: Any = None
    model: Any = None
    lower: np.ndarray | None = None
    upper: np.ndarray | None = None
    problem_settings: dict | None = None
    stable: np.ndarray | None = None
    truth: np.ndarray | None = None
    status: str | None = None
    reasons: tuple[str, ...] = ()
    path: Any = None
    trace: dict | None = None
    summary: dict | None = None
    force_max: float | None = None
    allow_poor_fit: bool = False


def context_from_problem(problem, run=None) -> PosteriorContext:
    """The context of a posterior sampled on ``problem`` (a
    :class:`treeinfer.inference.problem.Problem`); ``run``: the sampler's
    :class:`treeinfer.inference.samplers.RunResult` (its trace). A problem without observations
    (``obs`` None: a black-box target handed to the samplers) has no force range: ``force_max``
    None, predictions unguarded by it."""
    obs = problem.obs
    force = np.zeros(0)
    if obs is not None:
        force = np.where(np.asarray(obs.mask, bool), np.abs(np.asarray(obs.force, float)), 0.0)
    trace = None
    if run is not None and getattr(run, "trace_positions", None) is not None:
        trace = {
            "positions": np.asarray(run.trace_positions),
            "log_density": np.asarray(run.trace_logdensity),
            "iterations": np.asarray(run.trace_iterations),
        }
    return PosteriorContext(
        tree=problem.tree,
        sim=problem.sim,
        model=problem.model,
        lower=np.asarray(problem.lower, float),
        upper=np.asarray(problem.upper, float),
        problem_settings=dict(problem.settings),
        trace=trace,
        force_max=float(force.max()) if force.size else None,
    )


def unit_of(label: str) -> str:
    """The natural unit of a theta column label (``Kp[branch]`` -> ``N m/rad``)."""
    return UNITS.get(label.split("[")[0], "")


def _split(label: str) -> tuple[str, str | None]:
    """``"Kp[child]"`` -> ``("Kp", "child")``; ``"sigma_x"`` -> ``("sigma_x", None)``."""
    if label.endswith("]") and "[" in label:
        name, coord = label[:-1].split("[", 1)
        return name, coord
    return label, None


# ==== ArviZ, through the package's adapter (ArviZ 0.2x and 1.x) ===============================
def _arviz_from_dict(posterior, sample_stats, coords, dims, attrs, extra_groups):
    """InferenceData (0.2x) / DataTree (1.x) of ``posterior`` / ``sample_stats`` plus the
    ``extra_groups`` ``{name: (variables, coords, dims)}``."""
    from .diagnostics import arviz_compat

    idata = arviz_compat.from_dict(
        posterior, sample_stats=sample_stats, coords=coords, dims=dims, attrs=attrs
    )
    for name, (variables, g_coords, g_dims) in extra_groups.items():
        arviz_compat.add_group(idata, name, variables, coords=g_coords, dims=g_dims, attrs=attrs)
    return idata


def _arviz_summary(idata, kind: str, hdi_prob: float):
    """ArviZ's summary table (:func:`treeinfer.inference.diagnostics.arviz_compat.summary_table`),
    ArviZ's one-chain messages quiet (a particle set is one "chain" on purpose)."""
    import logging

    from .diagnostics import arviz_compat

    log = logging.getLogger("arviz")
    level = log.level
    log.setLevel(logging.ERROR)
    try:
        return arviz_compat.summary_table(idata, kind=kind, hdi_prob=hdi_prob)
    finally:
        log.setLevel(level)


def _arviz_rhat_ess(chains: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(r_hat, ess_bulk, ess_tail)`` per column of ``chains [C, S, D]``."""
    from .diagnostics import arviz_compat

    x = np.asarray(chains, dtype=float)
    r = arviz_compat.rhat(x)["x"].values
    eb = arviz_compat.ess(x, "bulk")["x"].values
    et = arviz_compat.ess(x, "tail")["x"].values
    return np.asarray(r, float), np.asarray(eb, float), np.asarray(et, float)


# ==== natural-unit InferenceData ==================================================================
def build_inference_data(
    chains, log_density, labels, lower=None, upper=None, *, method: str, sampler: str, attrs=None
):
    """InferenceData of ``chains [C, S, D]`` (theta, log units) with ``log_density [C, S]``.

    Groups: ``posterior`` in natural units (bracketed labels become one variable over a ``joint``
    dimension: ``Kp[child]`` is ``Kp`` at joint ``child``; each variable's attributes give
    ``units`` and the prior box ``prior_lower`` / ``prior_upper``), ``log_posterior`` (``theta``
    over ``param``, natural logs of the same values), ``sample_stats`` (``lp``). ``attrs``
    (strings and numbers) go on every group with ``method``, ``sampler`` and ``rhat_ess``."""
    from ..model.gains import natural_units

    x = np.asarray(chains, float)
    if x.ndim != 3 or x.shape[2] != len(labels):
        raise ConfigError(f"chains: expected [C, S, {len(labels)}], got shape {x.shape}")
    nat = natural_units(x.reshape(-1, x.shape[2]), labels).reshape(x.shape)
    lo = np.full(len(labels), np.nan) if lower is None else np.asarray(lower, float)
    hi = np.full(len(labels), np.nan) if upper is None else np.asarray(upper, float)
    box = natural_units(np.stack([lo, hi]), labels)
    groups: dict[str, list[int]] = {}
    coord_of: dict[str, list[str]] = {}
    for j, lab in enumerate(labels):
        name, coord = _split(lab)
        groups.setdefault(name, []).append(j)
        if coord is not None:
            coord_of.setdefault(name, []).append(coord)
    posterior, dims, coords, var_attrs = {}, {}, {}, {}
    for name, cols in groups.items():
        if name in coord_of:
            cs = coord_of[name]
            dim = "joint" if coords.get("joint", cs) == cs else f"{name}_joint"
            coords[dim], dims[name] = cs, [dim]
            posterior[name] = nat[:, :, cols]
        else:
            posterior[name] = nat[:, :, cols[0]]
        var_attrs[name] = {
            "units": unit_of(labels[cols[0]]),
            "prior_lower": [float(v) for v in box[0, cols]],
            "prior_upper": [float(v) for v in box[1, cols]],
        }
    all_attrs = {
        "method": method,
        "sampler": sampler,
        "rhat_ess": DIAGNOSTICS_NOTE[method],
        "parameters": "natural units (units attribute per variable); group log_posterior holds "
        "their natural logs (theta, the sampled coordinates)",
        **{k: v for k, v in (attrs or {}).items() if v is not None},
    }
    stats = None
    if log_density is not None:
        lp = np.asarray(log_density, float)
        if lp.shape != x.shape[:2]:
            raise ConfigError(f"log_density: expected shape {x.shape[:2]}, got {lp.shape}")
        stats = {"lp": lp}
    idata = _arviz_from_dict(
        posterior,
        stats,
        coords,
        dims,
        all_attrs,
        {"log_posterior": ({"theta": x}, {"param": list(labels)}, {"theta": ["param"]})},
    )
    for name, a in var_attrs.items():
        idata.posterior[name].attrs.update(a)
    idata.log_posterior["theta"].attrs["units"] = "natural log of each parameter's unit"
    from .diagnostics.arviz_compat import group_names

    for group in group_names(idata):
        idata[group].attrs.update(all_attrs)
    return idata


def run_attrs(problem_settings: dict | None, summary: dict | None = None) -> dict:
    """NetCDF attributes of a run: the likelihood, the noise model, the prior space, the fit."""
    s = problem_settings or {}
    out = {
        "likelihood": str(s.get("likelihood", "boltzmann")),
        "prior": f"smoothed box on {s.get('prior_space', 'log')} gains (prior_lower/prior_upper "
        f"per variable), edge width {s.get('prior_sigma', 'n/a')} of the box",
        "noise_model": json.dumps(
            {
                k: s[k]
                for k in (
                    "kT",
                    "noise_displacement",
                    "noise_sigma",
                    "noise_force",
                    "noise_velocity",
                    "kT_auto",
                )
                if k in s and s[k] is not None
            },
            sort_keys=True,
        ),
    }
    if summary and summary.get("status"):
        out["fit_status"] = str(summary["status"])
    return out


def mcmc_chains(post):
    """``(chains [C, S, D], lp [C, S])``: every MCMC chain after the run's warm-up, thinned as
    its summaries (``settings["mcmc_draws"]``; else the first half dropped), or None."""
    ctx = post.context
    trace = ctx.trace if ctx is not None else None
    if trace is None and post.run is not None:
        trace = {"positions": post.run.trace_positions, "log_density": post.run.trace_logdensity}
    if trace is None or len(np.asarray(trace["positions"])) < 2:
        return None
    pos, ld = np.asarray(trace["positions"], float), np.asarray(trace["log_density"], float)
    draws = post.settings.get("mcmc_draws") or {}
    warm = int(draws.get("warmup", math.floor(0.5 * len(pos))))
    thin = int(draws.get("thin", 1))
    return np.swapaxes(pos[warm::thin], 0, 1), np.swapaxes(ld[warm::thin], 0, 1)


def rhat_ess(chains: np.ndarray, labels) -> dict:
    """``{"r_hat": {label: v}, "ess_bulk": ..., "ess_tail": ...}`` in natural units."""
    from ..model.gains import natural_units

    nat = natural_units(chains.reshape(-1, chains.shape[2]), labels).reshape(chains.shape)
    r, eb, et = _arviz_rhat_ess(nat)
    return {
        key: {lab: float(v[j]) for j, lab in enumerate(labels)}
        for key, v in (("r_hat", r), ("ess_bulk", eb), ("ess_tail", et))
    }


def posterior_inference_data(post):
    """:meth:`Posterior.to_arviz`."""
    ctx = post.context or PosteriorContext()
    chains = mcmc_chains(post) if post.method == "mcmc" else None
    if chains is None:
        rows = post._rows(check_fit=False)  # a failed run's data can still be inspected
        ld = np.asarray(post.log_density, float)[post.usable]
        chains = (rows[None], ld[None])
    return build_inference_data(
        chains[0],
        chains[1],
        post.labels,
        ctx.lower,
        ctx.upper,
        method=post.method,
        sampler=post.sampler,
        attrs=run_attrs(ctx.problem_settings, ctx.summary),
    )


def arviz_summary(post, level: float = LEVEL):
    """:meth:`Posterior.summary`: ArviZ's table with a ``unit`` column."""
    idata = posterior_inference_data(post)
    df = _arviz_summary(idata, "all" if post.method == "mcmc" else "stats", level)
    df.insert(0, "unit", [unit_of(str(i)) for i in df.index])
    return df


# ==== figures =====================================================================================
def _title(post, n: int) -> str:
    what = {"mcmc": "post-warm-up MCMC draws", "importance": "importance-resampled particles"}
    return f"{post.sampler} posterior: {n} {what.get(post.method, 'particles')}"


def pair_plot_of(post, truth=None, **options):
    """:meth:`Posterior.pair_plot`."""
    from ..evaluation.posterior_plots import pair_plot
    from ..model.gains import natural_units

    ctx = post.context or PosteriorContext()
    nat = natural_units(post._rows(check_fit=False), post.labels)  # a failed run's too
    d = len(post.labels)
    tr = ctx.truth if truth is None else truth
    if tr is not None:
        tr = np.asarray(tr, float)
        if tr.ndim != 1 or len(tr) > d:
            raise ConfigError(f"truth: expected at most {d} values (natural units), got {tr.shape}")
        tr = np.concatenate([tr, np.full(d - len(tr), np.nan)])
    box = None
    if ctx.lower is not None and ctx.upper is not None:
        box = natural_units(np.stack([ctx.lower, ctx.upper]), post.labels)
    options.setdefault("title", _title(post, len(nat)))
    return pair_plot(
        nat,
        list(post.labels),
        tr,
        units=[unit_of(lab) for lab in post.labels],
        log_axes=[_split(lab)[0] not in ("rho", "Kp_taper_ratio") for lab in post.labels],
        prior_box=box,
        **options,
    )


def trace_plot_of(post, **options):
    """:meth:`Posterior.plot_trace`."""
    from ..evaluation.posterior_plots import plot_trace
    from ..model.gains import natural_units

    ctx = post.context or PosteriorContext()
    trace = ctx.trace
    if trace is None and post.run is not None:
        trace = {
            "positions": post.run.trace_positions,
            "log_density": post.run.trace_logdensity,
            "iterations": post.run.trace_iterations,
        }
    if trace is None:
        raise PosteriorError("plot_trace: this posterior has no sampler trace")
    pos = np.asarray(trace["positions"], float)
    nat = natural_units(pos.reshape(-1, pos.shape[2]), post.labels).reshape(pos.shape)
    warm = None
    if post.method == "mcmc" and len(pos) >= 2:
        draws = post.settings.get("mcmc_draws") or {}
        k = int(draws.get("warmup", math.floor(0.5 * len(pos))))
        warm = float(np.asarray(trace["iterations"])[k]) if k < len(pos) else None
    options.setdefault("title", f"{post.sampler}: trace of the log density and each parameter")
    return plot_trace(
        trace["log_density"],
        iterations=trace.get("iterations"),
        params=nat,
        labels=list(post.labels),
        units=[unit_of(lab) for lab in post.labels],
        warmup=warm,
        **options,
    )
