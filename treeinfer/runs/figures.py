"""What a run folder shows of its posterior: ``posterior.nc`` in natural units and the figures in
``plots/`` (trace, pair plot, training bands), built through
:class:`treeinfer.inference.posterior.Posterior` so the files and the API agree."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from ..inference.posterior import PosteriorContext


def _posterior(posterior, problem, trace: dict, stable, truth=None):
    """``posterior`` (the run's, as summarised) with the run's context attached."""
    from ..inference.posterior import Posterior

    ctx = PosteriorContext(
        tree=problem.tree,
        sim=problem.sim,
        model=getattr(problem, "model", None),
        lower=np.asarray(problem.lower, float),
        upper=np.asarray(problem.upper, float),
        problem_settings=dict(problem.settings),
        stable=np.asarray(stable, bool),
        truth=None if truth is None else np.asarray(truth, float),
        trace=trace,
    )
    if not isinstance(posterior, Posterior):  # a stand-in with the same fields (tests)
        posterior = Posterior(
            posterior.theta,
            posterior.kp,
            posterior.kd,
            posterior.log_density,
            tuple(posterior.labels),
            getattr(posterior, "run", None),
            dict(getattr(posterior, "settings", {}) or {}),
        )
    return dataclasses.replace(posterior, context=ctx)


def training_force_max(problem) -> float:
    """N, the largest |force| of the problem's training data (masked steps left out)."""
    obs = problem.obs
    f = np.where(np.asarray(obs.mask, bool), np.abs(np.asarray(obs.force, float)), 0.0)
    return float(f.max()) if f.size else 0.0


def run_inference_data(posterior, problem, trace: dict, stable, summary: dict, attrs: dict):
    """The InferenceData written to ``posterior.nc``: natural units, the prior box, the
    likelihood and noise model as attributes (:func:`.posterior_io.build_inference_data`)."""
    from ..inference.posterior_io import mcmc_chains, posterior_inference_data, run_attrs

    post = _posterior(posterior, problem, trace, stable)
    extra = {**attrs, **run_attrs(problem.settings, summary)}
    idata = posterior_inference_data(post)
    if post.method == "mcmc" and mcmc_chains(post) is not None:
        extra["trace_iterations"] = ",".join(str(int(i)) for i in trace["iterations"])
    from ..inference.diagnostics.arviz_compat import group_names

    for group in group_names(idata):
        idata[group].attrs.update({k: v for k, v in extra.items() if v is not None})
    return idata


def write_run_figures(
    plots: Path,
    posterior,
    problem,
    trace: dict,
    stable,
    truth,
    fit: dict,
    names,
    sampler: str,
    bandwidth=None,
    formats=("png",),
) -> list[Path]:
    """``plots/trace``, ``plots/pairs``, ``plots/bands_train`` and, for a run with observation
    channels, ``plots/channels_train`` (``fit["channel_bands"]``) in every format of
    ``formats`` (``png``, ``pdf``, ``svg``); returns the files written."""
    from ..evaluation.plots import plot_band_grid, save_figure

    post = _posterior(posterior, problem, trace, stable, truth)
    written = []
    fig, _ = post.plot_trace(bandwidth=bandwidth, title=f"{sampler}: log density and parameters")
    written += save_figure(fig, plots / "trace.png", formats=formats)
    fig, _ = post.pair_plot()
    written += save_figure(fig, plots / "pairs.png", formats=formats)
    pred = fit.get("prediction")
    if pred is not None:
        obs = problem.obs
        rec = np.where(obs.mask, obs.displacement, np.nan)
        t = np.arange(obs.force.shape[1]) * float(obs.dt)
        fig, _ = plot_band_grid(
            t,
            pred.lower,
            pred.upper,
            pred.mean,
            rec,
            titles=list(names),
            suptitle="95% band of the simulated displacement vs the training recordings",
            reference_label="recording",
        )
        written += save_figure(fig, plots / "bands_train.png", formats=formats)
    if fit.get("channel_bands"):  # observation channels: their bands on the training data
        from ..evaluation.channel_bands import plot_channel_bands

        fig, _ = plot_channel_bands(fit["channel_bands"])
        written += save_figure(fig, plots / "channels_train.png", formats=formats)
    return written
