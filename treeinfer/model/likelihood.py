"""The likelihood part of the posterior: :func:`likelihood_terms` builds, for one tree, its
recordings and a likelihood choice, the log-likelihood, its gradient and the extra (noise) columns
of theta, for the paper's Boltzmann loss (:mod:`treeinfer.model.boltzmann`, paper eq. 4-6, with
the choice of kT) or a generative measurement model (:mod:`treeinfer.model.measurement`).

Parameterisation: samplers work on ``theta = [log Kp_1..R, log Kd_1..R]``. Kp and Kd span
orders of magnitude, so a log scale gives every particle the same relative resolution, makes
one finite-difference step (and one SVGD bandwidth) fit all of them, and keeps gains positive.

Generative measurement likelihoods (:func:`measurement_log_likelihood`): recorded displacement =
simulated displacement + i.i.d. noise (Gaussian or Student-t, :mod:`treeinfer.model.noise`), with
sigma_x given or inferred as an extra column ``log sigma_x`` of theta. The simulator stays a
black box: :func:`treeinfer.model.gradients.finite_difference_jvp` gives it central-difference
derivatives, while the noise density and the sigma column get exact autodiff gradients.

Noise on the recorded force (``likelihood_terms(kind="gaussian", noise_force=...)``,
``--noise-force``): an errors-in-variables term, marginalised in closed form after linearising
the simulation in the force; each pull's residual is then ``MVN(0, C_b + sigma_x^2 I)`` with
``C_b = sigma_F^2 J_b J_b^T`` (:mod:`treeinfer.model.force_noise`, which says why this design).

Every name of :mod:`treeinfer.model.boltzmann`, :mod:`treeinfer.model.measurement`,
:mod:`treeinfer.model.temperature` and :mod:`treeinfer.model.gains` that lived here before the
splits is re-exported here.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..data.trajectories import Observations
from ..errors import ConfigError
from ..sim import Simulator
from . import noise
from .boltzmann import (  # noqa: F401 -- the paper's loss, re-exported (it lived here before)
    DEFAULT_KT,
    _padded_trajectory_loss,
    boltzmann_log_likelihood,
    log_likelihood_from_rollout,
    trajectory_loss,
)
from .gains import (  # noqa: F401  (re-exported: they lived here before)
    gains_from_theta,
    natural_units,
    noise_columns,
    noise_params_from_theta,
    predictive_noise_kind,
    theta_from_gains,
)
from .gradients import autodiff_value_and_grad, central_difference
from .measurement import (  # noqa: F401 -- the generative likelihood's pieces, re-exported
    _measurement_loglik,
    _noise_density,
    _padded_basis,
    data_observations,
    measurement_log_likelihood,
    observation_data,
    padded_rollout,
)

if TYPE_CHECKING:
    from .force_noise_model import ForceNoiseModel

from .temperature import (  # re-exported: the kT rule lived here before the split
    KTChoice,
    auto_kT,
    check_kT,
    signal_omega2,
    suggest_kT,
)

__all__ = [
    "DEFAULT_KT",
    "KTChoice",
    "LikelihoodTerms",
    "auto_kT",
    "boltzmann_log_likelihood",
    "check_kT",
    "data_observations",
    "gains_from_theta",
    "likelihood_terms",
    "log_likelihood_from_rollout",
    "measurement_log_likelihood",
    "natural_units",
    "noise_columns",
    "noise_params_from_theta",
    "observation_data",
    "padded_rollout",
    "predictive_noise_kind",
    "signal_omega2",
    "suggest_kT",
    "theta_from_gains",
    "trajectory_loss",
]


class LikelihoodTerms(NamedTuple):
    """What :func:`likelihood_terms` builds, ready to plug into ``make_problem``.

    log_likelihood: ``theta [N, D] -> [N]`` nats. value_and_grad: its value and uphill gradient
      (central differences for Boltzmann; autodiff through the FD-JVP simulator otherwise).
    extra_labels: labels of theta's extra columns after the 2R gains (``("sigma_x",)`` or ()).
      The column holds ``log sigma_x`` (sigma_x in m).
    extra_lower, extra_upper: [E] prior box of the extra columns (theta units): for a noise
      scale the flat part of :class:`treeinfer.model.noise.NoisePrior` (resolution to data range).
    extra_log_prior: ``theta [N, D] -> [N]`` prior of the extra columns (None if E = 0).
    kT: the Boltzmann temperature used (None for the generative kinds).
    sigma_x: fixed displacement noise (m) if not inferred: given, or for Boltzmann with
      ``kT="auto"`` the data estimate (for the predictive band); None otherwise (fixed-kT
      Boltzmann without a given noise: the paper's mode, parameter bands only).
    settings: JSON-ready record. description: human-readable lines (print them).
    force_noise: the force-noise term
      (:class:`treeinfer.model.force_noise_model.ForceNoiseModel`) when
      ``noise_force`` was given, else None; predictive bands of recordings driven by a noisy
      force add its covariance (``force_noise.basis(sim, forces)``).
    data_of, loglik_of: the same likelihood with the observations as an argument (None where a
      builder does not offer it): ``data_of(obs, shape=None)`` (host) turns observations on the
      training data's time step and grasp points, padded to ``shape`` ``(B', T')`` (a shape
      bucket, :mod:`treeinfer.sim.startup`), into a pytree of arrays (:func:`observation_data`, plus
      the force-noise basis of the padded pulls), and ``loglik_of(data)`` is ``theta [N, D] ->
      [N]`` on them, equal to ``log_likelihood`` on the unpadded data; ``data`` may be traced (a
      jitted program's argument), so programs built on it serve every data set of one shape.
    extra_init: ``(lower [E], upper [E])`` where uniform initial particles of the extra columns
      are drawn (near the data's noise estimate, inside the prior box), or None: the box.
    residual_loglik: ``(dx [N, B, T], dv [N, B, T], theta [N, D]) -> [N]``, the same
      log-likelihood from the recorded-minus-simulated displacement ``dx`` (m) and velocity
      ``dv`` (m/s) of the training data (zero at masked samples) of stable rollouts: what
      :mod:`treeinfer.inference.fast` evaluates on the host around its one rollout program
      (None where a builder does not offer it).
    """

    log_likelihood: Callable
    value_and_grad: Callable
    extra_labels: tuple[str, ...]
    extra_lower: np.ndarray
    extra_upper: np.ndarray
    extra_log_prior: Callable | None
    kT: float | None
    sigma_x: float | None
    settings: dict
    description: str
    force_noise: ForceNoiseModel | None = None
    data_of: Callable | None = None
    loglik_of: Callable | None = None
    extra_init: tuple | None = None
    residual_loglik: Callable | None = None

    @property
    def black_box(self) -> bool:
        """True: ``log_likelihood`` must be differenced (``combined_value_and_grad``'s
        ``fd_terms``: the Boltzmann loss). False: JAX differentiates it (its simulator is wrapped
        in :func:`finite_difference_jvp`), so it goes with the ``autodiff_terms``."""
        return self.settings.get("likelihood") == "boltzmann"

    def log_prior_terms(self) -> list:
        """The extra columns' prior as a list of terms (empty when there are none)."""
        return [] if self.extra_log_prior is None else [self.extra_log_prior]


def _integration_args(ie):
    """``(rms, shape)`` of :func:`_noise_density` for ``ie`` (None: no floor)."""
    return None if ie is None else (ie.rms, jnp.asarray(ie.shape))


def likelihood_terms(
    sim: Simulator,
    obs: Observations,
    kind: str = "boltzmann",
    *,
    kT: float | str = DEFAULT_KT,
    sigma_x: float | None = None,
    sigma_v: float | None = None,
    df: float = noise.DEFAULT_STUDENT_T_DF,
    noise_floor: float | None = None,
    grasp_fraction=None,
    gradient: str = "fd",
    rel_step: float | None = None,
    noise_force=None,
    force_noise_reference=None,
    force_noise_rule: str = "J at the given reference",
    integration_error=None,
) -> LikelihoodTerms:
    """The likelihood part of the posterior for one tree + data + likelihood choice.

    Args:
      kind: ``"boltzmann"`` (the paper's loss, ``kT`` a number or ``"auto"``), ``"gaussian"``,
        ``"student_t"`` or ``"ar1"`` (generative, :mod:`treeinfer.model.noise`; theta then has the
        noise columns of :func:`noise_columns` after the gains).
      sigma_x: m. Generative kinds: fixed noise, or None to infer ``log sigma_x`` jointly as
        theta's last column with the weakly-informative prior of
        :func:`treeinfer.model.noise.noise_scale_prior` (log sigma_x flat from the sensor's
        resolution to the data's range; the data estimate only seeds the start). Boltzmann with
        ``kT="auto"``: use it instead of the estimate.
      noise_floor: m, the displacement sensor's resolution if known: the prior's lower end
        (None: ``step / sqrt(12)`` of a quantised recording, else 1 micron).
      sigma_v: m/s, velocity noise for the generative kinds (None: velocity term off).
      gradient: ``"fd"`` (black box, central differences) or ``"autodiff"`` (through the simulator).
      noise_force: None (default: no force-noise term, behaviour unchanged) or the std of white
        noise on the recorded force: newtons, ``"P%"`` of the largest recorded |force|, or
        ``"auto"`` (:func:`treeinfer.model.force_noise.resolve_noise_force`). Gaussian only: adds
        the errors-in-variables covariance of :mod:`treeinfer.model.force_noise` to the likelihood.
      force_noise_reference: ``[2R]`` log gains at which the force Jacobian is taken; None: the
        MAP of the errors-in-variables model
        (:func:`~treeinfer.model.force_noise_reference.reference_theta`).
      force_noise_rule: how a given ``force_noise_reference`` was chosen (recorded in the
        settings' ``noise_force_rule``).
      integration_error: None, or the simulator's discretisation error measured at the MAP
        (:class:`treeinfer.model.integration_error.IntegrationError`), generative kinds only:
        removed from the simulated displacement, its rms added to sigma_x in quadrature
        (:mod:`treeinfer.model.integration_error`).
    """
    noise.check_kind(kind)
    if noise_force is not None and kind != "gaussian":
        raise ConfigError(
            f"noise_force: the force-noise term is available with --likelihood gaussian only, "
            f"got {kind!r}"
        )
    if gradient not in ("fd", "autodiff"):
        raise ConfigError(f"gradient: expected 'fd' or 'autodiff', got {gradient!r}")
    empty = np.zeros((0,))
    if kind == "boltzmann":
        if isinstance(kT, str):
            if kT != "auto":
                raise ConfigError(f"kT: expected a positive number or 'auto', got {kT!r}")
            choice = auto_kT(obs, sigma_x)
            kT_value, est, desc = choice.kT, choice.estimate.sigma, choice.describe()
            extra = {"kT_rule": desc, "omega2": choice.omega2}
        else:
            kT_value, extra = check_kT(kT), {}
            # the paper's mode: no noise model unless one is given (then predictive bands use it)
            est = (
                None
                if sigma_x is None
                else noise.check_sigma(sigma_x, "noise_displacement", noise.displacement_range(obs))
            )
            desc = f"Boltzmann likelihood, kT = {kT_value:g} (fixed)"
        loglik = boltzmann_log_likelihood(sim, obs, kT_value, grasp_fraction)
        vg = (
            central_difference(loglik, rel_step=rel_step)
            if gradient == "fd"
            else autodiff_value_and_grad(loglik)
        )
        settings = {
            "likelihood": "boltzmann",
            "kT": kT_value,
            "kT_auto": isinstance(kT, str),
            "noise_displacement": est,
            **extra,
        }

        def boltzmann_of(data):
            o = data_observations(data, obs.dt)
            gf = data.get("grasp", grasp_fraction)

            def loglik_data(theta: jax.Array) -> jax.Array:
                kp, kd = gains_from_theta(theta, sim.n_joints)
                ro = padded_rollout(sim, kp, kd, o.force, gf, data["n_steps"], o.mask)
                loss = _padded_trajectory_loss(ro, o)
                ll = -jnp.sum(loss, axis=-1) / kT_value
                return jnp.where(jnp.all(ro.stable, axis=-1), ll, -jnp.inf)

            return loglik_data

        mask_b = jnp.asarray(obs.mask, bool)  # may be traced (batch_posteriors)

        def boltzmann_residual(dx, dv, theta):
            def norm(r):
                return jnp.sqrt(jnp.sum(jnp.where(mask_b, r, 0.0) ** 2, -1))

            return -jnp.sum(norm(dx) + norm(dv), axis=-1) / kT_value

        return LikelihoodTerms(
            loglik,
            vg,
            (),
            empty,
            empty,
            None,
            kT_value,
            est,
            settings,
            desc,
            None,
            lambda o, shape=None: observation_data(o, grasp_fraction, shape),
            boltzmann_of,
            residual_loglik=boltzmann_residual,
        )

    df = noise.check_df(df)
    from .integration_error import check_integration_error

    ie = check_integration_error(integration_error, np.shape(obs.displacement))
    fmodel, basis = None, None
    if noise_force is not None:
        if sigma_v is not None:
            raise ConfigError(
                "noise_force: the force-noise term is not available with a velocity term "
                "(noise_velocity); leave the velocity out"
            )
        from . import force_noise
        from .force_noise_local import check_references
        from .force_noise_model import ForceNoiseModel, training_basis

        sigma_f, rule = force_noise.resolve_noise_force(noise_force, obs)
        if force_noise_reference is None:
            from .force_noise_reference import reference_theta

            ref = reference_theta(sim, obs, grasp_fraction, sigma_f)
            rule += "; J at the MAP of this errors-in-variables model"
        else:
            ref = check_references(force_noise_reference, 2 * sim.n_joints)
            rule += f"; {force_noise_rule}"
        fmodel = ForceNoiseModel(sigma_f, ref, rule, grasp_fraction)
        basis = training_basis(sim, fmodel, obs)
    loglik = measurement_log_likelihood(
        sim,
        obs,
        kind,
        sigma_x,
        sigma_v,
        df,
        grasp_fraction,
        rel_step,
        black_box=gradient == "fd",
        force_basis=basis,
        integration=_integration_args(ie),
    )
    vg = autodiff_value_and_grad(loglik)
    checked_sx = (
        None
        if sigma_x is None
        else noise.check_sigma(sigma_x, "noise_displacement", noise.displacement_range(obs))
    )
    checked_sv = None if sigma_v is None else noise.check_sigma(sigma_v, "noise_velocity")

    def data_of(o, shape=None):
        data = observation_data(o, grasp_fraction, shape)
        if fmodel is not None:  # the force-noise basis of these (padded) pulls: data as well
            if o is obs:  # the training pulls: their basis, padded (no second Jacobian)
                b = _padded_basis(basis, np.asarray(data["mask"]))
            else:
                b = fmodel.basis(sim, np.asarray(data["force"]), np.asarray(data["mask"]))
            data["force_basis"] = type(b)(*(None if x is None else jnp.asarray(x) for x in b))
        if ie is not None:  # the error's shape, padded as the pulls are (zero: no data there)
            data["integration_shape"] = jnp.asarray(ie.padded(np.shape(data["mask"])))
        return data

    def loglik_of(data):
        return _measurement_loglik(
            sim,
            data_observations(data, obs.dt),
            kind,
            checked_sx,
            checked_sv,
            df,
            data.get("grasp", grasp_fraction),
            rel_step,
            gradient == "fd",
            data.get("force_basis"),
            data["n_steps"],
            None if ie is None else (ie.rms, data["integration_shape"]),
        )

    residual_loglik = _noise_density(
        kind,
        checked_sx,
        checked_sv,
        df,
        jnp.asarray(obs.mask, bool),
        basis,
        2 * sim.n_joints,
        _integration_args(ie),
    )
    names = {
        "gaussian": "Gaussian",
        "student_t": f"Student-t (df = {df:g})",
        "ar1": "white + AR(1)",
    }
    vel = f", velocity noise {sigma_v:g} m/s" if sigma_v is not None else ", velocity term off"
    if fmodel is not None:
        vel += f"; errors-in-variables {fmodel.description}, bias-corrected"
    if ie is not None:
        vel += f"; {ie.describe()}"
    settings = {
        "likelihood": kind,
        "noise_velocity": sigma_v,
        "student_t_df": df if kind == "student_t" else None,
        **({} if fmodel is None else fmodel.settings()),
        **({} if ie is None else {"integration_error": ie.settings()}),
    }
    labels = noise_columns(kind, sigma_x is None)
    if sigma_x is not None:
        sx = noise.check_sigma(sigma_x, "noise_displacement", noise.displacement_range(obs))
        settings.update(noise_displacement=sx, noise_inferred=False)
        desc = f"{names[kind]} displacement noise, sigma_x = {sx * 1e3:.4g} mm (given){vel}"
        if kind != "ar1":
            return LikelihoodTerms(
                loglik, vg, (), empty, empty, None, None, sx, settings, desc, fmodel, data_of,
                loglik_of, residual_loglik=residual_loglik,
            )  # fmt: skip
        est = noise.NoiseEstimate(sx, 0, "given")
    else:
        try:
            est = noise.estimate_displacement_noise(obs)
        except ConfigError:  # the prior does not need it: the start box falls back to the range
            est = None
        sx = None
        settings.update(
            noise_displacement=None,
            noise_inferred=True,
            noise_estimate=None if est is None else est.sigma,
        )
    import numpyro.distributions as dist

    # weakly informative over decades: flat in log sigma from the sensor's resolution to the
    # data's range (treeinfer.model.noise.NoisePrior); its flat part is the columns' box
    prior = noise.noise_scale_prior(obs, est, noise_floor)
    if ie is not None and ie.rms > prior.floor:
        # the simulator's own error is a floor of the white part too: the posterior of log
        # sigma_x then sits ~0.12 below it inside the prior's steep Gaussian tail, a Gaussian,
        # not at a kink where the quadrature floor takes over (the start pipeline's importance
        # weights failed there: k_hat 1.2-1.3 on clean chain2, 0.02-0.3 with this floor)
        floor = min(ie.rms, prior.ceiling / 100.0)
        prior = prior._replace(floor=floor, rule="the simulator's integration error at the MAP")
    lo_s, hi_s = prior.log_bounds
    if est is None:
        init = (lo_s + 0.5 * (hi_s - lo_s), hi_s)
    else:  # start near the estimate; it misses model error, which only adds: more room above
        init = (max(math.log(est.sigma / 2.0), lo_s), min(math.log(est.sigma * 20.0), hi_s))
        init = init if init[1] > init[0] else (lo_s, hi_s)
    if sigma_x is None:
        desc = (
            f"{names[kind]} displacement noise, sigma_x inferred (prior {prior.describe()}; "
            f"{'no estimate' if est is None else est.describe()}){vel}"
        )
    rho_prior = dist.Normal(noise.RHO_PRIOR_LOC, noise.RHO_PRIOR_SCALE)
    col = 2 * sim.n_joints
    lower, upper, priors, init_lo, init_hi = [], [], [], [], []
    for k, lab in enumerate(labels):
        if lab == "rho":
            lower.append(0.0)  # rho 0.5 .. 0.99 for the initial particles
            upper.append(math.log(0.99 / 0.01))
            priors.append((col + k, rho_prior.log_prob))
        else:
            lower.append(lo_s)
            upper.append(hi_s)
            priors.append((col + k, prior.log_prob))
        init_lo.append(init[0] if lab != "rho" else lower[-1])
        init_hi.append(init[1] if lab != "rho" else upper[-1])

    def extra_log_prior(theta):
        theta = jnp.asarray(theta)
        return sum(f(theta[:, j]) for j, f in priors)

    settings["noise_prior"] = {
        lab: (
            f"logit rho ~ Normal({noise.RHO_PRIOR_LOC:.3g}, {noise.RHO_PRIOR_SCALE:g})"
            if lab == "rho"
            else prior.describe(lab)
        )
        for lab in labels
    }
    if kind == "ar1":
        desc += (
            f"; AR(1) component sigma_c, rho inferred (prior {prior.describe('sigma_c')}, "
            f"logit rho ~ Normal({noise.RHO_PRIOR_LOC:.3g}, {noise.RHO_PRIOR_SCALE:g}))"
        )
    return LikelihoodTerms(
        loglik,
        vg,
        labels,
        np.array(lower),
        np.array(upper),
        extra_log_prior,
        None,
        sx,
        settings,
        desc,
        fmodel,
        data_of,
        loglik_of,
        (np.array(init_lo), np.array(init_hi)),
        residual_loglik,
    )
