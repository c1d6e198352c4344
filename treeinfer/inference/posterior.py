"""The posterior a user holds: draws in natural units, summaries, ArviZ, predictions, figures.

:func:`treeinfer.infer` returns a :class:`Posterior`; :func:`load_posterior` reads one back from a
run folder (``treeinfer infer --out RUN`` or ``treeinfer demo``), old folders included. Every
sampler ends in the same form: ``P`` equal-weight rows of ``theta`` (log-parameters), which are

* SVGD / NNSVGD: the final interacting particles;
* MCMC (MH, SGLD, SGHMC): every chain's post-warm-up draws, thinned, in a run folder (the
  summaries' draws); the chains' final states from a bare :func:`treeinfer.infer`;
* importance sampling (``--init importance``): a systematic resample of the PSIS-weighted draws
  (the weights themselves are not stored; their Pareto k_hat and ESS are).

So :meth:`Posterior.sample` resamples those rows (with replacement: ``n`` above ``P`` repeats
particles; a particle posterior has no more information than its ``P`` rows). R-hat and ESS
are computed for MCMC chains only: for particles they do not apply (no Markov chain; judge
SVGD by the plateau of the log density and the KSD), and :meth:`Posterior.diagnostics` and the
ArviZ attributes say so.

Jupyter, from a run folder to draws, an ArviZ summary with units and a pair plot with the prior
box (``treeinfer demo --out demo`` writes ``demo/run``)::

    import treeinfer
    posterior = treeinfer.load_posterior("demo/run")   # any run folder
    draws = posterior.sample(1000, rng=0)               # {"Kp[child]": 1000 values (N m/rad), ...}
    fig, axes = posterior.pair_plot(); posterior.summary()  # prior box and truth; units column
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import ConfigError, PosteriorError
from .posterior_io import LEVEL, PosteriorContext, context_from_problem  # noqa: F401 -- API


@dataclass(frozen=True, eq=False)
class Posterior:
    """A posterior over a tree's joint gains, for every sampler (see the module docstring).

    Four lines from a run folder to draws, a summary with units and a pair plot::

        import treeinfer
        posterior = treeinfer.load_posterior("demo/run")
        draws = posterior.sample(1000, rng=0)    # {"Kp[child]": [1000] N m/rad, ...}
        fig, axes = posterior.pair_plot(); posterior.summary()

    Attributes (as :func:`treeinfer.infer` always returned them):
      theta: [P, D] equal-weight rows in log-parameters (log Kp, log Kd, then noise columns).
      kp, kd: [P, R] in natural units (N m/rad, N m s/rad). log_density: [P] of the target.
      labels: theta's column names (``Kp[branch]`` ..., ``Kd[branch]`` ..., ``sigma_x`` ...).
      run: the sampler's :class:`~treeinfer.inference.samplers.RunResult` (None for a loaded run).
      settings: problem + sampler settings. context: :class:`PosteriorContext`.
    """

    theta: np.ndarray
    kp: np.ndarray
    kd: np.ndarray
    log_density: np.ndarray
    labels: tuple[str, ...]
    run: Any = None
    settings: dict = field(default_factory=dict)
    context: PosteriorContext | None = None

    # ---- what the rows are -------------------------------------------------------------------
    @property
    def valid(self) -> np.ndarray:
        """[P] particles with a finite log-density (their simulations were stable)."""
        return np.isfinite(self.log_density)

    @property
    def usable(self) -> np.ndarray:
        """[P] rows the summaries and draws use: finite log density and coordinates, and stable
        on the training data where that is known."""
        ok = self.valid & np.all(np.isfinite(np.asarray(self.theta, float)), axis=1)
        ctx = self.context
        if ctx is not None and ctx.stable is not None and len(ctx.stable) == len(ok):
            ok &= np.asarray(ctx.stable, bool)
        return ok

    @property
    def sampler(self) -> str:
        return str(self.settings.get("sampler", "unknown"))

    @property
    def method(self) -> str:
        """``"particles"`` (SVGD, NNSVGD), ``"mcmc"`` or ``"importance"``."""
        if self.sampler == "importance":
            return "importance"
        from .samplers import REGISTRY

        spec = REGISTRY.get(self.sampler)
        return "mcmc" if spec is not None and spec.family == "mcmc" else "particles"

    @property
    def units(self) -> dict[str, str]:
        """``{label: unit}`` of the natural-unit values."""
        from .posterior_io import unit_of

        return {lab: unit_of(lab) for lab in self.labels}

    def _rows(self, check_fit: bool = True) -> np.ndarray:
        """The usable rows of theta [N, D], after checking the run may be sampled from
        (``check_fit=False``: figures and ArviZ data, which show a failed run too)."""
        ctx = self.context or PosteriorContext()
        where = f"{ctx.path}: " if ctx.path is not None else ""
        if check_fit and ctx.status == "poor_fit" and not ctx.allow_poor_fit:
            why = "; ".join(ctx.reasons) or "see summary.json's 'fit'"
            raise PosteriorError(
                f"{where}this run failed its fit check (poor_fit: {why}); its draws do not explain "
                "the training data. Fix the run, or load it with "
                "treeinfer.load_posterior(path, allow_poor_fit=True) to use them anyway"
            )
        ok = self.usable
        if not ok.any():
            raise PosteriorError(
                f"{where}no usable particle: all {len(ok)} have a non-finite log density or an "
                "unstable simulation"
            )
        return np.asarray(self.theta, float)[ok]

    # ---- draws and summaries -----------------------------------------------------------------
    def sample_array(self, n: int, rng=None, log: bool = False) -> np.ndarray:
        """``[n, D]`` draws (columns: :attr:`labels`) in natural units (``log=True``: theta).

        ``rng``: a :class:`numpy.random.Generator` or a seed (None: fresh entropy). Draws are the
        usable equal-weight rows resampled with replacement (see the module docstring)."""
        from ..model.gains import natural_units

        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise ConfigError(f"n: must be an integer >= 1, got {n!r}")
        n = int(n)
        rows = self._rows()
        gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        picked = rows[gen.integers(0, len(rows), size=n)]
        return picked if log else natural_units(picked, self.labels)

    def sample(self, n: int, rng=None) -> dict[str, np.ndarray]:
        """``{label: [n] draws}`` in natural units (N m/rad, N m s/rad, m); the rows of
        :meth:`sample_array` by label."""
        x = self.sample_array(n, rng)
        return {lab: x[:, j] for j, lab in enumerate(self.labels)}

    def natural(self) -> np.ndarray:
        """``[N, D]`` the usable rows in natural units."""
        from ..model.gains import natural_units

        return natural_units(self._rows(), self.labels)

    @property
    def mean(self):
        """Posterior mean per label in natural units (a :class:`pandas.Series`; units in
        ``.attrs["units"]``); the number summary.json reports."""
        return self._series(self.natural().mean(axis=0), "mean")

    @property
    def std(self):
        """Posterior standard deviation per label in natural units (:class:`pandas.Series`)."""
        x = self.natural()
        return self._series(x.std(axis=0, ddof=1) if len(x) > 1 else np.zeros(x.shape[1]), "std")

    def interval(self, level: float = LEVEL):
        """Central ``level`` credible interval per label in natural units, a
        :class:`pandas.DataFrame` with columns ``lower``, ``upper`` (units in ``.attrs``): the
        interval of summary.json (per-parameter KDE in log space, mapped back; monotone)."""
        import pandas as pd

        from ..evaluation.bands import _check_level, predictive_interval
        from ..model.gains import natural_units

        _check_level(level)
        rows = self._rows()
        if len(rows) < 2:
            raise PosteriorError(f"interval: needs 2 usable particles, got {len(rows)}")
        # as summary.json's table (runs.folder.posterior_table): the KDE interval of log values
        lo, hi, _ = (np.asarray(a, float) for a in predictive_interval(rows, level))
        ends = natural_units(np.stack([lo, hi]), self.labels)  # monotone maps: ends map over
        df = pd.DataFrame({"lower": ends[0], "upper": ends[1]}, index=list(self.labels))
        df.attrs["units"] = self.units
        df.attrs["level"] = float(level)
        return df

    def _series(self, values, name: str):
        import pandas as pd

        s = pd.Series(np.asarray(values, float), index=list(self.labels), name=name)
        s.attrs["units"] = self.units
        return s

    def diagnostics(self) -> dict:
        """Convergence diagnostics where they mean something.

        MCMC: R-hat and bulk/tail ESS per label over every chain's post-warm-up draws (ArviZ).
        Particles (SVGD/NNSVGD): no R-hat/ESS (the particles are not Markov chains), the run's
        log-density plateau and KSD checks from summary.json when loaded. Importance: the
        weights' Pareto k_hat and effective sample size. ``note`` says which applies."""
        from .posterior_io import DIAGNOSTICS_NOTE, mcmc_chains

        out: dict[str, Any] = {"method": self.method, "note": DIAGNOSTICS_NOTE[self.method]}
        summary = (self.context.summary if self.context is not None else None) or {}
        if self.method == "mcmc":
            chains = mcmc_chains(self)
            if chains is None or chains[0].shape[1] < 4:
                out["note"] += " (too short a trace here to compute them)"
                return out
            from .posterior_io import rhat_ess

            out.update(rhat_ess(chains[0], self.labels))
        elif self.method == "importance":
            run = getattr(self.run, "settings", None) or summary.get("diagnostics") or {}
            out.update({k: run[k] for k in ("khat", "ess", "n_draws") if k in run})
        elif summary.get("diagnostics"):
            out["run"] = summary["diagnostics"]
        return out

    def summary(self, level: float = LEVEL):
        """ArviZ's summary (:func:`arviz.summary`) of :meth:`to_arviz` in natural units with a
        ``unit`` column; ``r_hat``/``ess`` columns for MCMC only (meaningless for particles)."""
        from .posterior_io import arviz_summary

        return arviz_summary(self, level)

    def to_arviz(self):
        """:class:`arviz.InferenceData`: group ``posterior`` in natural units (variables ``Kp``,
        ``Kd`` over ``joint``, noise scalars; ``units`` and the prior box in each variable's
        attributes), ``log_posterior`` (``theta`` over ``param``, log units), ``sample_stats``
        (``lp``). MCMC: one chain per sampler chain, post-warm-up; particles: one chain of
        ``P`` draws (attributes say R-hat/ESS do not apply)."""
        from .posterior_io import posterior_inference_data

        return posterior_inference_data(self)

    # ---- predictions and figures ---------------------------------------------------------------
    def predict(self, forces, grasp=None, *, level: float = LEVEL, extrapolate: bool = False):
        """Posterior predictive band of the grasp point's displacement under ``forces``.

        Args:
          forces: ``[T]`` or ``[B, T]`` N, sampled at the run's time step (``context.sim``).
          grasp: fraction (0, 1] along the grasped branch (default: where the training data were
            recorded), or ``(branch, fraction)`` naming the grasped branch.
          level: band mass. extrapolate: allow a peak force beyond
            :data:`treeinfer.evaluation.posterior_bands.FORCE_MARGIN` times the training data's
            largest.

        Returns a :class:`treeinfer.evaluation.posterior_bands.PredictiveBand` (``mean``, ``lower``,
        ``upper``, ``draws``, ``time``; ``.plot()``). Raises
        :class:`~treeinfer.errors.PosteriorError` for a grasp point or force outside what the run
        supports."""
        from ..evaluation.posterior_bands import predict_band

        return predict_band(self, forces, grasp, level=level, extrapolate=extrapolate)

    def pair_plot(self, truth=None, **options):
        """Pair plot in natural units on log axes: 1-D marginals on the diagonal, the prior box
        (dashed), the truth (red) when known (a simulation's ``true_params.json``, or ``truth``
        [G] natural units). ``options`` go to
        :func:`treeinfer.evaluation.posterior_plots.pair_plot`. Returns ``(fig, axes)``."""
        from .posterior_io import pair_plot_of

        return pair_plot_of(self, truth, **options)

    def plot_trace(self, **options):
        """Trace of the log density and of every parameter (natural units) over iterations:
        ``(fig, axes)`` from :func:`treeinfer.evaluation.posterior_plots.plot_trace`."""
        from .posterior_io import trace_plot_of

        return trace_plot_of(self, **options)

    def save_figures(self, folder, formats=("png",)) -> list:
        """Write ``pairs`` and (with a sampler trace) ``trace`` into ``folder`` in every format
        of ``formats`` (``png``, ``pdf``, ``svg``); returns the paths written."""
        from pathlib import Path

        from ..evaluation.plots import save_figure

        folder = Path(folder)
        fig, _ = self.pair_plot()
        written = save_figure(fig, folder / "pairs.png", formats=formats)
        has_trace = (self.context is not None and self.context.trace is not None) or getattr(
            self.run, "trace_positions", None
        ) is not None
        if has_trace:
            fig, _ = self.plot_trace()
            written += save_figure(fig, folder / "trace.png", formats=formats)
        return written

    def __repr__(self) -> str:
        ctx = self.context or PosteriorContext()
        where = f", run={str(ctx.path)!r}" if ctx.path is not None else ""
        status = f", status={ctx.status!r}" if ctx.status else ""
        return (
            f"Posterior({self.method}: {int(self.usable.sum())} of {len(self.theta)} rows usable, "
            f"sampler={self.sampler!r}, labels={list(self.labels)}{status}{where})"
        )


__all__ = ["Posterior", "PosteriorContext", "context_from_problem"]
