"""The run layer's integration-error floor: the MAP, the simulator's step-doubling error there,
and the problem rebuilt with it (:mod:`treeinfer.model.integration_error` says what the floor
is and why).

    ie, finals = map_integration_error(problem, seed, programs, shape, log)
    problem = make_problem(..., integration_error=ie)   # and start_hint=finals

Both steps run on the start pipeline's one rollout program
(:class:`treeinfer.inference.fast_evaluator.BatchEvaluator`, same batch and shape bucket, so no
new compilation): the MAP is the screen and multi-start LM of
:func:`treeinfer.inference.start_pipeline.force_noise_reference`'s first step (its finals then
start the run's own fit, which takes 5 LM iterations from them), and the step doubling is two
evaluations of the MAP with ``s`` and ``2 s`` substeps (the program takes the step count as an
argument). With ``--noise-force`` the force-noise reference is that MAP already and only the
step doubling runs (:func:`measure_integration_error`).
"""

from __future__ import annotations

import numpy as np

from ..model.integration_error import IntegrationError
from ..model.noise import NOISE_KINDS

__all__ = ["applies", "floor_for_run", "map_integration_error", "measure_integration_error"]

# the MAP fit's starts and LM iterations: force_noise_reference's first step (the same batch,
# so the same compiled program)
N_STARTS = 8
# 40, not 15: with the fit's stopping rule in nats (fast_fit.STEP_NATS) a start on a curved ridge
# keeps climbing it; 15 iterations left SBC data set 90's best start 1.5 nats below the ridge's
# top (most fits stop well before the cap: every start converged, or two agree)
LM_ITERATIONS = 40
POLISH_ITERATIONS = 20  # then at the run's own step (fast_posterior's polish)


def applies(problem, init: str | None) -> bool:
    """Whether a run measures the floor: a generative likelihood with sigma_x inferred, the
    paper's dynamic model without observation channels (the rollout program's problems), and the
    start pipeline (``--init auto`` or ``importance``), which fits the MAP anyway."""
    s = problem.settings
    return (
        init in ("auto", "importance")
        and problem.model is None
        and not s.get("channels")
        and s.get("likelihood") in NOISE_KINDS
        and bool(s.get("noise_inferred"))
        and s.get("integration_error") is None
    )


def _batch(problem) -> int:
    """One LM iteration's batch (fast_posterior's and force_noise_reference's)."""
    return N_STARTS * (4 * problem.sim.n_joints + 1)


def _evaluator(problem, programs=None, shape=None):
    """The start pipeline's rollout program for ``problem`` (its batch: fast_posterior's)."""
    from .fast_evaluator import BatchEvaluator, default_chunk

    k = _batch(problem)
    return BatchEvaluator(problem, default_chunk(k, 8 * k), programs, shape)


def measure_integration_error(
    problem, theta, programs=None, shape=None, ev=None
) -> IntegrationError:
    """The step-doubling error ``2 (tau_s - tau_2s)`` of the training pulls at ``theta``
    (``[2R]`` log gains, or a full row; only the gains are used) with the run's ``s`` substeps.

    A rollout program whose step count is fixed (the Pallas kernel with traced substeps off)
    gets a traced one of its own for these two rollouts."""
    from .fast_evaluator import BatchEvaluator

    ev = _evaluator(problem, programs, shape) if ev is None else ev
    if not ev.traced:
        ev = BatchEvaluator(problem, ev.chunk, programs, shape, traced_substeps=True)
    g = ev.n_gains
    row = np.zeros((1, problem.dim))
    row[0, :g] = np.asarray(theta, float).reshape(-1)[:g]
    row[0, g:] = 0.5 * (np.asarray(problem.lower)[g:] + np.asarray(problem.upper)[g:])
    s = ev.substeps
    b = np.shape(problem.obs.force)[0]
    r1, ok1, _ = ev.evaluate(row, s)
    r2, ok2, _ = ev.evaluate(row, 2 * s)
    if not (ok1[0] and ok2[0]):
        from ..errors import SimulationError

        raise SimulationError("integration error: the MAP's rollout is unstable")
    # r = simulated - recorded, so r_s - r_2s = tau_s - tau_2s (the displacement rows)
    return IntegrationError.from_rollouts(r1[0, :b], r2[0, :b], problem.obs.mask, s, row[0, :g])


def map_integration_error(problem, seed: int = 0, programs=None, shape=None, log=None):
    """``(IntegrationError, finals [S, D])``: the MAP of ``problem`` (screen and multi-start LM
    on the coarse step, as the start pipeline's), the step-doubling error there, and the fit's
    final points (best first) for the run's own fit to start from."""
    from .fast import resolve_coarse_substeps
    from .fast_fit import fit_map_batched
    from .screen_points import screen_starts

    ev = _evaluator(problem, programs, shape)
    coarse = resolve_coarse_substeps(ev, "auto")
    # the start pipeline's own screen, the prior's tails included
    starts, _ = screen_starts(ev, problem, 4 * _batch(problem), N_STARTS, seed, coarse)
    fit = fit_map_batched(ev, starts, LM_ITERATIONS, substeps=coarse)
    if coarse != ev.substeps:  # the error is measured at the run's step's MAP, not the coarse's
        good = fit.finals[np.isfinite(fit.values)]
        fit = fit_map_batched(ev, good[np.argsort(fit.values[np.isfinite(fit.values)])],
                              POLISH_ITERATIONS)  # fmt: skip
    order = np.argsort(fit.values)
    finals = fit.finals[order][np.isfinite(fit.values[order])]
    ie = measure_integration_error(problem, fit.theta, programs, shape, ev)
    if log is not None:
        log(f"integration error at the MAP ({fit.iterations} LM iterations): {ie.describe()}")
    return ie, finals


def floor_for_run(problem, make, init, recorded, seed, programs=None, shape=None, log=None):
    """``problem`` with the floor, for the run layer (:func:`treeinfer.runs.problem.build_problem`).

    ``make(ie)`` builds the run's problem with ``integration_error=ie``. ``recorded``: a resumed
    run's recorded problem settings (None: a new run): it takes the floor again at the
    reference it recorded (two rollouts; a run recorded without one resumes without one). A new
    run where :func:`applies` fits the MAP (:func:`map_integration_error`) and its problem
    starts the start pipeline's fit from that fit's finals (``start_hint``)."""
    import dataclasses

    shape = None if shape is None else tuple(shape)
    if recorded is not None:
        rec = recorded.get("integration_error")
        if not rec:
            return problem
        return make(measure_integration_error(problem, rec["reference"], programs, shape))
    if not applies(problem, init):
        return problem
    ie, finals = map_integration_error(problem, seed, programs, shape, log)
    floored = make(ie)
    # the floor's offset moves the mode by the bias it removes (0.2-0.9% in the gains on clean
    # chain2: many posterior std), and the start pipeline's own fit takes only a few LM steps
    # from its start hint: the finals are polished on the floored problem at the run's step
    # first (clean chain2: k_hat 0.26 with the polish, 0.42 without)
    from .fast_fit import fit_map_batched

    fit = fit_map_batched(
        _evaluator(floored, programs, shape), finals[:N_STARTS], POLISH_ITERATIONS
    )
    order = np.argsort(fit.values)
    return dataclasses.replace(
        floored, start_hint=fit.finals[order][np.isfinite(fit.values[order])]
    )
