"""A posterior judged: predictions of every particle with their bands, metrics on plain arrays,
figures returning (fig, axes), and the fit checks after inference.

May import: treeinfer.inference and every layer below it.

The public API is re-exported here name by name, imported lazily (on first use), so
importing one module of the package does not import the others (startup cost, and no
import order between them).

Submodules: bands, checks, metrics, plots, posterior_bands, posterior_plots, ppc, predictive,
trace_plot."""

_EXPORTS = {
    "KDE1D": "bands",
    "PredictiveBands": "bands",
    "PredictiveInterval": "bands",
    "PredictiveNLL": "bands",
    "kde_1d": "bands",
    "noisy_predictive_interval": "bands",
    "noisy_predictive_nll": "bands",
    "posterior_predictive_draws": "bands",
    "predictive_bands": "bands",
    "predictive_interval": "bands",
    "Finding": "checks",
    "FitVerdict": "checks",
    "POOR_FIT_EXIT_CODE": "checks",
    "data_checks": "checks",
    "errors_of": "checks",
    "fit_checks": "checks",
    "fit_verdict_from_run": "checks",
    "format_findings": "checks",
    "grasp_reach": "checks",
    "lever_arm_compliance": "checks",
    "noise_from_kT": "checks",
    "preflight": "checks",
    "simulation_cost_check": "checks",
    "static_compliance": "checks",
    "TruthCheck": "metrics",
    "ci_width": "metrics",
    "fraction_outside": "metrics",
    "outside": "metrics",
    "posterior_nll": "metrics",
    "posterior_vs_truth": "metrics",
    "predictive_nll": "metrics",
    "summarize": "metrics",
    "plot_band_grid": "plots",
    "plot_trajectory_bands": "plots",
    "save_figure": "plots",
    "PredictiveBand": "posterior_bands",
    "predict_band": "posterior_bands",
    "metric_bars": "posterior_plots",
    "pair_plot": "posterior_plots",
    "PPCStats": "ppc",
    "explained_variance": "ppc",
    "ppc_findings": "ppc",
    "ppc_stats": "ppc",
    "standardised_residuals": "ppc",
    "Prediction": "predictive",
    "band_arrays": "predictive",
    "evaluate_trajectories": "predictive",
    "force_noise_for": "predictive",
    "kfold_splits": "predictive",
    "mean_metrics": "predictive",
    "noise_for": "predictive",
    "predict_run": "predictive",
    "rollout_loglik": "predictive",
    "write_evaluation": "predictive",
    "plot_trace": "trace_plot",
}
_SUBMODULES = (
    "_plot_common",
    "bands",
    "checks",
    "metrics",
    "plots",
    "posterior_bands",
    "posterior_plots",
    "ppc",
    "predictive",
    "trace_plot",
)

__all__ = sorted(_EXPORTS)


from ..io.lazy import lazy_package  # noqa: E402 -- after the tables it reads

__getattr__, __dir__ = lazy_package(__name__, _EXPORTS, _SUBMODULES)
