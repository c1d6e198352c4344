"""A posterior in seconds on a CPU: one compiled rollout program, a screened MAP fit and
importance sampling, no sampler iterations.

    result = fast_posterior(problem, n_particles=128)
    result.theta          # [P, D] posterior particles; result.ok says whether to trust them

The steps, all through **one** jitted batched rollout of a fixed number of parameter sets
(:class:`BatchEvaluator`; on a 2-core CPU each extra XLA program of the standard problem costs
3-12 s to compile, more than the work it does). Its batch is K below on a CPU and an importance
round's draws on an accelerator (:func:`default_chunk`: latency-bound there, so one run a round):

1. **Screen**: the Boltzmann loss at ``n_screen`` Latin-hypercube points of the prior box (no
   gradients); the ``n_starts`` lowest are the starting points.
2. **Levenberg–Marquardt** from them (the same damped Gauss–Newton step as
   :func:`treeinfer.inference.mapfit.fit_map`, kind ``"norm"``), with the residual Jacobian by
   central differences: each iteration evaluates the ``n_starts * (2D + 1)`` points of one call (=
   K). The prior enters through its values at the same points (gradient and PSD-clipped diagonal
   curvature by central differences); it is smooth on the step's scale.
3. **Importance sampling** (:mod:`treeinfer.inference.importance`) from the Student-t (df
   :data:`DEFAULT_DF`) matched to the Boltzmann loss at the mode
   (:func:`treeinfer.inference.laplace.norm_loss_covariance`, plus the box's precision), ``n_draws``
   draws weighted by ``p / q`` with Pareto smoothing, then, while the effective sample size is
   below ``4 P`` (at most 3 rounds), ``n_draws`` more from the weighted draws' moments, all
   reweighted against the mixture of the proposals
   (:func:`treeinfer.inference.importance.adaptive_importance`). The ``P`` particles are one draw
   per equal-weight stratum along the draws' leading prediction component
   (:func:`treeinfer.inference.importance.sorted_resample`). ``ok`` is ``k_hat <= 0.7``, an
   effective sample size of at least ``2 P``, and the even and odd draws' training bands within 20 %
   (:func:`treeinfer.inference.importance.band_split`, a guard against gross instability).

On the standard problem (10 seeds, ``experiments/importance_robustness.py``, 2-core CPU, 4
substeps; the held-out band against an exact one, 8.58 mm: 16384 Student-t importance draws,
averaged over 32 subsets of 128 particles) the former path (the fit's Gaussian, one round, 832
draws, ESS 37-169) scattered by 6.5 % (sd), worst 10.2 %; this one (Student-t, three rounds,
sorted resampling, ESS 634-888): mean -0.6 %, sd 3.9 %, worst 5.9 %. 128 exact posterior draws
scatter by 6.6 % themselves.

**Multi-fidelity** (``coarse_substeps``, default ``"auto"``: the stability step, 4 substeps on
the standard problem against the accuracy-controlled 14): the rollout program takes the step as
an argument (one compiled program), the screen, the LM fit (15 iterations) and two importance
rounds run at the coarse step, at about a third of the cost; the coarse rounds' weighted moments
are the first proposal of the accurate step's rounds, and only the accurate rounds' draws are
weighted and returned, so the result targets the accurate posterior exactly (any proposal gives
correct weights; ``tests/test_fast_posterior_multifidelity.py`` checks the weighted moments
against quadrature at the accurate step where the coarse posterior is measurably elsewhere).
Rollout-program runs on the standard problem (batch 104): before, 60 at 14 substeps; now 37 at
4 and 16-24 at 14.

Why not :func:`treeinfer.inference.mapfit.fit_problem` then ``problem.log_density``: that is three
programs (the LM's value/gradient/curvature with its vmapped Jacobian, the log-density at M
draws, the sampler's chunk), 11-14 s of compilation each on the 2-core box; here the LM,
screening and weights are NumPy on the host around one rollout program (D is small; the
log-prior, which holds no data, is a second small program).

Only the paper's model and loss: ``theta = [log Kp, log Kd]``, the Boltzmann likelihood.

The pieces live in modules of their own (issue 26), all re-exported here:
:mod:`treeinfer.inference.fast_evaluator` (the rollout program),
:mod:`treeinfer.inference.fast_fit` (the screen's points and the batched LM) and
:mod:`treeinfer.inference.fast_result` (the result and its conversion for the run layer); this
module runs the pipeline.
"""

from __future__ import annotations

import math
import time

import numpy as np

from ..errors import ConfigError
from .fast_evaluator import (  # noqa: F401 -- re-exported: they lived here before the split
    BatchEvaluator,
    _rollout_residuals,
    check_problem,
    default_chunk,
)
from .fast_fit import _lm_terms, fit_map_batched, latin_hypercube  # noqa: F401 -- re-exported
from .fast_result import (  # noqa: F401 -- re-exported: they lived here before the split
    FastPosterior,
    ParticleState,
    importance_run_result,
    posterior_from_fast,
)

# the coarse-step importance rounds draw with seed + COARSE_SEED (the accurate step's with seed)
COARSE_SEED = 7919
# Student-t proposals (every round): Gaussian ones leave the posterior's tails short, so the
# band came out 5-6 % narrow on average (experiments/importance_robustness.py, BENCHMARKS.md)
DEFAULT_DF = 8.0
# accurate-step LM iterations after the coarse fit for a generative likelihood (importance_for_run)
GENERATIVE_POLISH = 20

__all__ = [
    "DEFAULT_DF",
    "BatchEvaluator",
    "FastPosterior",
    "ParticleState",
    "default_chunk",
    "fast_posterior",
    "fit_map_batched",
    "importance_for_run",
    "posterior_from_fast",
    "resolve_coarse_substeps",
]


def fast_posterior(
    problem,
    n_particles: int = 128,
    n_starts: int = 8,
    n_screen: int | None = None,
    n_draws: int | None = None,
    max_iterations: int | None = None,
    tolerance: float = 1e-4,
    df: float = DEFAULT_DF,
    seed: int = 0,
    evaluator: BatchEvaluator | None = None,
    max_rounds: int = 3,
    target_ess: float | None = None,
    programs=None,
    coarse_substeps: int | str | None = "auto",
    polish_iterations: int = 0,
    coarse_rounds: int = 2,
    starts=None,
) -> FastPosterior:
    """Posterior particles of ``problem`` without sampler iterations (module docstring).

    Args:
      problem: a :func:`treeinfer.inference.problem.make_problem` problem (dynamic model,
      Boltzmann). n_particles: P particles returned.
      n_starts: LM starting points S; the program's batch is ``K = S (2D + 1)`` sets.
      n_screen: screened box points (default ``4 K``). n_draws: importance draws (default
        ``8 K``, at least ``4 P``; the Pareto k_hat needs several hundred to be reliable: with
        256 draws of a near-perfect proposal it read 1-2 on a one-joint test, a false alarm).
        max_iterations, tolerance: of the LM (:func:`fit_map_batched`). df: Student-t degrees
        of freedom of the importance proposals (:data:`DEFAULT_DF`; inf: Gaussian). seed: of
        the screen, the draws and the resample.
      evaluator: a :class:`BatchEvaluator` of the same problem to reuse (any batch; default
        :func:`default_chunk`).
      programs: a :class:`~treeinfer.sim.program_cache.ProgramCache` for the evaluator's rollout
        program (shared by every data set of one shape bucket, :class:`BatchEvaluator`).
      max_rounds, target_ess: :func:`treeinfer.inference.importance.adaptive_importance`: while the
        effective sample size is below ``target_ess`` (default ``4 P``), up to ``max_rounds``
        rounds of ``n_draws`` each, the later ones from the weighted draws' moments; ``ok``
        needs ``min(target_ess, 2 P)``.
      coarse_substeps: multi-fidelity: the screen and the LM fit simulate with this many
        substeps per observation (a cheaper, less accurate step), the importance weights with
        the simulator's own (accurate) step, so the posterior is still the accurate one: any
        proposal gives exact weights, the fit only has to place it near the mode. ``"auto"``:
        the step that is merely stable (``sim.step_info["stability_substeps"]``) when it is
        coarser than the simulator's and the rollout program takes the step as an argument
        (:class:`BatchEvaluator` ``traced``; the Pallas kernel only with
        :data:`treeinfer.sim.pallas.TRACED_SUBSTEPS`, the default), else the simulator's own;
        None: the simulator's own everywhere.
      polish_iterations: LM iterations at the accurate step from the coarse fit's mode (0:
        none; each costs one program run).
      coarse_rounds: with a coarse step, importance rounds at that step
        (:func:`treeinfer.inference.importance.adaptive_importance` from the fit's proposal) before
        the accurate step's: their weighted draws' mean and covariance are the first proposal of the
        accurate rounds (Student-t, ``df``), the accurate rounds adapt further (``max_rounds``)
        and only their draws are weighted and returned. On the standard problem the fit's own
        Student-t gives an effective sample size of 50-70 of 832 draws, the coarse posterior's
        180-270; the coarse rounds cost about a third of accurate ones (4 against 14 substeps).
      max_iterations (None): 15 with a coarse step (the coarse importance rounds re-centre the
        proposal), else 30.
      starts: ``[S, D]`` LM starting points instead of the screen's (e.g. a MAP found before,
        :func:`treeinfer.inference.start_pipeline.force_noise_reference`); None: screen the box.
    """
    from .importance import (
        BAND_SPLIT_LIMIT,
        adaptive_importance,
        band_split,
        leading_projection,
        proposal_from_fit,
        sorted_resample,
        weighted_moments,
    )

    for name, v in (("n_particles", n_particles), ("n_starts", n_starts)):
        if not (isinstance(v, (int, np.integer)) and v >= 1):
            raise ConfigError(f"{name}: must be an integer >= 1, got {v!r}")
    # one LM iteration's batch: the central differences in the gains (2R of them; a generative
    # likelihood's noise columns need no rollout, start_steps.ggn_terms), so the force-noise
    # reference's fits (start_pipeline.force_noise_reference) and this one share the program
    k = n_starts * (4 * problem.sim.n_joints + 1)
    n_screen = 4 * k if n_screen is None else int(n_screen)
    n_draws = max(8 * k, 4 * n_particles) if n_draws is None else int(n_draws)
    if n_screen < n_starts:
        raise ConfigError(f"n_screen: must be >= n_starts ({n_starts}), got {n_screen}")
    if not (isinstance(coarse_rounds, (int, np.integer)) and coarse_rounds >= 0):
        raise ConfigError(f"coarse_rounds: must be an integer >= 0, got {coarse_rounds!r}")
    if not (isinstance(polish_iterations, (int, np.integer)) and polish_iterations >= 0):
        raise ConfigError(f"polish_iterations: must be an integer >= 0, got {polish_iterations!r}")
    if evaluator is None:
        evaluator = BatchEvaluator(problem, default_chunk(k, n_draws), programs)
    ev = evaluator
    if ev.problem is not problem:
        raise ConfigError("evaluator: built for another problem")
    coarse = resolve_coarse_substeps(ev, coarse_substeps)
    if max_iterations is None:
        max_iterations = 15 if coarse != ev.substeps and coarse_rounds > 0 else 30
    phases, t = {}, time.perf_counter()
    lower = np.asarray(problem.lower, float)
    ev.evaluate(lower[None], coarse)  # compile (and run once)
    phases["compile"], t = time.perf_counter() - t, time.perf_counter()
    from .screen_points import screen_starts

    if starts is None:
        starts, _ = screen_starts(ev, problem, n_screen, n_starts, seed, coarse)
    else:
        starts = np.atleast_2d(np.asarray(starts, float))
    phases["screen"], t = time.perf_counter() - t, time.perf_counter()
    fit = fit_map_batched(ev, starts, max_iterations, tolerance, substeps=coarse)
    coarse_fit = fit
    modes = None
    if polish_iterations and coarse != ev.substeps:
        from .start_steps import distinct_modes

        # every distinct local mode of the multi-start fit within MODE_GAP nats is polished
        # and sampled (start_pipeline.multimode_importance), not the best one alone
        modes = distinct_modes(fit, proposal_from_fit(fit)[1])
        fit = fit_map_batched(ev, modes, polish_iterations, tolerance)
        modes = distinct_modes(fit, proposal_from_fit(fit)[1])
    phases["map_fit"], t = time.perf_counter() - t, time.perf_counter()
    mean, cov = proposal_from_fit(fit)
    target = 4.0 * n_particles if target_ess is None else float(target_ess)
    coarse_imp = None
    if coarse != ev.substeps and coarse_rounds > 0:
        # the proposal: the coarse step's own (importance-weighted) posterior, whose shape the
        # fit's Gaussian matches poorly (effective sample size 50-70 of 832 draws)
        coarse_imp, _ = adaptive_importance(
            lambda x: ev.log_density(x, coarse), mean, cov, n_draws, int(n_particles),
            seed + COARSE_SEED, float(df), int(coarse_rounds), target,
        )  # fmt: skip
        if np.isfinite(coarse_imp.ess) and coarse_imp.ess >= 2 * len(mean):
            mean, cov = weighted_moments(coarse_imp.draws, coarse_imp.log_weights)
        phases["coarse_importance"], t = time.perf_counter() - t, time.perf_counter()
    mask = np.asarray(problem.obs.mask, bool)
    kept = []  # each draw's displacement residual at the data's points, for the band check

    def log_density(theta):
        out, r = ev.log_density_terms(theta)
        kept.append(r[:, : mask.shape[0]][:, mask])
        return out

    if modes is not None and len(modes) > 1:
        from .start_steps import multimode_importance

        imp, idx = multimode_importance(
            log_density, modes, cov, n_draws, int(n_particles), seed, float(df), max_rounds,
            target, min(target, 2.0 * n_particles),
        )  # fmt: skip
    else:
        imp, idx = adaptive_importance(
            log_density, mean, cov, n_draws, int(n_particles), seed, float(df), max_rounds,
            target, min_ess=min(target, 2.0 * n_particles),
        )  # fmt: skip
    pred = np.concatenate(kept) + np.asarray(problem.obs.displacement, float)[mask]
    width_a, width_b, split = band_split(pred, imp.log_weights)
    # the particles: one draw per equal-weight stratum along the predictions' leading component
    idx = sorted_resample(
        seed, imp.log_weights, int(n_particles), leading_projection(pred, imp.log_weights)
    )
    imp = imp._replace(theta=imp.draws[idx])
    theta, khat, ess, ok, reason = imp.theta, imp.khat, imp.ess, imp.ok, imp.reason
    if not split <= BAND_SPLIT_LIMIT:
        ok = False
        why = (
            f"the two halves of the draws give training bands {width_a * 1e3:.2f} and "
            f"{width_b * 1e3:.2f} mm wide ({100 * split:.0f}% apart > "
            f"{100 * BAND_SPLIT_LIMIT:.0f}%)"
        )
        reason = f"{reason}; {why}" if reason else why
        imp = imp._replace(ok=False, reason=reason)
    phases["importance"] = time.perf_counter() - t
    settings = {
        "method": "fast_posterior",
        "n_starts": n_starts,
        "batch": k,
        "n_screen": n_screen,
        "n_draws": n_draws,
        "df": None if math.isinf(df) else df,
        "lm_iterations": coarse_fit.iterations,
        "n_fit_starts": len(coarse_fit.starts),
        "lm_values": [float(v) for v in coarse_fit.values],
        "substeps": ev.substeps,
        "fit_substeps": coarse,
        "polish_iterations": fit.iterations if fit is not coarse_fit else 0,
        "coarse_importance": None
        if coarse_imp is None
        else {"rounds": coarse_imp.rounds, "ess": coarse_imp.ess, "khat": coarse_imp.khat},
        "program_runs_by_substeps": {str(s): n for s, n in sorted(ev.runs.items())},
        "khat": khat,
        "ess": ess,
        "n_modes": 1 if modes is None else len(modes),
        "importance_rounds": imp.rounds,
        "band_split": split,
        "max_rounds": max_rounds,
        "ok": ok,
        "reason": reason,
        "program_calls": ev.calls,
    }
    return FastPosterior(
        theta, ok, reason, fit, imp, imp.log_density[idx], phases, ev.calls, settings, ev
    )


def resolve_coarse_substeps(ev: BatchEvaluator, coarse) -> int:
    """The substeps per observation of :func:`fast_posterior`'s screen and fit (its
    ``coarse_substeps``, resolved against the evaluator ``ev``)."""
    fine = ev.substeps
    if coarse is None:
        return fine
    if isinstance(coarse, str):
        if coarse != "auto":
            raise ConfigError(
                f"coarse_substeps: expected an integer, 'auto' or None, got {coarse!r}"
            )
        stable = ev.problem.sim.step_info.get("stability_substeps", fine)
        return int(stable) if ev.traced and 1 <= int(stable) < fine else fine
    if not (isinstance(coarse, (int, np.integer)) and coarse >= 1):
        raise ConfigError(f"coarse_substeps: must be an integer >= 1, got {coarse!r}")
    if coarse != fine and not ev.traced:
        raise ConfigError(
            "coarse_substeps: this rollout program runs only the simulator's own step "
            f"({fine} substeps; the Pallas kernel with TREEINFER_PALLAS_TRACED_SUBSTEPS=off)"
        )
    return int(coarse)


def importance_for_run(
    problem,
    n_particles: int,
    seed: int = 0,
    log=lambda msg: None,
    resample: bool = True,
    **options,
):
    """The run layer's ``--init importance``: :func:`fast_posterior`, one status line to ``log``,
    and ``(posterior, theta0)``: ``posterior`` (:func:`posterior_from_fast`) when the weights
    pass their check, so no sampler needs to run; when they do not, ``resample`` (default)
    refines them by resample-move (:mod:`treeinfer.inference.resample_move`: Metropolis sweeps
    on the same rollout program until the cloud settles), whose particles are then the
    posterior; else None. ``theta0`` [P, D] the particles (the sampler's start when
    ``posterior`` is None). ``options`` go to :func:`fast_posterior`.
    """
    if not (problem.noise is None or problem.noise.black_box):
        # a generative likelihood's posterior is sharp (2 mm noise on ~900 samples): the coarse
        # step moves its mode by several posterior widths (importance rounds at the coarse step
        # then gave an effective sample size of 2-3 of 832 on the standard problem), so the
        # coarse fit is polished at the accurate step and only accurate rounds are drawn
        # one more round than the Boltzmann path: Pareto k_hat 0.74 after three rounds with an
        # effective sample size of 225 sent the standard problem to the sampler (issue 27)
        options = {
            "coarse_rounds": 0,
            "polish_iterations": GENERATIVE_POLISH,
            "max_rounds": 4,
            **options,
        }
    res = fast_posterior(problem, n_particles, seed=seed, **options)
    imp = res.importance
    verdict = (
        "used as the posterior (no sampler iterations)"
        if res.ok
        else f"not trusted ({res.reason})"
        + ("" if resample else ": the sampler runs from these particles")
    )
    log(
        f"importance posterior: MAP from {res.settings['n_fit_starts']} starts in "
        f"{res.settings['lm_iterations']} LM iterations"
        + (
            f" (+{res.settings['polish_iterations']} at the accurate step)"
            if res.settings["polish_iterations"]
            else ""
        )
        + f", {len(imp.draws)} draws in {imp.rounds} "
        f"round{'s' if imp.rounds > 1 else ''}, Pareto k_hat "
        f"{imp.khat:.2f}, effective sample size {imp.ess:.0f}: {verdict}"
    )
    if res.ok or not resample:
        post, theta = (posterior_from_fast(problem, res, seed) if res.ok else None), res.theta
    else:
        post, theta = _resample_move_start(problem, res, n_particles, seed, log)
    if post is not None:
        from .mode_check import checked_posterior

        post, theta = checked_posterior(
            problem, res, post, theta, int(n_particles), seed, log, _resample_move_start
        )
    return post, theta


def _resample_move_start(problem, res, n_particles: int, seed: int, log):
    """Untrusted importance weights: resample-move (:mod:`treeinfer.inference.resample_move`)
    on the start pipeline's own rollout program; its cloud is the posterior when it settled,
    else the sampler's start."""
    import time

    from .resample_move import resample_move

    t0 = time.perf_counter()
    imp = res.importance
    mv = resample_move(
        res.evaluator.log_density, imp.draws, imp.log_weights, imp.log_density,
        int(n_particles), seed=seed,
    )  # fmt: skip
    elapsed = time.perf_counter() - t0
    log(
        f"resample-move: {mv.describe()}, {elapsed:.0f} s: "
        + (
            "used as the posterior"
            if mv.ok
            else f"not settled ({mv.reason}): the sampler runs from these particles"
        )
    )
    theta = np.asarray(mv.theta, float)
    if not mv.ok:
        return None, theta
    settings = {**res.settings, "resample_move": mv.settings(), "ok": True}
    phases = {**res.phases, "resample_move": elapsed}
    moved = res._replace(
        theta=theta, log_density=mv.log_density, ok=True, settings=settings, phases=phases
    )
    reason = (
        f"resample-move after importance sampling (Pareto k_hat {imp.khat:.2f}): "
        f"{mv.sweeps} Metropolis sweeps, the cloud settled"
    )
    return posterior_from_fast(problem, moved, seed, reason), theta
