"""What :func:`treeinfer.inference.fast.fast_posterior` returns (:class:`FastPosterior`) and its
conversion for the run layer: :func:`posterior_from_fast` and :func:`importance_run_result` make
a :class:`~treeinfer.inference.problem.Posterior` and a sampler-style ``RunResult`` (zero
iterations) of importance draws that no sampler refined.

Separate from :mod:`treeinfer.inference.fast` (issue 26): the result types and their conversion
are not the pipeline, and the start pipeline uses :func:`importance_run_result` for models the
rollout program does not run. :mod:`treeinfer.inference.fast` re-exports every name (they lived
there before the split).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = ["FastPosterior", "ParticleState", "importance_run_result", "posterior_from_fast"]


class FastPosterior(NamedTuple):
    """Result of :func:`fast_posterior`.

    theta: [P, D] particles (importance resample). ok: trust them (PSIS ``khat <= 0.7``,
    enough effective samples, a stable band); reason: why not. fit: the
    :class:`~treeinfer.inference.mapfit.MapFit`. importance: the
    :class:`~treeinfer.inference.importance.ImportancePosterior`. log_density: [P] at ``theta``.
    phases: wall seconds per phase (``compile`` is the first program run).
    calls: rollout-program runs. settings: JSON-ready options and diagnostics.
    """

    theta: np.ndarray
    ok: bool
    reason: str
    fit: object
    importance: object
    log_density: np.ndarray
    phases: dict
    calls: int
    settings: dict
    evaluator: object = None  # the BatchEvaluator it ran on (resample-move reuses its program)


class ParticleState(NamedTuple):
    """The minimal sampler state of a posterior that no sampler produced (the run layer reads
    ``position`` and ``logdensity``)."""

    position: np.ndarray
    logdensity: np.ndarray


def importance_run_result(
    theta, logp, run_settings: dict, importance, elapsed_s: float, stop_reason: str | None = None
):
    """The :class:`treeinfer.inference.samplers.RunResult` of an importance posterior that no
    sampler refined: one state (iteration 0) of ``theta [P, D]`` and ``logp [P]``, ``stop_reason``
    naming the weights' Pareto k_hat and effective sample size (``importance.khat``, ``.ess``).
    Shared by the paper's model (:func:`posterior_from_fast`) and the other models' start
    (:mod:`treeinfer.inference.start_pipeline`)."""
    from .samplers import RunResult

    return RunResult(
        final_positions=theta,
        final_state=ParticleState(theta, logp),
        trace_positions=theta[None],
        trace_logdensity=logp[None],
        trace_iterations=np.zeros(1, np.int64),
        diagnostics={},
        settings=run_settings,
        elapsed_s=elapsed_s,
        stop_reason=stop_reason
        or f"importance sampling (Pareto k_hat {importance.khat:.2f}, "
        f"effective sample size {importance.ess:.0f})",
    )


def posterior_from_fast(
    problem, result: FastPosterior, seed: int = 0, stop_reason: str | None = None
):
    """A :class:`treeinfer.inference.problem.Posterior` of ``result`` (zero sampler iterations), for
    the run layer (``--init importance --iterations 0``): ``run`` is a
    :class:`treeinfer.inference.samplers.RunResult` whose trace is the one state (iteration 0),
    ``stop_reason`` says that importance sampling produced it, and ``settings`` record the
    fit and the weights' diagnostics (``khat``, ``ess``)."""
    from ..model.likelihood import gains_from_theta
    from .problem import Posterior

    theta = np.asarray(result.theta, np.float32)
    logp = np.asarray(result.log_density, np.float32)
    run_settings = {
        **result.settings,
        "n_iterations": 0,
        "n_iterations_done": 0,
        "start_iteration": 0,
        "seed": seed,
    }
    run = importance_run_result(
        theta, logp, run_settings, result.importance, float(sum(result.phases.values())),
        stop_reason,
    )  # fmt: skip
    kp, kd = gains_from_theta(theta, problem.sim.n_joints)
    settings = {
        "problem": problem.settings,
        "sampler": "importance",
        "sampler_options": {k: result.settings[k] for k in ("n_starts", "n_draws", "df")},
        "n_particles": len(theta),
        "n_iterations": 0,
        "seed": int(seed),
        "run": run_settings,
    }
    return Posterior(theta, np.asarray(kp), np.asarray(kd), logp, problem.labels, run, settings)
