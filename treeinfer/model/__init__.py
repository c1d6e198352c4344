"""The log-density: theta's parameterisation (gains), priors and the learned inequality prior
(NNSVGD's network), the Boltzmann and Gaussian likelihoods, noise models and the force-noise
term, the temperature rule, and gradient estimators (central differences).

May import: treeinfer.sim, treeinfer.data, treeinfer.tree, treeinfer.io, treeinfer.errors. Known
exception until it is split: force_noise's noise estimate calls
treeinfer.inference.mapfit (inside a function).

The public API is re-exported here name by name, imported lazily (on first use), so
importing one module of the package does not import the others (startup cost, and no
import order between them).

Submodules: boltzmann, force_noise, gains, gradients, inequality_net, likelihood, noise,
prior_terms, priors, temperature."""

_EXPORTS = {
    "ForceNoiseBasis": "force_noise",
    "ForceNoiseModel": "force_noise_model",
    "check_noise_force": "force_noise",
    "estimate_force_noise": "force_noise",
    "force_jacobian": "force_noise",
    "force_noise_basis": "force_noise",
    "force_noise_covariance": "force_noise",
    "mvn_log_prob": "force_noise",
    "point_variance": "force_noise",
    "predictive_draws": "force_noise",
    "reference_theta": "force_noise_reference",
    "resolve_noise_force": "force_noise",
    "gains_from_theta": "gains",
    "natural_units": "gains",
    "noise_columns": "gains",
    "noise_params_from_theta": "gains",
    "predictive_noise_kind": "gains",
    "theta_from_gains": "gains",
    "GRADIENT_METHODS": "gradients",
    "LogDensityFn": "gradients",
    "ValueAndGradFn": "gradients",
    "autodiff_value_and_grad": "gradients",
    "central_difference": "gradients",
    "central_difference_jacobian": "gradients",
    "combine": "gradients",
    "combined_value_and_grad": "gradients",
    "default_rel_step": "gradients",
    "finite_difference_jvp": "gradients",
    "jvp_combined_value_and_grad": "gradients",
    "jvp_value_and_grad": "gradients",
    "likelihood_value_and_grad": "gradients",
    "mask_nonfinite": "gradients",
    "InequalityNet": "inequality_net",
    "inequality_target": "inequality_net",
    "train_inequality_network": "inequality_net",
    "DEFAULT_KT": "boltzmann",
    "LikelihoodTerms": "likelihood",
    "boltzmann_log_likelihood": "boltzmann",
    "data_observations": "likelihood",
    "likelihood_terms": "likelihood",
    "log_likelihood_from_rollout": "boltzmann",
    "measurement_log_likelihood": "likelihood",
    "observation_data": "likelihood",
    "padded_rollout": "likelihood",
    "trajectory_loss": "boltzmann",
    "DEFAULT_STUDENT_T_DF": "noise",
    "KINDS": "noise",
    "MIN_NOISE_SAMPLES": "noise",
    "NOISE_FLAGS": "noise",
    "NOISE_KINDS": "noise",
    "NoiseEstimate": "noise",
    "NoisePrior": "noise",
    "RESOLUTION_FLOOR": "noise",
    "SIGMA_PRIOR_SCALE": "noise",
    "as_observations": "noise",
    "check_df": "noise",
    "check_kind": "noise",
    "check_sigma": "noise",
    "estimate_displacement_noise": "noise",
    "log_sigma_prior": "noise",
    "noise_distribution": "noise",
    "noise_scale_prior": "noise",
    "residual_log_prob": "noise",
    "standard_quantile": "noise",
    "box_prior": "prior_terms",
    "nn_inequality_prior": "prior_terms",
    "default_cache_dir": "priors",
    "inequality_prior": "priors",
    "load_or_train_inequality_network": "priors",
    "smoothed_box": "priors",
    "KTChoice": "temperature",
    "auto_kT": "temperature",
    "check_kT": "temperature",
    "signal_omega2": "temperature",
    "suggest_kT": "temperature",
}
_SUBMODULES = (
    "boltzmann",
    "force_noise",
    "gains",
    "gradients",
    "inequality_net",
    "likelihood",
    "noise",
    "prior_terms",
    "priors",
    "temperature",
)

__all__ = sorted(_EXPORTS)


from ..io.lazy import lazy_package  # noqa: E402 -- after the tables it reads

__getattr__, __dir__ = lazy_package(__name__, _EXPORTS, _SUBMODULES)
