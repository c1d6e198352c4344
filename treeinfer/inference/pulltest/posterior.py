"""The posterior of a static pulling test: joint stiffnesses, optional creep and per-channel
noise, by NUTS.

Likelihood: each recorded tilt (rad, NaN = missing) is the model's tilt plus noise per
inclinometer, inferred with the stiffnesses:

    tilt_c(t) = model_c(F(.), t; Kp[, c, tau]) + e_c(t)

The model is the elastic chain (:func:`.model.model_tilts`) or, with ``creep=True``, the
viscoelastic one (:mod:`.creep`: a standard linear solid per joint, creep ratio ``c`` and relaxation
time ``tau`` per joint, LogUniform priors :data:`~.creep.CREEP_RATIO_PRIOR`,
:data:`~.creep.CREEP_TAU_PRIOR`); with ``lag=True`` as well, a fast lag element on the root joint
(ratio and time constant, :data:`~.creep.LAG_TAU_PRIOR`; the slow creep's relaxation time then
beyond it, :data:`~.creep.SLOW_TAU_PRIOR`: :func:`.creep.lagged_creep_tilts`); with ``soft=True``,
a softening root plate (:mod:`.softening`: ``theta_s`` with the LogUniform prior
:data:`~.softening.SOFT_TILT_PRIOR`). Priors ``log Kp_j ~
Uniform(log 1e3, log 1e8)`` (N m/rad; :data:`~.model.KP_PRIOR`). Noise ``"iid"``: ``e_c ~ Normal(0,
sigma_c)``, ``sigma_c ~ LogUniform(1e-6, 0.05)`` rad. ``"ar1"``: white noise (``sigma_w``) plus an
AR(1) component in continuous time (``sigma_a``, correlation time ``tau_ar`` with a bounded prior),
the exact likelihood of :func:`.residuals.ou_white_log_prob`; the band then uses the marginal sd
``sqrt(sigma_w^2 + sigma_a^2)`` (held-out points lie many correlation times from the fit).
``"ar1+gain"``: and a slowly varying gain error per channel, model error proportional to the
tilt (:mod:`.gain`: ``sigma_g``, ``tau_g``), in the band by its stationary marginal or its
forecast from the fitted part (``predictive_band(..., fit_tilt=)``). The force is
taken as given (errors in it are not modelled; :func:`treeinfer.data.pull_test.dequantised_force`
removes most of the load cell's 10 N rounding before a fit).

Why NUTS from numpyro and not treeinfer's start pipeline and samplers: those are built around
the displacement likelihood of :mod:`treeinfer.model.likelihood` (particles x profiles x time
rollouts, the grasp point's ``tau``) and do not take another likelihood without changing that
module; this problem is small (2 stiffnesses, up to 4 creep and 6 noise parameters, one
equilibrium solve per force sample with exact implicit gradients), exactly what NUTS does
best, and numpyro handles the bounded priors' transforms and the warm-up.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from ...errors import ConfigError
from .creep import (
    CREEP_RATIO_PRIOR,
    CREEP_TAU_PRIOR,
    LAG_RATIO_PRIOR,
    LAG_TAU_PRIOR,
    SLOW_TAU_PRIOR,
)
from .gain import GAIN_SD_PRIOR, GAIN_TAU_PRIOR, gain_ou_log_prob
from .model import KP_PRIOR, PullModel, model_tilts
from .residuals import TAU_AR_PRIOR, lag1_autocorrelation, ou_white_log_prob
from .softening import SOFT_TILT_PRIOR, chain_tilts

__all__ = [
    "NOISE_MODELS",
    "NOISE_PRIOR",
    "PullPosterior",
    "fit_pull_test",
    "initial_stiffness",
    "predictive_band",
    "residual_check",
]

NOISE_PRIOR = (1.0e-6, 0.05)  # rad: the LogUniform prior of each channel's noise sd
NOISE_DRAWS = 4  # noise samples per parameter draw in the predictive band
NOISE_MODELS = ("iid", "ar1", "ar1+gain")
DEFAULT_DT = 0.1  # s: the time step assumed when no time base is given (the .pul rate)


@dataclass(frozen=True)
class PullPosterior:
    """Posterior draws: ``kp`` [S, R] N m/rad (columns ``joints``), ``sigma`` [S, C] rad
    (columns ``channels``: each channel's marginal noise sd), ``noise_params`` the noise
    model's own draws (``ar1``: ``sigma_w``, ``sigma_a``, ``tau_ar`` s and ``rho`` the lag-1
    correlation at the median step, each [S, C]), ``creep_params`` (``creep=True``: ``ratio``
    and ``tau`` s, each [S, R]), ``lag_params`` (``lag=True``: the root's fast lag, ``ratio``
    and ``tau`` s, each [S], or [S, R] with a lag on every joint), ``soft_params``
    (``soft=True``: ``tilt``, the root plate's ``theta_s`` rad [S]), and NUTS diagnostics
    (``r_hat``, ``ess`` per parameter, ``divergences``)."""

    joints: tuple[str, ...]
    channels: tuple[str, ...]
    kp: np.ndarray
    sigma: np.ndarray
    diagnostics: dict = field(default_factory=dict)
    noise: str = "iid"
    noise_params: dict = field(default_factory=dict)
    creep: bool = False
    creep_params: dict = field(default_factory=dict)
    lag_params: dict = field(default_factory=dict)
    soft_params: dict = field(default_factory=dict)

    def summary(self) -> dict:
        def stats(x):
            return {
                "mean": float(np.mean(x)),
                "sd": float(np.std(x)),
                "q2.5": float(np.quantile(x, 0.025)),
                "q97.5": float(np.quantile(x, 0.975)),
            }

        out = {f"kp_{j}": stats(self.kp[:, i]) for i, j in enumerate(self.joints)}
        out |= {f"sigma_{c}": stats(self.sigma[:, i]) for i, c in enumerate(self.channels)}
        for name, x in self.noise_params.items():
            out |= {f"{name}_{c}": stats(x[:, i]) for i, c in enumerate(self.channels)}
        for name, x in self.creep_params.items():
            out |= {f"creep_{name}_{j}": stats(x[:, i]) for i, j in enumerate(self.joints)}
        for name, x in self.lag_params.items():  # [S] (the root's) or [S, R] (every joint's)
            if np.ndim(x) == 1:
                out[f"lag_{name}_root"] = stats(x)
            else:
                out |= {f"lag_{name}_{j}": stats(x[:, i]) for i, j in enumerate(self.joints)}
        for name, x in self.soft_params.items():  # [S]: the root plate's softening
            out[f"soft_{name}_root"] = stats(x)
        return out

    def tilts(self, model: PullModel, idx, force, time):
        """The model's tilts ``[S, C, T]`` and ``stable`` [S] at the draws ``idx``."""
        kp = jnp.asarray(self.kp[idx])
        creep = lag = soft = None
        if self.creep:
            creep = tuple(jnp.asarray(self.creep_params[k][idx]) for k in ("ratio", "tau"))
        if self.lag_params:
            cf, tf = (jnp.asarray(self.lag_params[k][idx]) for k in ("ratio", "tau"))
            lag = (cf, tf, "root" if cf.ndim == 1 else None)
        if self.soft_params:
            soft = jnp.asarray(self.soft_params["tilt"][idx])
        return chain_tilts(model, kp, force, time, creep=creep, lag=lag, soft=soft)


def initial_stiffness(model: PullModel, force, tilt) -> np.ndarray:
    """A start for the chain's two springs from the small-angle closed form: the root spring
    carries the cable's moment at the ground, ``tilt_root = F h cos a / K_root``, the stem
    spring the moment at its hinge; each slope by least squares through the origin. Clipped
    to the prior box."""
    force, tilt = np.asarray(force, float), np.asarray(tilt, float)
    chans = list(model.sensors)
    h_r = model.tree.branch("root").length
    arm = {"root": model.sling_height, "stem": max(model.sling_height - h_r, 0.0)}
    ca = math.cos(model.cable_angle)
    slopes = {}
    for i, c in enumerate(chans):
        ok = np.isfinite(tilt[i])
        den = float(np.sum(force[ok] ** 2))
        slopes[model.sensors[c]] = float(np.sum(force[ok] * tilt[i][ok]) / den) if den else 0.0
    lo, hi = KP_PRIOR
    s_root = slopes.get("root", 0.0)
    k_root = arm["root"] * ca / s_root if s_root > 0 else math.sqrt(lo * hi)
    s_stem = slopes.get("stem", 0.0) - s_root
    k_stem = arm["stem"] * ca / s_stem if s_stem > 0 and arm["stem"] > 0 else math.sqrt(lo * hi)
    kp = {"root": k_root, "stem": k_stem}
    return np.clip(np.array([kp[j] for j in model.joints]), lo * 1.01, hi / 1.01)


def _numpyro_model(
    model: PullModel,
    force,
    time,
    tilt,
    mask,
    kp_prior,
    noise_prior,
    noise="iid",
    creep=False,
    lag=False,
    soft=False,
):
    import numpyro
    import numpyro.distributions as dist

    r, c = len(model.joints), tilt.shape[0]
    lo, hi = (math.log(v) for v in kp_prior)
    log_kp = numpyro.sample("log_kp", dist.Uniform(lo, hi).expand([r]).to_event(1))
    creep_el = lag_el = soft_el = None
    if creep:
        ratio = numpyro.sample(
            "creep_ratio", dist.LogUniform(*CREEP_RATIO_PRIOR).expand([r]).to_event(1)
        )
        tau_prior = SLOW_TAU_PRIOR if lag else CREEP_TAU_PRIOR
        tau = numpyro.sample("creep_tau", dist.LogUniform(*tau_prior).expand([r]).to_event(1))
        creep_el = (ratio[None], tau[None])
        if lag:
            n_lag = [r] if lag == "all" else []
            cf = numpyro.sample("lag_ratio", _prior(dist.LogUniform(*LAG_RATIO_PRIOR), n_lag))
            tf = numpyro.sample("lag_tau", _prior(dist.LogUniform(*LAG_TAU_PRIOR), n_lag))
            lag_el = (cf[None], tf[None], None if lag == "all" else "root")
    if soft:
        soft_el = numpyro.sample("soft_tilt", dist.LogUniform(*SOFT_TILT_PRIOR))[None]
    pred, stable = chain_tilts(
        model, jnp.exp(log_kp)[None], force, time, creep=creep_el, lag=lag_el, soft=soft_el
    )
    numpyro.factor("stable", jnp.where(stable[0], 0.0, -jnp.inf))
    scale = dist.LogUniform(*noise_prior).expand([c]).to_event(1)
    if noise == "iid":
        sigma = numpyro.sample("sigma", scale)
        obs = dist.Normal(pred[0], sigma[:, None]).mask(mask)
        numpyro.sample("tilt", obs.to_event(2), obs=jnp.where(mask, tilt, 0.0))
        return
    sigma_w = numpyro.sample("sigma_w", scale)
    sigma_a = numpyro.sample("sigma_a", scale)
    tau_ar = numpyro.sample("tau_ar", dist.LogUniform(*TAU_AR_PRIOR).expand([c]).to_event(1))
    resid = jnp.where(mask, tilt - pred[0], 0.0)
    if noise == "ar1":
        numpyro.factor("tilt", ou_white_log_prob(resid, mask, time, sigma_w, sigma_a, tau_ar))
        return
    sigma_g = numpyro.sample("sigma_g", dist.LogUniform(*GAIN_SD_PRIOR).expand([c]).to_event(1))
    tau_g = numpyro.sample("tau_g", dist.LogUniform(*GAIN_TAU_PRIOR).expand([c]).to_event(1))
    lp = gain_ou_log_prob(resid, pred[0], mask, time, sigma_w, sigma_a, tau_ar, sigma_g, tau_g)
    numpyro.factor("tilt", lp)


def _prior(d, shape: list):
    """``d`` for a scalar parameter, else ``shape`` independent copies as one event."""
    return d.expand(shape).to_event(1) if shape else d


def _time_base(time, n: int) -> np.ndarray:
    if time is None:
        return np.arange(n) * DEFAULT_DT
    time = np.asarray(time, float)
    if time.shape != (n,) or not np.all(np.diff(time) > 0):
        raise ConfigError(f"time: expected {n} increasing times (s), got shape {time.shape}")
    return time


def fit_pull_test(
    model: PullModel,
    force,
    tilt,
    *,
    time=None,
    num_warmup: int = 500,
    num_samples: int = 1000,
    num_chains: int = 2,
    seed: int = 0,
    kp_prior: tuple[float, float] = KP_PRIOR,
    noise_prior: tuple[float, float] = NOISE_PRIOR,
    noise: str = "iid",
    creep: bool = False,
    lag: bool | str = False,
    soft: bool = False,
    progress: bool = False,
) -> PullPosterior:
    """NUTS on the static model: ``force`` [T] N along the cable, ``tilt`` [C, T] rad for the
    channels of ``model.sensors`` (NaN where missing), ``time`` [T] s (default: every
    :data:`DEFAULT_DT`; the creep and the AR(1) part follow it), ``noise`` ``"iid"`` or
    ``"ar1"``, ``creep`` the viscoelastic joints, ``lag`` (with ``creep``) a fast lag element on
    the root joint (``True``) or on every joint (``"all"``) (the module docstring), ``soft`` a
    softening root plate (:mod:`.softening`). Chains run one after the other (CPU)."""
    from numpyro.infer import MCMC, NUTS, init_to_value

    if noise not in NOISE_MODELS:
        raise ConfigError(f"noise: expected one of {', '.join(NOISE_MODELS)}, got {noise!r}")
    if lag not in (False, True, "all"):
        raise ConfigError(f"lag: expected False, True (the root's) or 'all', got {lag!r}")
    if lag and not (creep and "root" in model.joints):
        raise ConfigError("lag: the root's fast lag element needs creep=True and a root joint")
    if soft and "root" not in model.joints:
        raise ConfigError("soft: the softening root plate needs a root joint")

    force_np = np.asarray(force, float)
    force = jnp.asarray(force_np)
    time = _time_base(time, force.shape[0])
    tilt_np = np.atleast_2d(np.asarray(tilt, float))
    if tilt_np.shape != (len(model.sensors), force.shape[0]):
        raise ConfigError(
            f"fit_pull_test: tilt is {tilt_np.shape}, expected "
            f"({len(model.sensors)}, {force.shape[0]}) (channels x force samples)"
        )
    mask = np.isfinite(tilt_np)
    if mask.sum(axis=1).min() < 3:
        raise ConfigError("fit_pull_test: fewer than 3 recorded tilts in a channel")
    k0 = initial_stiffness(model, force_np, tilt_np)
    pred0, _ = model_tilts(model, jnp.asarray(k0)[None], force)
    resid = np.where(mask, tilt_np - np.asarray(pred0[0]), np.nan)
    s0 = np.clip(np.nanstd(resid, axis=1), noise_prior[0] * 2, noise_prior[1] / 2)
    kernel = NUTS(
        _numpyro_model,
        init_strategy=init_to_value(values=_start(noise, creep, k0, s0, lag, soft)),
        target_accept_prob=0.9,
        dense_mass=True,  # the trunk channel couples the two stiffnesses
    )
    mcmc = MCMC(
        kernel,
        num_warmup=num_warmup,
        num_samples=num_samples,
        num_chains=num_chains,
        chain_method="sequential",
        progress_bar=progress,
    )
    mcmc.run(
        jax.random.PRNGKey(seed),
        model,
        force,
        jnp.asarray(time),
        jnp.asarray(tilt_np),
        jnp.asarray(mask),
        kp_prior,
        noise_prior,
        noise,
        creep,
        lag,
        soft,
    )
    draws = mcmc.get_samples(group_by_chain=True)
    from numpyro.diagnostics import effective_sample_size, split_gelman_rubin

    diag = {"divergences": int(np.asarray(mcmc.get_extra_fields()["diverging"]).sum())}
    names = ["log_kp", *(("sigma",) if noise == "iid" else ("sigma_w", "sigma_a", "tau_ar"))]
    names += ["sigma_g", "tau_g"] if noise == "ar1+gain" else []
    names += ["creep_ratio", "creep_tau"] if creep else []
    names += ["lag_ratio", "lag_tau"] if lag else []
    names += ["soft_tilt"] if soft else []
    for name in names:
        x = np.asarray(draws[name])
        diag[f"r_hat_{name}"] = (
            np.asarray(split_gelman_rubin(x)).tolist() if num_chains > 1 else None
        )
        diag[f"ess_{name}"] = np.asarray(effective_sample_size(x)).tolist()
    flat = {k: np.asarray(v) for k, v in mcmc.get_samples().items()}
    params = {}
    if noise == "iid":
        sigma = flat["sigma"]
    else:
        step = float(np.median(np.diff(time)))
        params = {
            "sigma_w": flat["sigma_w"],
            "sigma_a": flat["sigma_a"],
            "tau_ar": flat["tau_ar"],
            "rho": np.exp(-step / flat["tau_ar"]),
        }
        if noise == "ar1+gain":
            params |= {"sigma_g": flat["sigma_g"], "tau_g": flat["tau_g"]}
        sigma = np.hypot(params["sigma_w"], params["sigma_a"])
    creep_params = {"ratio": flat["creep_ratio"], "tau": flat["creep_tau"]} if creep else {}
    lag_params = {"ratio": flat["lag_ratio"], "tau": flat["lag_tau"]} if lag else {}
    return PullPosterior(
        joints=tuple(model.joints),
        channels=tuple(model.sensors),
        kp=np.exp(flat["log_kp"]),
        sigma=sigma,
        diagnostics=diag,
        noise=noise,
        noise_params=params,
        creep=creep,
        creep_params=creep_params,
        lag_params=lag_params,
        soft_params={"tilt": flat["soft_tilt"]} if soft else {},
    )


CREEP_START = (0.05, 20.0)  # NUTS's start: a little creep, a relaxation time of 20 s
LAG_START = (0.05, 0.5)  # and a little fast lag, 0.5 s
SOFT_START = math.radians(10.0)  # and a nearly linear root plate (theta_s 10 deg)


def _start(noise: str, creep: bool, k0, s0, lag: bool = False, soft: bool = False) -> dict:
    """NUTS's start: the closed-form stiffnesses, the noise sd of their residuals (``ar1``:
    split evenly between the white and the correlated part, a correlation time of 1 s)."""
    r = len(k0)
    out = {"log_kp": jnp.log(k0)}
    if creep:
        out |= {
            "creep_ratio": jnp.full(r, CREEP_START[0]),
            "creep_tau": jnp.full(r, CREEP_START[1]),
        }
    if lag:
        shape = (r,) if lag == "all" else ()
        out |= {k: jnp.full(shape, v) for k, v in zip(("lag_ratio", "lag_tau"), LAG_START)}
    if soft:
        out["soft_tilt"] = jnp.asarray(SOFT_START)
    if noise == "iid":
        return out | {"sigma": jnp.asarray(s0)}
    half = jnp.asarray(s0) / math.sqrt(2)
    out |= {"sigma_w": half, "sigma_a": half, "tau_ar": jnp.full(len(s0), 1.0)}
    if noise == "ar1+gain":  # a 2% gain error wandering over 15 s
        out |= {"sigma_g": jnp.full(len(s0), 0.02), "tau_g": jnp.full(len(s0), 15.0)}
    return out


def predictive_band(
    model: PullModel,
    post: PullPosterior,
    force,
    level: float = 0.95,
    n_draws: int = 400,
    seed=0,
    time=None,
    fit_tilt=None,
) -> dict[str, np.ndarray]:
    """The posterior predictive of the recorded tilt under ``force`` [T] (at ``time`` [T] s,
    which the creep follows; its state starts at rest at ``time[0]``): ``mean`` (the model's
    tilt averaged over draws), ``lo``/``hi`` (the central ``level`` interval of model + noise),
    ``model_lo``/``model_hi`` (of the model's tilt alone), ``centre`` (the predictive mean:
    ``mean`` but for a gain forecast's mean); each [C, T] rad. An ``ar1+gain``
    posterior's gain error enters by its stationary marginal, or, given ``fit_tilt`` [C, n]
    (the recorded tilts of the first ``n`` samples, the fitted part), by its forecast from
    them after them (:func:`.gain.gain_band_terms`)."""
    rng = np.random.default_rng(seed)
    idx = rng.choice(post.kp.shape[0], size=min(n_draws, post.kp.shape[0]), replace=False)
    force = jnp.asarray(np.asarray(force, float))
    time = _time_base(time, force.shape[0])
    pred, stable = post.tilts(model, idx, force, jnp.asarray(time))
    pred = np.asarray(pred)[np.asarray(stable)]  # [S, C, T]
    if pred.shape[0] == 0:
        raise ConfigError("predictive_band: no posterior draw has an equilibrium for this force")
    sig = post.sigma[idx][np.asarray(stable)]
    # a few noise draws per parameter draw: smoother tail quantiles for the same solves
    eps = rng.standard_normal((NOISE_DRAWS, *pred.shape))
    noisy = pred[None] + sig[None, :, :, None] * eps
    centre = pred.mean(axis=0)
    if "sigma_g" in post.noise_params:  # the gain error (.gain)
        from .gain import gain_band_terms

        keep = idx[np.asarray(stable)]
        params = {k: v[keep] for k, v in post.noise_params.items()}
        g_mean, g_sd = gain_band_terms(pred, params, time, fit_tilt)
        noisy = noisy + pred[None] * (g_mean[None] + g_sd[None] * rng.standard_normal(eps.shape))
        centre = (pred * (1.0 + g_mean)).mean(axis=0)
    noisy = noisy.reshape(-1, *pred.shape[1:])
    q = (1 - level) / 2
    return {
        "mean": pred.mean(axis=0),
        "lo": np.quantile(noisy, q, axis=0),
        "hi": np.quantile(noisy, 1 - q, axis=0),
        "model_lo": np.quantile(pred, q, axis=0),
        "model_hi": np.quantile(pred, 1 - q, axis=0),
        "centre": centre,
    }


def residual_check(band_mean, tilt, post: PullPosterior | None = None, time=None) -> dict:
    """The check of :mod:`.residuals`: ``lag1`` [C] the lag-1 autocorrelation of the recorded
    ``tilt`` [C, T] minus a fit's predictive ``mean`` [C, T] (on the fitted samples), and
    ``needs_ar1`` [C] where it exceeds :data:`~.residuals.LAG1_LIMIT` (i.i.d. noise would
    make the band and the intervals too narrow). With an ``ar1`` or ``ar1+gain`` posterior
    ``post`` (and ``time`` [T] s), also ``lag1_innovations`` [C]: the same statistic of the
    standardised Kalman innovations at the posterior medians of the noise parameters (for
    ``ar1+gain`` the two-state filter of :mod:`.gain`, with ``mean`` as the gain's
    coefficient), and ``ar1_enough`` [C] where it is below the limit (the correlated noise
    model accounts for the residuals' correlation)."""
    from .gain import gain_ou_innovations
    from .residuals import LAG1_LIMIT, ou_white_innovations

    resid = np.asarray(tilt, float) - np.asarray(band_mean, float)
    r1 = lag1_autocorrelation(resid)
    out = {"lag1": r1, "needs_ar1": r1 > LAG1_LIMIT}
    if post is None or post.noise not in ("ar1", "ar1+gain"):
        return out
    keys = ("sigma_w", "sigma_a", "tau_ar")
    keys += ("sigma_g", "tau_g") if post.noise == "ar1+gain" else ()
    med = [np.median(post.noise_params[k], axis=0) for k in keys]
    mask = np.isfinite(resid)
    args = (np.nan_to_num(resid), mask, _time_base(time, resid.shape[1]), *med)
    if post.noise == "ar1":
        z = ou_white_innovations(*args)
    else:
        theta = np.nan_to_num(np.asarray(band_mean, float))
        z = gain_ou_innovations(args[0], theta, *args[1:])
    out["lag1_innovations"] = lag1_autocorrelation(z)
    out["ar1_enough"] = out["lag1_innovations"] < LAG1_LIMIT
    return out
