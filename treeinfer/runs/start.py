"""A run's starting particles (``--init``): uniform in the box (the sampler's own), a Laplace
approximation around a MAP fit (``laplace``), or Pareto-smoothed importance sampling around the
mode (``importance``), which can be the posterior itself. Used by :mod:`.service` for new runs,
resumed runs that stopped before their first checkpoint, and k-fold refits."""

from __future__ import annotations

from collections.abc import Callable

import jax
import numpy as np

from ..errors import ConfigError, SimulationError

# For the Boltzmann loss laplace_particles draws the Gaussian matched to the loss's cone-shaped
# density (mapfit.norm_loss_covariance), not the Gauss-Newton H^-1, which is far too narrow at a
# small-residual mode; it is used as it is (scale 1): BENCHMARKS.md, "second pass (issue 15)".
LAPLACE_SCALE = 1.0
LAPLACE_LM_ITERATIONS = 40  # 25 left every start short of the mode on the standard problem


def _own_density(problem) -> bool:
    """True where the start runs on the problem's own log-density, not on the rollout program
    of the paper's model: another model (static, stiffness only, a tie), or observation channels
    besides the grasp point (:mod:`treeinfer.model.channels`)."""
    return getattr(problem, "model", None) is not None or bool(problem.settings.get("channels"))


def laplace_start(problem, config: dict, log: Callable[[str], None]):
    """Particles around a Levenberg–Marquardt MAP fit (``--init laplace``): its Laplace
    approximation, drawn with the run's seed. The residual Jacobian follows ``--gradients``."""
    from ..inference.laplace import particle_covariance
    from ..inference.mapfit import fit_problem, laplace_particles

    o = config["options"]
    if _own_density(problem):  # static, stiffness only, a taper tie, observation channels
        return _model_laplace_start(problem, o, log)
    jacobian = "jvp" if o.get("gradients", "fd") == "jvp" else "fd"
    fit = fit_problem(
        problem,
        "boltzmann",
        n_starts=6,
        seed=o["seed"],
        jacobian=jacobian,
        max_iterations=LAPLACE_LM_ITERATIONS,
    )
    # the spread the particles are drawn with (laplace_particles: the fit's precision plus the
    # prior box's), not the fit's own covariance, which is unbounded in columns the loss does
    # not see (a noise column under the Boltzmann fit printed a std of 2e4)
    std = np.sqrt(np.diag(particle_covariance(fit)))
    log(
        f"Laplace start: MAP from {len(fit.starts)} starts in {fit.iterations} LM iterations, "
        "start std (log units) " + ", ".join(f"{x:.3g}" for x in std)
    )
    theta = laplace_particles(
        jax.random.fold_in(jax.random.key(o["seed"]), 0x1A9),
        fit,
        o["particles"],
        scale=LAPLACE_SCALE,
    )
    # the Boltzmann-loss fit does not see the noise columns: start them near the data's noise
    # estimate, not over the prior's decades (issue 27)
    from ..inference.problem import noise_start_columns

    return noise_start_columns(problem, theta, o["seed"])


def _check_init(problem, options: dict) -> None:
    """ConfigError (before the run folder is made) if the problem does not support ``--init``.
    Every value works with every likelihood and model: the paper's dynamic model goes through
    the rollout program (:func:`treeinfer.inference.fast_evaluator.check_problem`), any other model
    through its own log-density (:mod:`treeinfer.inference.start_pipeline`)."""
    if options.get("init", "uniform") not in ("auto", "importance") or _own_density(problem):
        return
    from ..inference.fast_evaluator import check_problem

    try:
        check_problem(problem)
    except ConfigError as e:
        why = str(e).removeprefix("fast posterior: ")
        raise ConfigError(
            f"--init {options['init']}: {why}; use --init uniform or laplace"
        ) from None


def _start(problem, config: dict, log: Callable[[str], None], programs=None):
    """``(ready, theta0)`` for the run's ``--init``: ``ready`` a finished posterior (``--init
    importance`` whose importance weights pass their check: no sampler iterations) or None;
    ``theta0`` [P, D] the sampler's initial particles, None for the sampler's own (uniform).
    ``programs``: the command's :class:`~treeinfer.sim.program_cache.ProgramCache`
    (``SimulatorCache.programs``), where ``--init importance`` keeps its rollout program, so
    runs and folds whose data share a shape bucket compile it once."""
    o = config["options"]
    init = o.get("init", "uniform")
    if init == "laplace":
        return None, laplace_start(problem, config, log)
    if init in ("auto", "importance"):
        from ..inference.start_pipeline import auto_start

        _check_init(problem, o)
        options = {} if programs is None or _own_density(problem) else {"programs": programs}
        if init == "importance":
            return auto_start(problem, o["particles"], o["seed"], log, **options)
        try:
            return auto_start(problem, o["particles"], o["seed"], log, **options)
        except (SimulationError, np.linalg.LinAlgError) as e:
            # the pipeline found no stable start or no usable proposal: the sampler starts from
            # the prior box instead, and says so
            log(f"start pipeline failed ({e}); the sampler starts uniformly in the prior box")
            return None, None
    return None, None


def _model_laplace_start(problem, o: dict, log: Callable[[str], None]):
    """``--init laplace`` for any model other than the paper's (the LM fit needs its
    residuals): the MAP and Hessian of the problem's own log-density
    (:func:`treeinfer.inference.laplace.problem_laplace`), drawn with the run's seed."""
    from ..inference.laplace import problem_laplace, problem_laplace_particles

    exact = getattr(problem.model, "kind", None) == "static" and o.get("gradients") == "jvp"
    if exact:
        # exact derivatives (implicit function theorem through the equilibrium): Newton steps
        # reach the MAP and its Hessian, where the generic fit stopped short of it and its
        # covariance came out 7x too wide in log sigma_x (experiments/README.md, stem study)
        from ..inference.static import exact_laplace

        lap = exact_laplace(problem, seed=o["seed"])
    else:
        lap = problem_laplace(problem, seed=o["seed"])
    std = np.sqrt(np.diag(lap.cov))
    log(
        f"Laplace start: MAP of the log-density ({lap.n_evals} evaluations, "
        f"{'exact derivatives' if exact else 'generic fit'}), std "
        + ", ".join(f"{x:.3g}" for x in std)
    )
    return problem_laplace_particles(
        jax.random.fold_in(jax.random.key(o["seed"]), 0x1A9), lap, o["particles"]
    )


def held_evaluator(problem, posterior, cache):
    """The start pipeline's :class:`~treeinfer.inference.fast_evaluator.BatchEvaluator` of
    ``problem`` when ``cache`` (the command's :class:`~.cache.SimulatorCache`) still holds its
    compiled program and ``posterior`` came from it (its run settings record the batch and the
    draws, :func:`treeinfer.inference.fast.fast_posterior`), else None. The training fit runs the
    particles on it instead of compiling a prediction program of its own."""
    run = getattr(getattr(posterior, "run", None), "settings", None) or {}
    if cache is None or run.get("method") != "fast_posterior":
        return None
    from ..inference.fast_evaluator import default_chunk
    from ..inference.fast_evaluator import held_evaluator as held

    try:
        chunk = default_chunk(int(run["batch"]), int(run["n_draws"]))
    except (KeyError, TypeError, ValueError):
        return None
    return held(problem, cache.programs, chunk)
