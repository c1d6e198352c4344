"""The one start pipeline (``--init auto``, the default): a posterior from a global screen, a
multi-start MAP fit and importance sampling, for every likelihood and prior.

    ready, theta0 = auto_start(problem, n_particles=64, seed=0)
    # ready: a Posterior when the importance weights pass their check (no sampler needed);
    # theta0 [P, D]: the particles the sampler starts from otherwise

The paper's dynamic model (theta = [log Kp, log Kd] and the likelihood's noise columns) goes
through :func:`treeinfer.inference.fast.fast_posterior`: one compiled rollout program for the
gains, the likelihood's noise density evaluated on its residuals by a small program of its own
(:attr:`treeinfer.model.likelihood.LikelihoodTerms.residual_loglik`, the very function the problem's
likelihood uses), so noise columns (``sigma_x``, ...) cost no rollout. For the generative
likelihoods the Levenberg–Marquardt step of the MAP fit uses the generalised Gauss–Newton
curvature (:func:`ggn_terms`): the rollout is linearised by central differences, ``e(theta +
a) ~ e + J a``, and the noise density of the linearised residual is differentiated exactly in
``a`` and the noise columns (autodiff through the noise density only: a few microseconds);
the prior (smoothed box, the NN inequality prior, the noise priors of
:mod:`treeinfer.model.noise`) enters through its own autodiff derivatives. The importance weights
are then ``p / q`` with the problem's exact log-density, prior included.

With ``--noise-force`` the likelihood's force Jacobian is taken at a reference point, the MAP
of the errors-in-variables model
(:func:`treeinfer.model.force_noise_reference.reference_theta` finds it with two compiled LM
programs of its own, 30-200 s on a 2-core CPU). Here
(:func:`force_noise_reference`) the same two steps run on the one rollout program: the MAP of
the Gaussian model without the force term, then the MAP of the model whose force Jacobian is
taken there (sigma_x inferred jointly, where reference_theta fixes it at the data's estimate);
its gains are the reference.

Any other model (static, stiffness only, a tie, per-recording pulls), and the paper's model with
observation channels besides the grasp point (:mod:`treeinfer.model.channels`), goes through the
problem's own jitted log-density: :func:`treeinfer.inference.laplace.problem_laplace` for the MAP
and the covariance, then the same adaptive importance sampling (:func:`model_importance`).
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ConfigError
from .start_steps import (  # noqa: F401 -- re-exported: their import path before the move
    MAX_MODES,
    MODE_GAP,
    MODE_SEPARATION,
    distinct_modes,
    ggn_terms,
    multimode_importance,
    noise_guess,
    screen,
)

__all__ = [
    "auto_start",
    "channel_resample_move",
    "channel_starts",
    "force_noise_reference",
    "ggn_terms",
    "model_importance",
    "noise_guess",
]

# resample-move sweeps for a problem with observation channels: its start (Laplace at the
# generic fit's MAP) can sit off the mode of a sharp posterior (an inclinometer at 1 mrad), and
# the chains take more sweeps to get there (56 on the two-branch tree with a tilt sensor, where 40
# stopped short); a sweep costs one batched evaluation of the chains
CHANNEL_MAX_SWEEPS = 150

# LM iterations of each force-noise reference step (at most: as integration_floor.LM_ITERATIONS)
REFERENCE_LM_ITERATIONS = 40
# the force-noise reference: at most this many linearisations of the bias correction, taken
# again while the corrected MAP moves more than RELINEARISE_TOL log units from the reference
MAX_REFERENCE_ROUNDS = 3
RELINEARISE_TOL = 0.25
# the posterior's other lobes, each with its own linearisation (treeinfer.model.force_noise_local):
# an earlier round's MAP, or a final of the reference fits within LOBE_GAP nats of the best, is
# fitted again with the Jacobian taken at itself when it lies, in some stiffness, more than
# LOBE_SEPARATION log units AND LOBE_SDS standard deviations (the last fit's Laplace curvature)
# from every reference: a weakly identified damping spread over a log unit inside ONE lobe is not
# another lobe (SBC data set 90: a child's damping 1.2 log units, 1.2 sd, from the reference took
# a reference of its own before the other lobe, 0.8-1.4 log units and > 5 sd away in the
# stiffnesses, could). At most MAX_REFERENCES references in all. On data set 90 each lobe
# scored 2-4 nats BELOW the other when judged by the other's linearisation, so the gap is wide
LOBE_GAP = 10.0
# ... and a lobe takes its reference when, under its own linearisation, its MAP is within this
# many nats of the best: a lobe further down holds under e^-5 of the mass (less than the
# importance draws resolve), while each reference costs 1 + 2R force Jacobians and its share of
# every density evaluation (on the seed-0 standard problem a lobe that held no mass doubled the
# start pipeline's time: its k_hat went from 0.41 to 0.50 and resample-move ran)
LOBE_KEEP = 5.0
LOBE_SEPARATION = 0.5
LOBE_SDS = 3.0
MAX_REFERENCES = 3


def force_noise_reference(
    make: Callable,
    problem0,
    n_starts: int,
    seed: int,
    programs=None,
    log=lambda m: None,
    shape=None,
):
    """``(theta_ref [2R], finals [S, D])``: the force-noise term's reference (module docstring)
    and the final points of its second fit (the start pipeline's LM starts there).

    ``make(reference)`` builds the problem whose force Jacobian is taken at ``reference``
    (``[2R]`` log gains); ``problem0`` is the Gaussian problem without the force term. Both
    steps are :func:`treeinfer.inference.fast.fast_posterior`'s screen and LM on one rollout
    program (the evaluators share it through ``programs``; ``shape``: the observations' shape
    bucket ``[B', T']`` of the run's own fast posterior, so that it shares the program too)."""
    from .fast import resolve_coarse_substeps as coarse_of
    from .fast_evaluator import BatchEvaluator, default_chunk
    from .fast_fit import fit_map_batched
    from .screen_points import prior_range, screen_starts

    d, g = problem0.dim, 2 * problem0.sim.n_joints
    k = n_starts * (2 * g + 1)
    ev0 = BatchEvaluator(problem0, default_chunk(k, 8 * k), programs, shape)
    coarse = coarse_of(ev0, "auto")
    # the screen covers the prior, its tails beyond the box included (screen_points.prior_points)
    starts, pts = screen_starts(ev0, problem0, 4 * k, n_starts, seed, coarse)
    lower, upper = prior_range(problem0)
    first = fit_map_batched(ev0, starts, REFERENCE_LM_ITERATIONS, substeps=coarse)
    ref = np.clip(first.theta[:g], lower, upper)
    finals = first.finals[np.isfinite(first.values)]
    iterations, moves, history = [], [], [first.theta]
    for rounds in range(1, MAX_REFERENCE_ROUNDS + 1):
        problem1 = make(ref)
        ev1 = BatchEvaluator(problem1, ev0.chunk, programs, shape)
        if problem1.dim != d:
            raise ConfigError("force_noise_reference: the two problems have other columns")
        starts1 = finals
        if rounds == 1:
            # the bias correction can move the mode far from the uncorrected one (chain2 of
            # experiments/default_calibration.py: a child's damping from 0.04 to 0.6, 3.6 nats
            # higher), beyond the LM's reach from there: the screen's points are ranked again
            # under the corrected model and its best few start too
            lp1, pts1 = screen(ev1, pts, coarse)
            best = np.argsort(np.where(np.isfinite(lp1), -lp1, np.inf))[: max(2, n_starts // 2)]
            starts1 = np.vstack([finals, pts1[best[np.isfinite(lp1[best])]]])
        second = fit_map_batched(ev1, starts1, REFERENCE_LM_ITERATIONS, substeps=coarse)
        new = np.clip(second.theta[:g], lower, upper)
        iterations.append(second.iterations)
        moves.append(float(np.max(np.abs(new - ref))))
        ref = new
        history.append(second.theta)
        finals = second.finals[np.isfinite(second.values)]
        # the correction is first order in the log gains about the reference: taken again at
        # a MAP that moved far from it (RELINEARISE_TOL log units), until it stays
        if moves[-1] <= RELINEARISE_TOL:
            break
    log(
        "force-noise reference: MAP without the force term in "
        f"{first.iterations} LM iterations, then with it in "
        + " + ".join(str(i) for i in iterations)
        + (
            f" ({len(moves)} linearisations; the last moved the reference "
            f"{moves[-1]:.2f} log units)"
            if len(moves) > 1
            else ""
        )
    )
    order = np.argsort(second.values)
    finals = second.finals[order][np.isfinite(second.values[order])]

    def fit_at(reference, starts):  # LM with the Jacobian taken at ``reference``
        ev = BatchEvaluator(make(reference), ev0.chunk, programs, shape)
        return fit_map_batched(ev, starts, REFERENCE_LM_ITERATIONS, substeps=coarse)

    refs, lobes = lobe_references(
        fit_at, ref, second, history[:-1], lambda th: np.clip(th[:g], lower, upper), log
    )
    return (refs[0] if len(refs) == 1 else refs), np.vstack([finals, *lobes])


def lobe_references(fit_at, ref, last, earlier, gains_of, log=lambda m: None):
    """``(references [K, 2R], lobe finals [K - 1, D] list)``: ``ref`` (the reference loop's
    last) and one self-consistent reference per other lobe of the force-noise posterior
    (:mod:`treeinfer.model.force_noise_local`): each candidate (an ``earlier`` round's MAP, the
    latest first: a reference loop that flipped between lobes; then a final of ``last``, the last
    fit, within :data:`LOBE_GAP` nats of its best) that is a distinct lobe (module constants) is
    fitted by ``fit_at(reference, starts)`` with the Jacobian taken at itself, then at the
    fit's MAP when it moved (the term is first order about its reference); kept when it stays a
    distinct lobe within :data:`LOBE_KEEP` nats of ``last``'s best."""
    vals = np.asarray(last.values, float)
    ok = np.isfinite(vals)
    best = float(np.min(vals[ok]))
    near = [last.finals[i] for i in np.argsort(vals) if ok[i] and vals[i] <= best + LOBE_GAP]
    refs, lobes, gaps = [np.asarray(ref, float)], [], []
    cov = getattr(last, "cov", None)
    g = refs[0].size
    sd = np.ones(g) if cov is None else np.sqrt(np.clip(np.diag(cov)[:g], 1e-4, 1e2))

    def distinct(theta):
        # in the stiffnesses (the first R gains): J scales with the branch's compliance, while
        # a damping spread along a weakly identified direction is one lobe (the seed-0 standard
        # problem: the child's damping 2.4 log units apart at two MAPs 1.1 nats apart, the same
        # posterior with one reference or two, and twice the time with two)
        far = [np.abs(gains_of(theta) - r)[: g // 2] for r in refs]
        return all(np.any((d > LOBE_SEPARATION) & (d > LOBE_SDS * sd[: g // 2])) for d in far)

    for cand in [*earlier[::-1], *near]:
        if len(refs) >= MAX_REFERENCES:
            break
        if not distinct(cand):
            continue
        start, at = np.asarray(cand, float), gains_of(cand)
        for _ in range(2):
            fit = fit_at(at, start[None])
            moved = float(np.max(np.abs(gains_of(fit.theta) - at)))
            start, at = fit.theta, gains_of(fit.theta)
            if moved <= RELINEARISE_TOL:
                break
        gap = fit.neg_log_posterior - best
        if gap <= LOBE_KEEP and distinct(start):
            refs.append(at)
            lobes.append(start)
            gaps.append(gap)
    if len(refs) > 1:
        log(
            f"force-noise reference: {len(refs)} lobes (MAPs "
            + ", ".join(f"{v:+.1f}" for v in gaps)
            + " nats from the first's, each under its own linearisation), the force Jacobian "
            "taken in each (the term is first order about its reference)"
        )
    return np.stack(refs), lobes


def channel_starts(problem, seed: int = 0, n: int = 8, log=lambda m: None) -> np.ndarray:
    """``[n, D]`` start points for a problem with observation channels: the grasp-point-only
    problem's start pipeline (the rollout program's multi-start LM fit and importance draws,
    far more robust than random starts of the generic fit, which on the two-branch tree stopped
    in a mode 4x off in Kp), each channel's ``log sigma`` then set by a line search of the full
    log-density over its prior box."""
    from .fast import importance_for_run
    from .problem import make_problem

    base = make_problem(
        problem.tree, problem.obs, problem.spec.replace(channels=()), sim=problem.sim
    )
    _, theta0 = importance_for_run(base, max(16, n), seed, lambda m: None)
    theta0 = np.asarray(theta0, float)
    fn = jax.jit(problem.log_density)
    lp0 = np.asarray(jax.jit(base.log_density)(jnp.asarray(theta0, jnp.float32)), float)
    d0, lower, upper = base.dim, np.asarray(problem.lower), np.asarray(problem.upper)
    starts = theta0[np.argsort(-np.nan_to_num(lp0, nan=-np.inf))[:n]]
    starts = np.concatenate([starts, np.tile(0.5 * (lower[d0:] + upper[d0:]), (len(starts), 1))], 1)
    grid = np.linspace(0.0, 1.0, 17)
    for j in range(d0, problem.dim):  # one column at a time: 17 candidates per start
        cand = np.repeat(starts, len(grid), axis=0)
        cand[:, j] = np.tile(lower[j] + grid * (upper[j] - lower[j]), len(starts))
        lp = np.asarray(fn(jnp.asarray(cand, jnp.float32)), float).reshape(len(starts), -1)
        starts[:, j] = cand.reshape(len(starts), len(grid), -1)[
            np.arange(len(starts)), np.argmax(np.nan_to_num(lp, nan=-np.inf), axis=1), j
        ]
    log(f"channel starts: {len(starts)} points from the grasp-point fit")
    return starts


def model_importance(
    problem, n_particles: int, seed: int = 0, n_draws: int | None = None, extra=None
):
    """:class:`treeinfer.inference.fast_result.FastPosterior`-like ``(theta [P, D], ok, reason,
    importance, lap)`` for a problem the rollout program does not run (static model, stiffness
    only, a tie, per-recording pulls): the MAP and covariance of its own log-density
    (:func:`treeinfer.inference.laplace.problem_laplace`), then Student-t adaptive importance
    sampling with weights from ``problem.log_density`` (exact)."""
    from .fast import DEFAULT_DF
    from .importance import adaptive_importance
    from .laplace import problem_laplace

    lap = problem_laplace(problem, seed=seed, extra=extra)
    fn = jax.jit(problem.log_density)
    m = max(8 * problem.dim * 8, 4 * int(n_particles)) if n_draws is None else int(n_draws)
    dtype = jnp.asarray(0.0).dtype

    def log_density(x):
        return np.asarray(fn(jnp.asarray(x, dtype)), float)

    imp, idx = adaptive_importance(
        log_density, lap.theta, lap.cov, m, int(n_particles), seed, DEFAULT_DF, 3,
        4.0 * n_particles, min_ess=2.0 * n_particles,
    )  # fmt: skip
    return imp._replace(theta=imp.draws[idx]), idx, lap


def auto_start(problem, n_particles: int, seed: int = 0, log=lambda m: None, **options):
    """``(posterior or None, theta0 [P, D])`` of the start pipeline (module docstring):
    ``posterior`` (:func:`treeinfer.inference.fast_result.posterior_from_fast`) when the importance
    weights pass their check, else None and the sampler starts from ``theta0``. ``options`` go
    to :func:`treeinfer.inference.fast.fast_posterior` (the paper's dynamic model)."""
    from .fast import importance_for_run

    if problem.model is None and not problem.settings.get("channels"):
        if problem.start_hint is not None and "starts" not in options:
            # the MAP fit is done (the force-noise reference's): a few LM steps from its finals
            options = {"starts": problem.start_hint, "max_iterations": 5, **options}
        return importance_for_run(problem, n_particles, seed, log, **options)
    return _model_start(problem, n_particles, seed, log)


def channel_resample_move(problem, imp, n_particles: int, seed: int, log):
    """Untrusted importance weights of a problem with observation channels: resample-move
    (:mod:`treeinfer.inference.resample_move`) on the problem's own jitted log-density.
    ``(MoveResult, theta [P, D], log density [P] or None when the cloud did not settle)``."""
    import time

    from .resample_move import resample_move

    fn = jax.jit(problem.log_density)
    dtype = jnp.asarray(0.0).dtype
    t0 = time.perf_counter()
    mv = resample_move(
        lambda x: np.asarray(fn(jnp.asarray(x, dtype)), float),
        imp.draws, imp.log_weights, imp.log_density, int(n_particles), seed=seed,
        max_sweeps=CHANNEL_MAX_SWEEPS,
    )  # fmt: skip
    log(
        f"resample-move: {mv.describe()}, {time.perf_counter() - t0:.0f} s: "
        + ("used as the posterior" if mv.ok else f"not settled ({mv.reason}): the sampler runs")
    )
    theta = np.asarray(mv.theta, np.float32)
    return mv, theta, (np.asarray(mv.log_density, np.float32) if mv.ok else None)


def _model_start(problem, n_particles: int, seed: int, log):
    """:func:`auto_start` for a model the rollout program does not run."""
    from .fast_result import importance_run_result
    from .problem import Posterior

    extra = None
    if problem.settings.get("channels"):
        from .static.dynamic_starts import static_first_starts

        # a quasi-static pull (a winch ramp): the static model's fit seeds the dynamic one
        extra = static_first_starts(problem, seed, log=log)
        if extra is None and problem.model is None:
            extra = channel_starts(problem, seed, log=log)
    imp, idx, lap = model_importance(problem, n_particles, seed, extra=extra)
    verdict = (
        "used as the posterior (no sampler iterations)"
        if imp.ok
        else f"not trusted ({imp.reason}): the sampler runs from these particles"
    )
    log(
        f"importance posterior: MAP of the log-density ({lap.n_evals} evaluations), "
        f"{len(imp.draws)} draws in {imp.rounds} rounds, Pareto k_hat {imp.khat:.2f}, "
        f"effective sample size {imp.ess:.0f}: {verdict}"
    )
    theta = np.asarray(imp.theta, np.float32)
    logp = np.asarray(imp.log_density[idx], np.float32) if imp.ok else None
    moved = None
    if not imp.ok and problem.settings.get("channels"):  # channels (any model): resample-move
        moved, theta, logp = channel_resample_move(problem, imp, n_particles, seed, log)
    if logp is None:
        return None, theta
    run_settings = {
        "method": "model_importance",
        "khat": imp.khat,
        "ess": imp.ess,
        "n_draws": len(imp.draws),
        "lm_iterations": 0,
        "importance_rounds": imp.rounds,
        "n_iterations": 0,
        "n_iterations_done": 0,
        "start_iteration": 0,
        "seed": seed,
        **({"resample_move": moved.settings()} if moved is not None else {}),
    }
    reason = None
    if moved is not None:
        reason = (
            f"resample-move after importance sampling (Pareto k_hat {imp.khat:.2f}): "
            f"{moved.sweeps} Metropolis sweeps, the cloud settled"
        )
    run = importance_run_result(theta, logp, run_settings, imp, 0.0, reason)
    if problem.model is None:  # the paper's model with observation channels
        from ..model.likelihood import gains_from_theta

        kp, kd = gains_from_theta(theta, problem.sim.n_joints)
    else:
        kp, kd = problem.model.layout.gains(theta)
    settings = {
        "problem": problem.settings,
        "sampler": "importance",
        "sampler_options": {"n_draws": len(imp.draws)},
        "n_particles": len(theta),
        "n_iterations": 0,
        "seed": int(seed),
        "run": run_settings,
    }
    return Posterior(
        theta, np.asarray(kp), np.asarray(kd), logp, problem.labels, run, settings
    ), theta
