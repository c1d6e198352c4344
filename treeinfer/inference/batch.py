"""Many posteriors of one tree at once: the batched, compiled programs behind studies that refit
many data sets (``experiments/design_study.py``: seeds x second pulls).

:func:`posterior_program` runs NNSVGD (or SVGD) on C data sets in one ``jax.vmap``-ed, jitted
program whose data and temperatures are arguments, so a new batch of the same shape does not
recompile; :func:`map_fits` does the same for the Levenberg-Marquardt MAP fits that start them
(:func:`treeinfer.inference.mapfit.fit_map` compiles one program per data set, because the data are
constants of its closure: on a GPU, 100 data sets cost 100 compiles).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ConfigError
from ..sim.program_cache import ProgramCache

__all__ = ["map_fits", "posterior_program", "run_posteriors"]


# ==== many posteriors of one tree in one jitted program ==========================================
# No module-level program cache: callers that build the same program repeatedly pass their own
# ProgramCache (keyed by the content-hashed Simulator and the settings).


def posterior_program(
    tree,
    sim,
    n_iterations: int,
    *,
    sampler: str = "nnsvgd",
    learning_rate: float = 0.1,
    final_learning_rate: float | None = None,
    cache: ProgramCache | None = None,
):
    """One jitted program that runs the sampler on C data sets at once (``jax.vmap``).

    ``run(theta0 [C, P, D], seeds [C] int, kT [C], force [C, B, T] N, displacement [C, B, T] m,
    velocity [C, B, T] m/s, mask [C, B, T] bool, grasp [C, B]) -> (theta [C, P, D],
    log_density [C, P])``. Per data set it is the target of
    :func:`treeinfer.inference.problem.infer` (:func:`~treeinfer.inference.problem.make_problem`'s
    Boltzmann likelihood, box prior and, for ``"nnsvgd"``, the NN inequality prior; the likelihood
    by central differences, the priors by autodiff) with that data set's temperature ``kT`` (the
    log-likelihood of ``kT=1`` divided by it), and the sampler's init and per-iteration keys from
    ``jax.random.key(seed)``. The recordings and kT are arguments instead of constants closed over,
    so a new data set (or batch) of the same shape does not recompile; on a 2-core CPU a compile
    costs more than a run. Studies that refit many data sets use it
    (``experiments/design_study.py``).

    ``final_learning_rate``: None keeps Adam's step ``learning_rate`` (theta units) constant, as
    ``infer`` does; a value decays it along a cosine to that value over the ``n_iterations``, so
    the particles settle instead of jittering by about ``learning_rate`` around the stationary
    configuration (which matters where the posterior is much narrower than 0.1 log units).
    ``cache``: a :class:`~treeinfer.sim.program_cache.ProgramCache` the caller owns; the program is
    kept there per (sim, iterations, sampler, rates) and reused on the next call (jit caches the
    shapes). None: a new program."""
    from .problem import check_count

    n_iterations = check_count(n_iterations, "n_iterations")
    if sampler not in ("nnsvgd", "svgd"):
        raise ConfigError(f"sampler: expected 'nnsvgd' or 'svgd', got {sampler!r}")
    for name, v in (("learning_rate", learning_rate), ("final_learning_rate", final_learning_rate)):
        if v is not None and not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise ConfigError(f"{name}: must be a positive number, got {v!r}")
    # keyed by the simulator itself (hashed by content): id() may be reused after it is freed
    key_ = ("posterior", sim, n_iterations, sampler, learning_rate, final_learning_rate)
    return _cached(
        cache,
        key_,
        lambda: _posterior_program(
            tree, sim, n_iterations, sampler, learning_rate, final_learning_rate
        ),
    )


def _posterior_program(tree, sim, n_iterations, sampler, learning_rate, final_learning_rate):
    import optax

    from ..data.trajectories import Observations
    from ..model.gradients import combined_value_and_grad
    from .problem import make_problem
    from .samplers import init_key, iteration_key, nnsvgd, svgd

    if final_learning_rate is None:
        rate = float(learning_rate)
    else:
        rate = optax.cosine_decay_schedule(
            float(learning_rate), n_iterations, alpha=float(final_learning_rate) / learning_rate
        )
    make_alg = nnsvgd if sampler == "nnsvgd" else svgd

    def one(theta0, seed, kT, force, disp, vel, mask, grasp):
        obs = Observations(force, disp, vel, mask, float(sim.obs_dt))
        problem = make_problem(
            tree,
            obs,
            kT=1.0,
            sim=sim,
            grasp_fraction=grasp,
            nn_prior=sampler == "nnsvgd",
            likelihood="boltzmann",
        )
        loglik = lambda th: problem.log_likelihood(th) / kT
        vg = combined_value_and_grad([loglik], [problem.log_prior])
        alg = make_alg(vg, optimizer=optax.adam(rate))
        key = jax.random.key(seed)
        state = alg.init(init_key(key), theta0)
        state, _ = jax.lax.scan(
            lambda st, i: (alg.step(iteration_key(key, i), st)[0], None),
            state,
            jnp.arange(n_iterations),
        )
        return state.position, state.logdensity

    return jax.jit(jax.vmap(one))


def _cached(cache, key, build):
    if cache is None:
        return build()
    if not isinstance(cache, ProgramCache):
        raise ConfigError(f"cache: expected a ProgramCache or None, got {type(cache).__name__}")
    return cache.get(key, build)


def run_posteriors(program, theta0, seeds, kT, observations, grasp):
    """Run :func:`posterior_program`'s ``program`` on a list of C data sets.

    theta0: [C, P, D] starting particles; seeds: [C] ints; kT: [C] temperatures (or one number);
    observations: C :class:`~treeinfer.data.trajectories.Observations` of the same shape [B, T]
    (e.g. from :func:`~treeinfer.data.trajectories.stack_trajectories`); grasp: [C, B] grasp
    fractions. Returns numpy ``(theta [C, P, D], log_density [C, P])``."""
    if not observations:
        raise ConfigError("run_posteriors: no data sets given")
    shapes = {np.shape(o.displacement) for o in observations}
    if len(shapes) != 1:
        raise ConfigError(f"run_posteriors: data sets differ in shape [B, T]: {sorted(shapes)}")
    kT = np.broadcast_to(np.asarray(kT, np.float32), (len(observations),))
    if not np.all(np.isfinite(kT) & (kT > 0)):
        raise ConfigError(f"run_posteriors: kT must be positive numbers, got {kT.tolist()}")
    f32 = lambda a: np.asarray(a, np.float32)
    stack = lambda field: np.stack([getattr(o, field) for o in observations])
    theta, ld = program(
        f32(theta0),
        np.asarray(seeds, np.uint32),
        kT,
        f32(stack("force")),
        f32(stack("displacement")),
        f32(stack("velocity")),
        np.asarray(stack("mask"), bool),
        f32(grasp),
    )
    return np.asarray(theta), np.asarray(ld)


# ==== MAP fits of many data sets =================================================================


def _terms_program(tree, sim, nn_prior: bool, cache: ProgramCache | None = None):
    """jitted ``(theta [N, D], kT [N], force, displacement, velocity [N, B, T], mask [N, B, T],
    grasp [N, B]) -> (objective [N], gradient [N, D], curvature [N, D, D])`` of ``-log
    posterior`` with the Boltzmann loss as :func:`treeinfer.inference.mapfit.boltzmann_residuals`
    builds it (``kind="norm"``, central-difference Jacobian) and the prior of
    :func:`~treeinfer.inference.problem.make_problem`, through mapfit's own per-point terms."""
    # keyed by the simulator itself (hashed by content): id() may be reused after it is freed
    key_ = ("terms", sim, bool(nn_prior))
    return _cached(cache, key_, lambda: _build_terms_program(tree, sim, nn_prior))


def _build_terms_program(tree, sim, nn_prior: bool):
    from ..data.trajectories import Observations
    from ..model.likelihood import gains_from_theta
    from ..sim import simulate
    from .mapfit import ResidualModel, _terms_one
    from .problem import make_problem

    def one(theta, kT, force, disp, vel, mask, grasp):
        obs = Observations(force, disp, vel, mask, float(sim.obs_dt))
        problem = make_problem(
            tree,
            obs,
            kT=1.0,
            sim=sim,
            grasp_fraction=grasp,
            nn_prior=nn_prior,
            likelihood="boltzmann",
        )

        def residuals(th):  # as mapfit.boltzmann_residuals, with the data as arguments
            kp, kd = gains_from_theta(th[None, :], sim.n_joints)
            out = simulate(sim, kp, kd, force, grasp)
            m = mask.astype(out.tau.dtype)
            dpos = (out.tau[0] - disp) * m
            dvel = (out.tau_dot[0] - vel) * m
            return jnp.concatenate([dpos, dvel], axis=0), jnp.all(out.stable[0])

        model = ResidualModel(residuals, "norm", scale=kT)
        # (objective, gradient, curvature); the fourth term (grams) is for the Laplace start
        return _terms_one(model, problem.log_prior, "fd", None, theta)[:3]

    return jax.jit(jax.vmap(one))


def map_fits(
    tree,
    sim,
    kT,
    observations,
    grasp,
    *,
    n_starts: int = 6,
    seeds=None,
    nn_prior: bool = True,
    max_iterations: int = 25,
    tolerance: float = 1e-6,
    max_step: float = 1.0,
    cache: ProgramCache | None = None,
) -> list:
    """:func:`treeinfer.inference.mapfit.fit_map` (Boltzmann residuals, ``jacobian="fd"``) on C data
    sets at once: one compiled program for all of them and all their starts.

    kT: [C] temperatures (or one); observations: C
    :class:`~treeinfer.data.trajectories.Observations` of one shape [B, T]; grasp: [C, B]; seeds:
    [C] ints for each data set's Latin-hypercube starts (default 0..C-1). The Levenberg-Marquardt
    iteration is fit_map's, step for step, run on all ``C * n_starts`` points together (a point
    stops when it meets the tolerance, as there). Returns C
    :class:`~treeinfer.inference.mapfit.MapFit` (theta, Laplace ``cov``, ``hessian``, starts and
    finals of that data set), ready for
    :func:`~treeinfer.inference.mapfit.laplace_particles`. ``cache``: as
    :func:`posterior_program`'s."""
    from .lm import levenberg_marquardt
    from .mapfit import MapFit, latin_hypercube
    from .problem import make_problem

    c = len(observations)
    if c == 0:
        raise ConfigError("map_fits: no data sets given")
    if len({np.shape(o.displacement) for o in observations}) != 1:
        raise ConfigError("map_fits: data sets differ in shape [B, T]")
    if not (isinstance(n_starts, int) and n_starts >= 1):
        raise ConfigError(f"n_starts: must be an integer >= 1, got {n_starts!r}")
    kT = np.broadcast_to(np.asarray(kT, np.float32), (c,))
    if not np.all(np.isfinite(kT) & (kT > 0)):
        raise ConfigError(f"map_fits: kT must be positive numbers, got {kT.tolist()}")
    seeds = list(range(c)) if seeds is None else [int(s) for s in seeds]
    problem = make_problem(
        tree, observations[0], kT=1.0, sim=sim, nn_prior=False, likelihood="boltzmann"
    )
    lower, upper = np.asarray(problem.lower, float), np.asarray(problem.upper, float)
    starts = np.stack([latin_hypercube(n_starts, lower, upper, s) for s in seeds])  # [C, S, D]
    d = lower.size
    rep = lambda a: np.repeat(np.asarray(a), n_starts, axis=0)
    stack = lambda field: rep(np.stack([getattr(o, field) for o in observations]))
    data = (
        rep(kT),
        stack("force").astype(np.float32),
        stack("displacement").astype(np.float32),
        stack("velocity").astype(np.float32),
        stack("mask").astype(bool),
        rep(np.asarray(grasp, np.float32)),
    )
    prog = _terms_program(tree, sim, nn_prior, cache)
    dtype = jnp.asarray(0.0).dtype

    def evaluate(theta):
        return prog(jnp.asarray(theta, dtype), *data)

    # fit_map's Levenberg-Marquardt iteration, over all C * S points at once
    lm = levenberg_marquardt(evaluate, starts.reshape(-1, d), max_iterations, tolerance, max_step)
    theta, f, h, _, converged, iterations = lm
    fits = []
    for k in range(c):
        part = slice(k * n_starts, (k + 1) * n_starts)
        fk = f[part]
        best = int(np.argmin(np.where(np.isfinite(fk), fk, np.inf)))
        if not np.isfinite(fk[best]):
            from ..errors import SimulationError

            raise SimulationError(
                f"map_fits: data set {k}: every start gave an unstable simulation"
            )
        hess = 0.5 * (h[part][best] + h[part][best].T)
        settings = {"n_starts": n_starts, "seed": seeds[k], "jacobian": "fd", "kind": "norm"}
        settings.update(max_iterations=max_iterations, tolerance=tolerance, max_step=max_step)
        fits.append(
            MapFit(
                theta[part][best].copy(),
                np.linalg.pinv(hess),
                hess,
                float(fk[best]),
                starts[k],
                theta[part].copy(),
                fk.copy(),
                converged[part].copy(),
                iterations,
                lower,
                upper,
                d,
                settings,
            )
        )
    return fits
