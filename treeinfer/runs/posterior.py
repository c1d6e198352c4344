"""A run's posterior as reported: MCMC traces cut to their post-warm-up draws (thinned), stragglers
dropped when asked, and the trace of a resumed run merged with its checkpoints' (for
:mod:`.service`)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..inference.samplers import sampler_spec
from .checkpoint import Checkpoint

MAX_MCMC_DRAWS = 1024  # --mcmc-thin 0: thin the post-warm-up draws to at most this many


def _summarised_posterior(posterior, problem, trace: dict, o: dict):
    """The particles the run's summaries describe (summary.json, particles.csv, the fit).

    MCMC samplers: every chain's post-warm-up trace (``--mcmc-warmup``), thinned
    (``--mcmc-thin``; 0: to at most MAX_MCMC_DRAWS draws), not only the final states.
    ``--drop-stragglers``: stuck final particles (SVGD) are left out. The sampler's own
    final state stays in ``posterior.run``."""
    from ..inference.diagnostics import find_stragglers, mcmc_draws
    from ..model.likelihood import gains_from_theta

    theta, logp, extra = posterior.theta, posterior.log_density, {}
    pos, ld = np.asarray(trace["positions"]), np.asarray(trace["log_density"])
    if sampler_spec(o["sampler"]).family == "mcmc" and len(pos) >= 2:
        warm = math.floor(o.get("mcmc_warmup", 0.5) * len(pos))
        thin = int(o.get("mcmc_thin", 0))
        if thin == 0:
            thin = max(1, math.ceil((len(pos) - warm) * pos.shape[1] / MAX_MCMC_DRAWS))
        theta, logp = mcmc_draws(pos, warm, thin, log_density=ld)
        extra = {"mcmc_draws": {"warmup": warm, "thin": thin, "n_draws": int(len(theta))}}
    elif o.get("drop_stragglers"):
        rep = find_stragglers(logp, theta, problem.lower, problem.upper)
        if 0 < rep.n_stragglers < len(theta) - 1:
            theta, logp = theta[~rep.mask], logp[~rep.mask]
            extra = {"dropped_stragglers": True, "n_dropped": rep.n_stragglers}
    if not extra:
        return posterior
    if getattr(problem, "model", None) is not None:
        kp, kd = problem.model.layout.gains(np.asarray(theta))
    else:
        kp, kd = gains_from_theta(theta, problem.sim.n_joints)
    return dataclasses.replace(
        posterior,
        theta=np.asarray(theta),
        kp=np.asarray(kp),
        kd=np.asarray(kd),
        log_density=np.asarray(logp),
        settings={**posterior.settings, **extra},
    )


def _merged_trace(run, previous: Checkpoint | None) -> dict:
    """Trace of the whole run.

    The driver's, preceded on a resumed run by the checkpoints' coarse one."""
    pos, ld, it = run.trace_positions, run.trace_logdensity, run.trace_iterations
    if previous is not None and len(previous.trace_iterations):
        keep = previous.trace_iterations <= previous.iteration
        pos = np.concatenate([previous.trace_positions[keep], pos])
        ld = np.concatenate([previous.trace_logdensity[keep], ld])
        it = np.concatenate([previous.trace_iterations[keep], it])
    first = run.settings["start_iteration"]
    diag = {k: np.asarray(v) for k, v in run.diagnostics.items()}
    n_diag = len(next(iter(diag.values()))) if diag else 0
    return {
        "positions": np.asarray(pos),
        "log_density": np.asarray(ld),
        "iterations": np.asarray(it, np.int64),
        "diagnostics": diag,
        "diag_iterations": np.arange(first + 1, first + 1 + n_diag, dtype=np.int64),
        "resumed_from": None if previous is None else int(previous.iteration),
        "elapsed_s": float(run.elapsed_s),
    }
