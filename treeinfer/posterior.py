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
from typing import Any, NamedTuple

import numpy as np

from .errors import PosteriorError

LEVEL = 0.95


class PosteriorContext(NamedTuple):
    """What a posterior knows about the run that produced it (None where unknown).

    tree, sim, model: the tree, its simulator at the data's time step, and the
      :class:`treeinfer.static.Model` (None: the paper's dynamic model of [log Kp, log Kd]).
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
    """The context of a posterior sampled on ``problem`` (a :class:`treeinfer.inference.Problem`);
    ``run``: the sampler's :class:`treeinfer.samplers.RunResult` (its trace)."""
    obs = problem.obs
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
      run: the sampler's :class:`~treeinfer.samplers.RunResult` (None for a loaded run).
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
        from .gains import natural_units
        from .inference import check_count

        n = check_count(n, "n")
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
        from .gains import natural_units

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

        from .bands import _check_level
        from .runs.folder import posterior_table

        _check_level(level)
        rows = self._rows()
        if len(rows) < 2:
            raise PosteriorError(f"interval: needs 2 usable particles, got {len(rows)}")
        table = posterior_table(rows, self.labels, level=level)
        df = pd.DataFrame(
            {
                "lower": [table[lab]["lower"] for lab in self.labels],
                "upper": [table[lab]["upper"] for lab in self.labels],
            },
            index=list(self.labels),
        )
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
            :data:`treeinfer.predictive.FORCE_MARGIN` times the training data's largest.

        Returns a :class:`treeinfer.predictive.PredictiveBand` (``mean``, ``lower``, ``upper``,
        ``draws``, ``time``; ``.plot()``). Raises :class:`~treeinfer.errors.PosteriorError` for
        a grasp point or force outside what the run supports."""
        from .predictive import predict_band

        return predict_band(self, forces, grasp, level=level, extrapolate=extrapolate)

    def pair_plot(self, truth=None, **options):
        """Pair plot in natural units on log axes: 1-D marginals on the diagonal, the prior box
        (dashed), the truth (red) when known (a simulation's ``true_params.json``, or ``truth``
        [G] natural units). ``options`` go to :func:`treeinfer.plot_posterior.pair_plot`.
        Returns ``(fig, axes)``."""
        from .posterior_io import pair_plot_of

        return pair_plot_of(self, truth, **options)

    def plot_trace(self, **options):
        """Trace of the log density and of every parameter (natural units) over iterations:
        ``(fig, axes)`` from :func:`treeinfer.plot_posterior.plot_trace`."""
        from .posterior_io import trace_plot_of

        return trace_plot_of(self, **options)

    def __repr__(self) -> str:
        ctx = self.context or PosteriorContext()
        where = f", run={str(ctx.path)!r}" if ctx.path is not None else ""
        status = f", status={ctx.status!r}" if ctx.status else ""
        return (
            f"Posterior({self.method}: {int(self.usable.sum())} of {len(self.theta)} rows usable, "
            f"sampler={self.sampler!r}, labels={list(self.labels)}{status}{where})"
        )


def load_posterior(
    path, *, allow_poor_fit: bool = False, allow_modified: bool = False, cache=None
) -> Posterior:
    """The :class:`Posterior` of a run folder (``treeinfer infer --out RUN``, ``demo/run``).

    Checks the folder's checksums (``allow_modified`` to accept edited files, noted in
    ``context.summary``), refuses an interrupted run (``RUN.partial``: resume it first), and
    keeps a ``poor_fit`` run loadable for inspection (figures, :meth:`Posterior.diagnostics`)
    while :meth:`Posterior.sample` and friends refuse it unless ``allow_poor_fit``. Folders
    written before posterior.nc held natural units load the same (from trace.npz)."""
    from .posterior_io import load_run_posterior

    return load_run_posterior(path, allow_poor_fit, allow_modified, cache)


__all__ = ["Posterior", "PosteriorContext", "context_from_problem", "load_posterior"]
