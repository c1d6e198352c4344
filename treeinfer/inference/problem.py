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

from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ..data.trajectories import Observations, Trajectory, stack_trajectories
from ..errors import ConfigError
from ..model import noise
from ..model.boltzmann import DEFAULT_KT
from ..model.gradients import combine, combined_value_and_grad, jvp_combined_value_and_grad
from ..model.likelihood import gains_from_theta, likelihood_terms
from ..model.prior_terms import (  # noqa: F401 -- re-exported: their old home
    DEFAULT_ETA,
    DEFAULT_PRIOR_SIGMA,
    box_prior,
    nn_inequality_prior,
)
from ..sim import Simulator, make_simulator
from ..sim.program_cache import ProgramCache
from ..tree.description import Tree
from . import samplers as _samplers
from .posterior import Posterior, context_from_problem  # the result type of infer (issue 29)
from .problem_types import DataTarget, Problem
from .rollout import _predict_jit, _predict_traced, predict  # noqa: F401 -- moved (issue 29)
from .spec import (  # noqa: F401 -- re-exported: their old home
    CLEAN_FORCE,
    DEFAULT_LIKELIHOOD,
    GRADIENTS,
    ProblemSpec,
    default_noise_force,
    resolve_likelihood,
)


def make_problem(
    tree: Tree,
    trajectories: Sequence[Trajectory] | Observations,
    spec: ProblemSpec | None = None,
    *,
    sim: Simulator | None = None,
    **options,
) -> Problem:
    """Build the posterior target of ``tree`` given training ``trajectories``.

    Args:
      spec: a :class:`~treeinfer.inference.spec.ProblemSpec` (likelihood and noise, priors,
        gradients, simulator, model and pulls; every field documented there and validated when
        the spec is made). None: the defaults.
      sim: a compiled simulator to use (None: one is built from the spec's simulator fields,
        its step accuracy-controlled on the trajectories' forces).
      options: fields of the spec as keywords (``make_problem(tree, trajs, likelihood=
        "boltzmann", kT=0.05)``), applied over ``spec``; an unknown name is a ConfigError.
    """
    spec = ProblemSpec.from_options(spec, **options)
    likelihood = spec.resolved_likelihood
    kT, gradient, rel_step = spec.kT, spec.gradient, spec.rel_step
    grasp_fraction, noise_velocity = spec.grasp_fraction, spec.noise_velocity
    eta, prior_sigma, prior_space, nn_seed = (
        spec.eta,
        spec.prior_sigma,
        spec.prior_space,
        spec.nn_seed,
    )
    model, shape_bucket = spec.model, spec.shape_bucket
    obs = (
        trajectories
        if isinstance(trajectories, Observations)
        else stack_trajectories(list(trajectories))
    )
    if noise_velocity is not None:
        v = np.asarray(obs.velocity, float)[np.asarray(obs.mask, bool)]
        # a sigma above everything the velocity column holds is a unit mistake, as for sigma_x
        noise.check_sigma(noise_velocity, "noise_velocity", float(np.ptp(v)) if v.size else None)
    if sim is None:  # the step accuracy-controlled on the training forces (sim_tolerance, m)
        kwargs = {} if spec.max_sim_dt is None else {"max_sim_dt": spec.max_sim_dt}
        if spec.substeps is None:
            tolerance = spec.sim_tolerance
            if tolerance is None and spec.channels:  # a tenth of each channel's noise too
                from ..model.channels import channel_tolerance
                from ..sim import DEFAULT_SIM_TOLERANCE

                tol_ch = channel_tolerance(spec.channels, tree)
                tolerance = DEFAULT_SIM_TOLERANCE if tol_ch is None else min(tol_ch, 1e-4)
            kwargs.update(
                forces=np.asarray(obs.force),
                sim_tolerance=tolerance,
                grasp_fraction=grasp_fraction,
            )
        sim = make_simulator(
            tree,
            obs_dt=float(obs.dt),
            substeps=spec.substeps,
            model_file=spec.model_file,
            backend=spec.backend,
            force_interp=spec.force_interp,
            **kwargs,
        )
    from .static import model_for, model_likelihood_terms

    if model is None:
        model = model_for(tree, spec.model_kind, spec.direction, spec.grasp_branch)
    tree, layout = model.tree, model.layout
    noise_force, force_note = default_noise_force(
        spec.noise_force, likelihood, model.is_paper or model.kind == "static", obs
    )
    if model.is_paper:
        model = None  # the paper's model: theta = [log Kp, log Kd] (+ noise columns), as before
    options = dict(kT=kT, sigma_x=spec.noise_displacement, grasp_fraction=grasp_fraction)
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
            force_noise_reference=spec.force_noise_reference,
            force_noise_rule=spec.force_noise_rule,
            integration_error=spec.integration_error,
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
    if spec.channels:  # any model: the paper's, static, stiffness only, a tie, per-pull branches
        terms = _add_channels(terms, sim, trajectories, obs, spec, grasp_fraction, rel_step, model)
    loglik = terms.log_likelihood
    n_gains = layout.dim
    box = box_prior(tree, prior_sigma, prior_space, None if model is None else layout)
    prior_terms = [box if not terms.extra_labels else (lambda th: box(th[:, :n_gains]))]
    prior_terms += terms.log_prior_terms()
    kinds = ("Kp", "Kd") if layout.infers_damping else ("Kp",)
    # the learned inequality prior orders free per-joint stiffness columns; a tied layout (one
    # scale along the taper, :mod:`treeinfer.inference.static.tied`) has none, its taper orders them
    nn_prior = spec.nn_prior and getattr(layout, "shape", None) is None
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
        spec=spec,
    )


def _add_channels(terms, sim, trajectories, obs, spec, grasp_fraction, rel_step, model=None):
    """``terms`` with the observation channels' terms (:mod:`treeinfer.model.channels`); the
    channels name their pulls by file name, so the data must be trajectories (not stacked)."""
    from ..model.channels import channel_layout, with_channels

    if isinstance(trajectories, Observations):
        raise ConfigError(
            "channels: pass the trajectories (their file names tie each channel to its pull), "
            "not stacked Observations"
        )
    trajs = list(trajectories)
    layout = channel_layout(
        sim,
        spec.channels,
        [tr.source for tr in trajs],
        [float(tr.time[0]) for tr in trajs],
        [tr.n_steps for tr in trajs],
    )
    if model is None:  # the paper's rollout
        return with_channels(terms, sim, obs, layout, grasp_fraction, rel_step)
    from .static.channels import channel_rollout

    rollout = channel_rollout(sim, model, obs.force, layout.features, grasp_fraction)
    return with_channels(
        terms, sim, obs, layout, grasp_fraction, rel_step, model.layout.dim, rollout
    )


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
