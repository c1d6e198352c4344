"""The front end: tree + trajectories -> posterior particles -> predictions.

    problem = treeinfer.make_problem(tree, trajectories)          # likelihood + priors
    posterior = treeinfer.infer(problem, sampler="nnsvgd", n_particles=64, n_iterations=200)
    bands = treeinfer.predict(problem, posterior.theta, forces)   # Rollout [P, B, T]

The target density is built by composition (Optax style), all in theta = [log Kp, log Kd]:

    log p(theta | D) = boltzmann_log_likelihood          (black box: central differences)
                     + smoothed_box(log bounds)          (autodiff)
                     [+ NN inequality prior, NNSVGD]     (autodiff)

Prior space: the box is placed on log Kp / log Kd (a log-uniform prior on the gains), so no
Jacobian is needed. ``prior_space="linear"`` puts the box on Kp / Kd themselves instead and
adds the log-Jacobian ``sum(theta)`` of ``K = exp(theta)`` so the density stays correct in theta.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ..data.trajectories import Observations, Trajectory, stack_trajectories
from ..errors import ConfigError
from ..model import noise
from ..model.gradients import combine, combined_value_and_grad, jvp_combined_value_and_grad
from ..model.likelihood import DEFAULT_KT, check_kT, gains_from_theta, likelihood_terms
from ..model.prior_terms import DEFAULT_ETA, DEFAULT_PRIOR_SIGMA, box_prior, nn_inequality_prior
from ..sim import Simulator, make_simulator
from ..sim.program_cache import ProgramCache
from ..tree.description import Tree
from . import samplers as _samplers
from .posterior import Posterior, context_from_problem  # the result type of infer (issue 29)
from .rollout import _predict_jit, _predict_traced, predict  # noqa: F401 -- moved (issue 29)

GRADIENTS = ("fd", "jvp", "autodiff")  # how make_problem differentiates the simulator likelihood


class DataTarget(NamedTuple):
    """The problem's target with the observations as an argument (:func:`make_problem`'s
    ``shape_bucket``).

    built_for: the problem's ``value_and_grad`` it was built with; a problem whose target was
      replaced since (e.g. :func:`treeinfer.inference.sequential.with_prior`) no longer uses it.
    target: ``data -> (value_and_grad, log_density)``, the same functions as the problem's on
      ``data`` (traceable: ``data`` may be a jitted program's argument).
    data: the training observations padded to ``shape`` and masked, as a pytree of arrays
      (:meth:`treeinfer.model.likelihood.LikelihoodTerms.data_of`).
    shape: ``(B', T')`` the bucket.
    """

    built_for: Callable
    target: Callable
    data: Any
    shape: tuple[int, int]


@dataclass(frozen=True, eq=False)
class Problem:
    """Everything the samplers need about one inference problem.

    Attributes:
      tree, sim, obs: the tree, its compiled simulator, the stacked training trajectories.
      kT: Boltzmann temperature (the value given, or "auto"'s result; for the generative
        likelihoods only the Boltzmann training-fit report uses it).
      labels: ``Kp[j]``..., ``Kd[j]``..., then the noise columns (``sigma_x``...; see
        :func:`treeinfer.model.likelihood.noise_columns`) of theta.
      lower, upper: [D] the prior box in theta (log) units (initial box for noise columns).
      noise: the :class:`~treeinfer.model.likelihood.LikelihoodTerms` (likelihood kind, fixed or
        inferred noise, description) -- what predictions need for the predictive band.
      log_likelihood, log_prior: batched terms ``theta [N, D] -> [N]``.
      value_and_grad: ``theta [P, D] -> (log p [P], grad [P, D])`` of the whole target.
      log_density: ``theta [P, D] -> [P]``, the whole target (for MH and metrics).
      settings: what built it (recorded next to results).
      model: None (the dynamic rollout of theta = [log Kp, log Kd]) or the
        :class:`treeinfer.inference.static.Model` (static model, or stiffness only) theta is mapped
        by.
    """

    tree: Tree
    sim: Simulator
    obs: Observations
    kT: float
    labels: tuple[str, ...]
    lower: np.ndarray
    upper: np.ndarray
    log_likelihood: Callable
    log_prior: Callable
    value_and_grad: Callable
    log_density: Callable
    nn_prior: bool
    settings: dict = field(default_factory=dict)
    noise: Any = (
        None  # treeinfer.model.likelihood.LikelihoodTerms: the likelihood choice and its noise
    )
    model: Any = (
        None  # treeinfer.inference.static.Model when not the dynamic model of [log Kp, log Kd]
    )
    data_target: Any = None  # DataTarget: the samplers' programs take the data as an argument
    # [S, D] starting points for the start pipeline's MAP fit found while building the problem
    # (the force-noise reference's fit, treeinfer.inference.start_pipeline), None: it screens the
    # box
    start_hint: Any = None

    @property
    def dim(self) -> int:
        return len(self.labels)

    def data_sampler(self, name: str = "nnsvgd", **options):
        """:meth:`sampler` with the observations as its programs' argument: a
        :class:`treeinfer.inference.samplers.DataSamplingAlgorithm` on :attr:`data_target`, or None
        when the problem has none (or its target was replaced since it was built)."""
        dt = self.data_target
        if dt is None or dt.built_for is not self.value_and_grad:
            return None
        # the constructor's hyperparameters on the host, once: arrays made here (MH's proposal
        # scale) are concrete, so the settings record can read them inside a trace
        spec = _samplers.sampler_spec(name)
        hyper = spec.hyperparameters(
            _samplers.sampler_options(name, **options), self.upper - self.lower
        )

        def build(data):
            value_and_grad, log_density = dt.target(data)
            return _samplers.make_sampler(
                name, value_and_grad_fn=value_and_grad, logdensity_fn=log_density, **hyper
            )

        host = build(dt.data)  # name and settings (nothing is traced here)
        return _samplers.DataSamplingAlgorithm(build, dt.data, host.name, host.settings)

    def sampler(self, name: str = "nnsvgd", **options) -> _samplers.SamplingAlgorithm:
        """The sampler ``name`` (see :data:`treeinfer.inference.samplers.REGISTRY`) wired to this
        target, with the registry's default options updated by ``options``."""
        return _samplers.build_sampler(
            name,
            value_and_grad_fn=self.value_and_grad,
            logdensity_fn=self.log_density,
            box_width=self.upper - self.lower,
            **options,
        )


def make_problem(
    tree: Tree,
    trajectories: Sequence[Trajectory] | Observations,
    kT: float | str = DEFAULT_KT,
    nn_prior: bool = True,
    eta: float = DEFAULT_ETA,
    prior_sigma: float = DEFAULT_PRIOR_SIGMA,
    prior_space: str = "log",
    gradient: str = "fd",
    rel_step: float | None = None,
    substeps: int | None = None,
    max_sim_dt: float | None = None,
    grasp_fraction: float | None = None,
    model_file=None,
    sim: Simulator | None = None,
    nn_seed: int = 0,
    backend: str = "auto",
    force_interp: str = "linear",
    sim_tolerance: float | None = None,
    likelihood: str | None = None,
    noise_displacement: float | None = None,
    model_kind: str = "dynamic",
    direction=None,
    grasp_branch=None,
    model=None,
    noise_force="default",
    shape_bucket=None,
    noise_velocity: float | None = None,
    force_noise_reference=None,
    force_noise_rule: str = "J at the given reference",
) -> Problem:
    """Build the posterior target of ``tree`` given training ``trajectories``.

    Args:
      kT: Boltzmann temperature, a number or ``"auto"`` (from the data's noise estimate, see
        :mod:`treeinfer.model.likelihood` on choosing it).
      likelihood: ``"gaussian"`` (None, the default: recorded = simulated + white noise,
        sigma_x inferred jointly), ``"student_t"`` or ``"ar1"`` (generative noise models,
        :mod:`treeinfer.model.noise`), or ``"boltzmann"`` (the paper's loss with temperature
        ``kT``); built by :func:`treeinfer.model.likelihood.likelihood_terms`. A ``kT`` other than
        the default without ``likelihood`` is refused (before issue 27 it meant the Boltzmann loss).
      noise_displacement: m, fixed displacement noise sigma_x for the generative likelihoods
        (None: inferred as an extra column of theta) or the noise used by ``kT="auto"``.
      noise_force: ``"default"`` (the default: ``"auto"`` where the likelihood and model offer
        the term and the data let it be estimated, else off; :func:`default_noise_force`), None
        (off), or the recorded force's noise std (N, ``"P%"`` of the largest recorded
        force, or ``"auto"``: :func:`treeinfer.model.force_noise.resolve_noise_force`). With the
        paper's dynamic model: the errors-in-variables term of :mod:`treeinfer.model.force_noise`
        (gaussian likelihood). With ``model_kind="static"``: the load cell's noise read through
        each pull's compliance, ``sqrt(sigma_x^2 + (noise_force * compliance)^2)``
        (:func:`treeinfer.inference.static.model_likelihood_terms`, Gaussian/Student-t).
      force_noise_reference: ``[2R]`` log gains where the force-noise term's Jacobian is taken
        (dynamic model; None: :func:`treeinfer.model.force_noise.reference_theta`'s MAP fit; the
        start pipeline, :mod:`treeinfer.inference.start_pipeline`, passes its own MAP of the same
        model); force_noise_rule: how it was chosen (recorded).
      noise_velocity: None (default: the velocity term off) or m/s, the velocity residual's
        noise std for the generative likelihoods of the paper's model
        (:func:`treeinfer.model.likelihood.likelihood_terms`'s ``sigma_v``).
      nn_prior: add the learned inequality prior (NNSVGD's target); False gives SVGD's.
      eta: inequality penalty slope (nats per unit of log-gain the child exceeds its parent).
      gradient: ``"fd"`` (central differences, the paper's black-box route), ``"jvp"`` (exact
        forward-mode sensitivities of the simulator,
        :func:`~treeinfer.model.gradients.jvp_value_and_grad`)
        or ``"autodiff"`` (exact reverse mode; slow to compile, for checks).
      rel_step: finite-difference step in log units (default ~5e-3 for float32).
      grasp_fraction: where the training data were recorded (None: the tree's grasp).
      backend: simulator backend when ``sim`` is not given (see :func:`make_simulator`).
      force_interp, sim_tolerance, max_sim_dt: the simulator's force interpolation and step
        bounds when ``sim`` is not given (then the step is accuracy-controlled on the
        trajectories' forces; see :func:`make_simulator`).
      model_kind: ``"dynamic"`` (the rollout) or ``"static"`` (the equilibrium under each force
        sample, stiffness only: :mod:`treeinfer.inference.static`). ``tree.parameters == ("kp",)``
        (``inference: {parameters: [kp]}``) infers stiffness only with either model, damping
        held at :func:`treeinfer.inference.static.tree_layout`'s value; theta is then ``[log Kp]``.
      direction, grasp_branch: each training pull's direction ([3] or [B, 3] world vectors,
        default the tree's ``pull.direction``) and grasped branch (None or B names), for either
        model kind (one batched simulator call; see
        :func:`treeinfer.inference.static.model_with_pulls` for reading them from a data folder's
        ``pulls.yaml``). Every likelihood works with every model:
        :func:`treeinfer.inference.static.model_likelihood_terms`.
      model: a prebuilt :class:`treeinfer.inference.static.Model` (e.g. a
        :func:`~treeinfer.inference.static.tied_layout` of one stiffness scale); overrides
        ``model_kind``, ``direction`` and ``grasp_branch``.
      shape_bucket: None (the samplers' programs embed the data as constants, as before), or
        ``(B', T')`` at least the data's ``[B, T]``: the samplers' programs then take the data
        as an argument, padded to ``[B', T']`` and masked (:class:`DataTarget`), so another
        data set of that bucket reuses them (:func:`infer`'s ``cache``, and the persistent
        compile cache). Recorded as ``shape_bucket`` and ``sampler_data: "arguments"``.
        Applies to the paper's dynamic model (theta = [log Kp, log Kd] + noise columns); a
        static model, a stiffness-only layout or per-recording pulls keep the constants.
    """
    likelihood = resolve_likelihood(likelihood, kT)
    if not (isinstance(kT, str) and kT == "auto"):
        kT = check_kT(kT)
    if gradient not in GRADIENTS:
        raise ConfigError(f"gradient: expected one of {', '.join(GRADIENTS)}, got {gradient!r}")
    if not (isinstance(prior_sigma, (int, float)) and prior_sigma > 0):
        raise ConfigError(f"prior_sigma: must be positive, got {prior_sigma!r}")
    obs = (
        trajectories
        if isinstance(trajectories, Observations)
        else stack_trajectories(list(trajectories))
    )
    if noise_velocity is not None:
        if likelihood == "boltzmann":
            raise ConfigError(
                "--noise-velocity: the velocity term belongs to a generative likelihood "
                "(gaussian, student_t, ar1); the Boltzmann loss has its own velocity term"
            )
        v = np.asarray(obs.velocity, float)[np.asarray(obs.mask, bool)]
        # a sigma above everything the velocity column holds is a unit mistake, as for sigma_x
        noise.check_sigma(noise_velocity, "noise_velocity", float(np.ptp(v)) if v.size else None)
    if sim is None:  # the step accuracy-controlled on the training forces (sim_tolerance, m)
        kwargs = {} if max_sim_dt is None else {"max_sim_dt": max_sim_dt}
        if substeps is None:
            kwargs.update(
                forces=np.asarray(obs.force),
                sim_tolerance=sim_tolerance,
                grasp_fraction=grasp_fraction,
            )
        sim = make_simulator(
            tree,
            obs_dt=float(obs.dt),
            substeps=substeps,
            model_file=model_file,
            backend=backend,
            force_interp=force_interp,
            **kwargs,
        )
    from .static import model_for, model_likelihood_terms

    if model is None:
        model = model_for(tree, model_kind, direction, grasp_branch)
    tree, layout = model.tree, model.layout
    noise_force, force_note = default_noise_force(
        noise_force, likelihood, model.is_paper or model.kind == "static", obs
    )
    if model.is_paper:
        model = None  # the paper's model: theta = [log Kp, log Kd] (+ noise columns), as before
    options = dict(kT=kT, sigma_x=noise_displacement, grasp_fraction=grasp_fraction)
    grad_kind = "autodiff" if gradient == "jvp" else gradient
    if model is None:
        terms = likelihood_terms(
            sim,
            obs,
            likelihood,
            gradient=grad_kind,
            rel_step=rel_step,
            noise_force=noise_force,
            sigma_v=noise_velocity,
            force_noise_reference=force_noise_reference,
            force_noise_rule=force_noise_rule,
            **options,
        )
    else:  # the model's own rollout (static, stiffness only, per-recording pulls)
        if noise_velocity is not None:
            raise ConfigError(
                "--noise-velocity: the velocity term is available for the paper's dynamic model "
                "only (not for a static model, stiffness-only parameters, a tie or per-recording "
                "pulls)"
            )
        extra = {}
        if noise_force is not None:
            if model.kind != "static":
                raise ConfigError(
                    "--noise-force: available for the paper's dynamic model (an errors-in-"
                    "variables term through the force Jacobian) and for --model-kind static (the "
                    "load cell's noise read through each pull's compliance); not for a dynamic "
                    "model with stiffness-only parameters, a tie or per-recording pulls"
                )
            from ..model.force_noise import resolve_noise_force

            # one meaning of --noise-force for both models: N, 'P%' of the largest force, 'auto'
            extra["force_noise"], _ = resolve_noise_force(noise_force, obs)
        terms = model_likelihood_terms(
            sim, model, obs, likelihood, gradient=grad_kind, rel_step=rel_step, **options, **extra
        )
    loglik = terms.log_likelihood
    n_gains = layout.dim
    box = box_prior(tree, prior_sigma, prior_space, None if model is None else layout)
    prior_terms = [box if not terms.extra_labels else (lambda th: box(th[:, :n_gains]))]
    prior_terms += terms.log_prior_terms()
    kinds = ("Kp", "Kd") if layout.infers_damping else ("Kp",)
    # the learned inequality prior orders free per-joint stiffness columns; a tied layout (one
    # scale along the taper, :mod:`treeinfer.inference.static.tied`) has none, its taper orders them
    nn_prior = nn_prior and getattr(layout, "shape", None) is None
    nn = nn_inequality_prior(tree, eta=eta, seed=nn_seed, kinds=kinds) if nn_prior else None
    if nn is not None:
        prior_terms.append(nn)
    log_prior = combine(*prior_terms)

    def target(loglik):
        """``(value_and_grad, log_density)`` of ``loglik`` + the prior: the black-box likelihood
        by central differences (or forward mode, or reverse-mode autodiff for checks); priors
        by autodiff."""
        if gradient == "jvp":
            return jvp_combined_value_and_grad([loglik], [log_prior]), combine(loglik, log_prior)
        if gradient == "fd" and terms.black_box:
            black_box, differentiable = [loglik], [log_prior]
        else:  # autodiff, or a generative likelihood (its simulator carries an FD custom_jvp)
            black_box, differentiable = [], [loglik, log_prior]
        vg = combined_value_and_grad(black_box, differentiable, rel_step=rel_step)
        return vg, combine(loglik, log_prior)

    value_and_grad, log_density = target(loglik)
    data_target = None
    if shape_bucket is not None and model is None and terms.loglik_of is not None:
        # the sampler programs take the data as an argument, padded to the bucket and masked
        data = terms.data_of(obs, shape_bucket)
        data_target = DataTarget(
            value_and_grad,
            lambda data: target(terms.loglik_of(data)),
            data,
            tuple(int(n) for n in np.shape(data["force"])),
        )

    kT = terms.kT if terms.kT is not None else (DEFAULT_KT if isinstance(kT, str) else kT)
    # the paper's mode (Boltzmann, fixed kT, no noise given) records exactly what it did before
    # issue 11, so older interrupted runs still resume with identical settings
    paper_mode = terms.black_box and not terms.settings.get("kT_auto") and terms.sigma_x is None
    settings = {
        **({} if paper_mode else terms.settings),
        **dict(
            kT=kT,
            nn_prior=bool(nn is not None),
            eta=eta,
            prior_sigma=prior_sigma,
            prior_space=prior_space,
            gradient=gradient,
            rel_step=rel_step,
            backend=sim.backend,
            substeps=sim.substeps,
            sim_dt=sim.sim_dt,
            obs_dt=sim.obs_dt,
            force_interp=sim.force_interp,
            sim_step=dict(sim.step_info),
            grasp_fraction=grasp_fraction if grasp_fraction is not None else tree.grasp_fraction,
            n_trajectories=int(obs.force.shape[0]),
            n_steps=int(obs.force.shape[1]),
            nn_seed=nn_seed,
        ),
    }
    if force_note is not None:
        settings["noise_force_default"] = force_note
    if data_target is not None:
        settings["shape_bucket"] = list(data_target.shape)
        settings["sampler_data"] = "arguments"
    labels = tuple(layout.labels) + terms.extra_labels
    lower = np.concatenate([np.asarray(layout.lower), terms.extra_lower])
    upper = np.concatenate([np.asarray(layout.upper), terms.extra_upper])
    if model is not None:  # recorded only when not the default (older runs' settings unchanged)
        settings["model_kind"] = model.kind
        settings["parameters"] = list(layout.parameters)
        if not layout.infers_damping:
            settings["fixed_kd"] = [float(v) for v in layout.fixed_kd]
        if getattr(layout, "shape", None) is not None:  # one stiffness scale (TiedLayout)
            settings["kp_shape"] = [float(v) for v in layout.shape]
            if getattr(layout, "tie", None) is not None:
                settings["tie"] = layout.tie
                settings["tie_scale"] = layout.tau
        if model.grasp_branch is not None or model.direction is not None:
            settings["pulls"] = _pulls_record(model, int(obs.force.shape[0]))
    return Problem(
        tree=tree,
        sim=sim,
        obs=obs,
        kT=kT,
        labels=labels,
        lower=lower,
        upper=upper,
        log_likelihood=loglik,
        log_prior=log_prior,
        value_and_grad=value_and_grad,
        log_density=log_density,
        nn_prior=nn is not None,
        settings=settings,
        noise=terms,
        model=model,
        data_target=data_target,
    )


DEFAULT_LIKELIHOOD = "gaussian"
# a force-noise estimate below this share of the largest recorded force is float rounding
CLEAN_FORCE = 1e-9


def resolve_likelihood(likelihood: str | None, kT=DEFAULT_KT) -> str:
    """``likelihood`` or, for None, the default (:data:`DEFAULT_LIKELIHOOD`). A ``kT`` other than
    the default meant the Boltzmann loss while that was the default (before issue 27); given
    without a likelihood it is refused with what to pass, rather than silently ignored."""
    if likelihood is not None:
        return likelihood
    if not (isinstance(kT, (int, float)) and not isinstance(kT, bool) and kT == DEFAULT_KT):
        raise ConfigError(
            f"kT={kT!r} sets the temperature of the Boltzmann loss, which is no longer the "
            f"default likelihood (now {DEFAULT_LIKELIHOOD!r}: recorded = simulated + noise, the "
            "noise inferred); pass likelihood='boltzmann' with kT to keep the paper's loss, or "
            "leave kT out"
        )
    return DEFAULT_LIKELIHOOD


def default_noise_force(noise_force, likelihood: str, supported: bool, obs):
    """``(noise_force, note)``: ``"default"`` resolved to ``"auto"`` (the recorded force's noise
    estimated from the data, an errors-in-variables term) where the likelihood is Gaussian, the
    model offers the term (``supported``: the paper's dynamic model or the static one) and the
    force noise can be estimated; otherwise None (off) and ``note`` says why (recorded as the
    problem setting ``noise_force_default``). Any other value is returned as given."""
    if not (isinstance(noise_force, str) and noise_force == "default"):
        return noise_force, None
    if likelihood != "gaussian":
        return None, None
    if not supported:
        return None, "off: this model (stiffness only, a tie or per-recording pulls) has no term"
    from ..model.force_noise import estimate_force_noise

    try:
        est = estimate_force_noise(obs)
    except ConfigError as e:
        return None, f"off: {str(e).removeprefix('noise_force: ')}"
    f = np.abs(np.asarray(obs.force, float)[np.asarray(obs.mask, bool)])
    if f.size and est.sigma < CLEAN_FORCE * float(f.max()):
        # rounding in the second differences of a noise-free force (7.6e-17 N on a simulated
        # ramp): a term of no size that would still cost its Jacobian
        return None, f"off: the recorded force looks noise-free (estimate {est.sigma:.3g} N)"
    return "auto", None


def _pulls_record(model, n: int) -> dict:
    """JSON record of the training pulls: grasped branch and unit direction per trajectory."""
    branch = model.grasp_branch
    names = [branch] * n if branch is None or isinstance(branch, str) else list(branch)
    dirs = None
    if model.direction is not None:
        d = np.broadcast_to(np.asarray(model.direction, float), (n, 3))
        dirs = (d / np.linalg.norm(d, axis=1, keepdims=True)).round(9).tolist()
    return {"grasp_branch": names, "direction": dirs}


def initial_particles(problem: Problem, n_particles: int, seed: int = 0) -> jax.Array:
    """``[P, D]`` particles drawn uniformly in the (log) prior box; a noise scale's column in
    its start box (``problem.noise.extra_init``) instead."""
    check_count(n_particles, "n_particles")
    key = jax.random.fold_in(jax.random.key(int(seed)), 0x1A17)
    u = jax.random.uniform(key, (n_particles, problem.dim))
    theta = jnp.asarray(problem.lower) + u * jnp.asarray(problem.upper - problem.lower)
    return noise_start_columns(problem, theta, seed)


def noise_start_columns(problem: Problem, theta, seed: int = 0) -> jax.Array:
    """``theta [P, D]`` with the noise-scale columns (if any) drawn uniformly in their start box
    ``problem.noise.extra_init`` (near the data's noise estimate): the prior's box spans
    decades (issue 27), and a start spread over them costs the sampler its warm-up. For starts
    that do not fit the noise columns themselves (uniform, the Boltzmann-loss Laplace fit)."""
    init = getattr(getattr(problem, "noise", None), "extra_init", None)
    if init is None or not len(init[0]):
        return jnp.asarray(theta)
    theta = jnp.asarray(theta)
    lo, hi = (jnp.asarray(b, theta.dtype) for b in init)
    key = jax.random.fold_in(jax.random.key(int(seed)), 0x5161)
    u = jax.random.uniform(key, (theta.shape[0], lo.shape[0]), theta.dtype)
    return theta.at[:, -lo.shape[0] :].set(lo + u * (hi - lo))


def check_count(n, what: str, minimum: int = 1) -> int:
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < minimum:
        raise ConfigError(f"{what}: must be an integer >= {minimum}, got {n!r}")
    return int(n)


def _algorithm(problem: Problem, name: str, options: dict, cache):
    """``problem.sampler(name, **options)``, kept in ``cache`` (a ProgramCache or None) per
    (problem object, name, options): a later run of the same problem with that cache gets the
    same algorithm object, so the driver finds its compiled program there too."""
    if cache is not None and not isinstance(cache, ProgramCache):
        raise ConfigError(f"infer: cache must be a ProgramCache or None, got {cache!r}")
    try:
        key = ("sampler algorithm", problem, name, tuple(sorted(options.items())))
        hash(key)
    except TypeError:  # an option that is not hashable (an optax optimizer object, ...)
        key = None

    def build():  # the data as the programs' argument where the problem offers it
        algorithm = problem.data_sampler(name, **options)
        return problem.sampler(name, **options) if algorithm is None else algorithm

    if cache is None or key is None:
        return build()
    return cache.get(key, build)


def infer(
    problem: Problem,
    sampler: str = "nnsvgd",
    n_particles: int = 64,
    n_iterations: int = 200,
    seed: int = 0,
    progress: bool = True,
    initial_theta=None,
    callback=None,
    callback_every: int | None = None,
    initial_state=None,
    start_iteration: int = 0,
    trace_every: int | None = 1,
    stop_when=None,
    reinit_stragglers=None,
    cache=None,
    **sampler_options,
) -> Posterior:
    """Sample the posterior of ``problem`` with ``nnsvgd``, ``svgd``, ``sgld``, ``sghmc`` or ``mh``.

    Particles start uniformly in the prior box (seeded); MCMC samplers run one chain per
    particle. Returns a :class:`Posterior`; ``posterior.run.trace`` holds the particle and
    log-density trace. ``callback(iteration, state)`` every ``callback_every`` iterations is
    where checkpoints are written; ``initial_state``/``start_iteration`` resume exactly.
    ``stop_when`` (e.g. :class:`treeinfer.inference.diagnostics.ConvergenceCriterion`) and
    ``reinit_stragglers`` (:class:`treeinfer.inference.diagnostics.ReinitStragglers`) go to
    :func:`treeinfer.inference.samplers.run`, and so does ``cache`` (a
    :class:`~treeinfer.sim.program_cache.ProgramCache` the caller owns, where the compiled sampler
    program is kept for later runs of the same algorithm; None: compiled for this call only).
    """
    check_count(n_particles, "n_particles")
    check_count(n_iterations, "n_iterations")
    name = sampler.lower()
    spec = _samplers.sampler_spec(name)
    # a taper tie has no per-joint columns to order: nnsvgd is SVGD there (make_problem)
    tied = problem.model is not None and getattr(problem.model.layout, "shape", None) is not None
    if spec.nn_prior and not problem.nn_prior and problem.tree.inferred_pairs() and not tied:
        raise ConfigError(f"sampler '{name}' needs a problem built with nn_prior=True")
    algorithm = _algorithm(problem, name, sampler_options, cache)
    theta0 = (
        initial_particles(problem, n_particles, seed)
        if initial_theta is None
        else jnp.asarray(initial_theta)
    )
    result = _samplers.run(
        algorithm,
        jax.random.key(int(seed)),
        theta0,
        n_iterations,
        progress=progress,
        callback=callback,
        callback_every=callback_every,
        initial_state=initial_state,
        start_iteration=start_iteration,
        trace_every=trace_every,
        stop_when=stop_when,
        reinit_stragglers=reinit_stragglers,
        cache=cache,
    )
    theta = np.asarray(result.final_positions)
    # every sampler state carries log p at its positions: no extra (compiled) evaluation
    logp = np.asarray(result.final_state.logdensity)
    kp, kd = (
        gains_from_theta(theta, problem.sim.n_joints)
        if problem.model is None
        else problem.model.layout.gains(theta)
    )
    settings = {
        "problem": problem.settings,
        "sampler": name,
        "sampler_options": _samplers.sampler_options(name, **sampler_options),
        "n_particles": n_particles,
        "n_iterations": n_iterations,
        "seed": int(seed),
        "run": result.settings,
    }
    return Posterior(
        theta,
        np.asarray(kp),
        np.asarray(kd),
        logp,
        problem.labels,
        result,
        settings,
        context_from_problem(problem, result),
    )


__all__ = [
    "DataTarget",
    "Problem",
    "Posterior",
    "make_problem",
    "infer",
    "predict",
    "initial_particles",
    "noise_start_columns",
    "box_prior",
    "nn_inequality_prior",
]
