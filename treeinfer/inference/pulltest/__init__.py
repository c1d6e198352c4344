"""Static tree pulling tests (winch cable at a height and angle, inclinometers on the stem):
the chain model with angle observations, its posterior over the joint stiffnesses (NUTS), the
predictive band, and a cantilever-beam baseline.

May import: treeinfer.sim, treeinfer.tree, treeinfer.data, treeinfer.io, treeinfer.errors
(the layers below inference), and treeinfer.inference.static.

Submodules: model (the chain and its tilts), creep (a standard linear solid per joint: the
viscoelastic chain), residuals (AR(1) residuals in continuous time, the lag-1 check),
gain (a slowly varying gain error per channel: model error that grows with the tilt),
softening (a softening root plate, and the chain with any of its series elements),
posterior (likelihood, NUTS, bands), beam (the least-squares baselines: a beam on a root-plate
spring, and one spring per inclinometer)."""

_EXPORTS = {
    "BeamFit": "beam",
    "beam_design": "beam",
    "beam_predict": "beam",
    "fit_beam": "beam",
    "fit_springs": "beam",
    "springs_predict": "beam",
    "CREEP_RATIO_PRIOR": "creep",
    "CREEP_TAU_PRIOR": "creep",
    "LAG_RATIO_PRIOR": "creep",
    "LAG_TAU_PRIOR": "creep",
    "SLOW_TAU_PRIOR": "creep",
    "lagged_creep_tilts": "creep",
    "creep_states": "creep",
    "creep_tilts": "creep",
    "LAG1_LIMIT": "residuals",
    "TAU_AR_PRIOR": "residuals",
    "lag1_autocorrelation": "residuals",
    "ou_white_innovations": "residuals",
    "ou_white_log_prob": "residuals",
    "GAIN_SD_PRIOR": "gain",
    "GAIN_TAU_PRIOR": "gain",
    "gain_forecast": "gain",
    "gain_ou_innovations": "gain",
    "gain_ou_log_prob": "gain",
    "SOFT_TILT_PRIOR": "softening",
    "chain_tilts": "softening",
    "softening_angle": "softening",
    "DENSITY": "model",
    "KP_PRIOR": "model",
    "PullModel": "model",
    "chain_tree": "model",
    "model_response": "model",
    "model_tilts": "model",
    "pull_model": "model",
    "NOISE_MODELS": "posterior",
    "NOISE_PRIOR": "posterior",
    "PullPosterior": "posterior",
    "fit_pull_test": "posterior",
    "initial_stiffness": "posterior",
    "predictive_band": "posterior",
    "residual_check": "posterior",
}
_SUBMODULES = ("beam", "creep", "gain", "model", "posterior", "residuals", "softening")

__all__ = sorted(_EXPORTS)


from ...io.lazy import lazy_package  # noqa: E402 -- after the tables it reads

__getattr__, __dir__ = lazy_package(__name__, _EXPORTS, _SUBMODULES)
