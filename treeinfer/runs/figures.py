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
    channels: bool = True,
) -> list[Path]:
    """``plots/trace``, ``plots/pairs``, ``plots/bands_train`` and, for a run with observation
    channels, ``plots/channels_train`` (``fit["channel_bands"]``; not with ``channels=False``)
    in every format of ``formats`` (``png``, ``pdf``, ``svg``); returns the files written."""
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
    if channels:
        written += _channel_figure(plots, fit, formats)
    return written


def _channel_figure(plots: Path, fit: dict, formats) -> list[Path]:
    if not fit.get("channel_bands"):
        return []
    # observation channels: their bands on the training data
    from ..evaluation.channel_bands import plot_channel_bands
    from ..evaluation.plots import save_figure

    fig, _ = plot_channel_bands(fit["channel_bands"])
    return save_figure(fig, plots / "channels_train.png", formats=formats)


class RunFigures:
    """The run's figures (:func:`write_run_figures`) drawn on a second thread
    (:class:`treeinfer.runs.background.Job`) into a scratch folder while the main thread
    computes the run's summary and verdict (XLA compiles and runs, which release Python's lock);
    :meth:`write` moves them into the run's ``plots/`` (about 3 CPU-s of matplotlib, two thirds
    of it the pair plot's layout, off the command's critical path on a 2-core CPU). The same
    files as drawing them in place; a drawing error is raised by :meth:`write`. The channels'
    figure (``fit["channel_bands"]``, made by the verdict) is drawn by :meth:`write`."""

    def __init__(self, posterior, problem, trace, stable, truth, fit, names, sampler,
                 bandwidth=None, formats=("png",)):  # fmt: skip
        import tempfile

        from .background import Job

        self._scratch = tempfile.TemporaryDirectory(prefix="treeinfer-plots-")
        self._formats = formats
        folder = Path(self._scratch.name)
        names, fit = list(names), dict(fit)
        self._job = Job(
            lambda: write_run_figures(
                folder, posterior, problem, trace, stable, truth, fit, names, sampler,
                bandwidth=bandwidth, formats=formats, channels=False,
            ),
            "run-figures",
        )  # fmt: skip

    def write(self, plots: Path, fit: dict) -> list[Path]:
        """The figures in ``plots`` (created); returns the files written."""
        import shutil

        try:
            drawn = self._job.result()
            plots.mkdir(parents=True, exist_ok=True)
            written = [Path(shutil.move(str(f), str(plots / f.name))) for f in drawn]
        finally:
            self._scratch.cleanup()
        return written + _channel_figure(plots, fit, self._formats)
