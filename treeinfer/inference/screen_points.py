"""Where the start pipeline's global screen looks: stratified points of the prior, its smoothed
box's tails beyond the box included (:func:`prior_points`), and the range a MAP found there may
take (:func:`prior_range`). A module of its own because :mod:`treeinfer.inference.fast_fit`
(the Latin hypercube) and :mod:`treeinfer.inference.start_steps` (the screen's densities) import
each other's neighbours; :mod:`treeinfer.inference.fast`,
:mod:`treeinfer.inference.start_pipeline` and :mod:`treeinfer.inference.integration_floor` (the
first fit of a run without a force-noise term) draw from here.
"""

from __future__ import annotations

import numpy as np

__all__ = ["SCREEN_TAIL_SDS", "prior_points", "prior_range", "screen_starts"]

# the screen's gain columns reach this many tail widths beyond the box at most (the quantile of
# the smoothed box's tail mass that a Latin hypercube of a few hundred points resolves anyway)
SCREEN_TAIL_SDS = 3.0


def prior_points(problem, n: int, seed: int = 0) -> np.ndarray:
    """``[n, D]`` the global screen's points: a Latin hypercube (:func:`treeinfer.inference.
    fast_fit.latin_hypercube`, the same strata as before) whose gain columns are mapped through
    the smoothed box prior's quantile function (:func:`treeinfer.model.priors.
    smoothed_box_quantile`), the noise columns uniform in their range (the screen sets them from
    the residuals anyway, :func:`screen`).

    Why not the box alone: the prior puts a fifth of each gain's mass in the tails beyond the box
    (``prior_sigma`` 0.1 of the log width: ``p_box = 1 / (1 + 0.1 sqrt(2 pi)) = 0.8``), so a
    posterior there is as likely a priori as one inside, and the screen never looked. SBC of the
    default command (``experiments/results/sbc_default_s14/``): 150 of 192 data sets had a true
    gain beyond the box; their truths' z-scores had an rms of up to 5.9 (clean force: 33) against
    0.8-1.8 where every truth was inside; with a clean force, a fit from the box's starts ended in
    a wrong basin with the noise scale 3.4 times the truth's (z 198)."""
    from ..model.priors import smoothed_box_quantile
    from .fast_fit import latin_hypercube

    lower, upper = np.asarray(problem.lower, float), np.asarray(problem.upper, float)
    d = lower.size
    u = latin_hypercube(n, np.zeros(d), np.ones(d), seed)
    pts = lower + u * (upper - lower)
    st = problem.settings or {}
    sigma, space = st.get("prior_sigma"), st.get("prior_space", "log")
    if problem.model is not None or not sigma or space != "log":
        return pts  # another parameterisation or prior: its box
    g = 2 * problem.sim.n_joints
    s = float(sigma) * (upper[:g] - lower[:g])
    # the extreme strata's quantiles clipped at SCREEN_TAIL_SDS tail widths (the half-normal's
    # quantile of the last of n strata grows without bound as the jitter nears the edge)
    q = smoothed_box_quantile(u[:, :g], lower[:g], upper[:g], s)
    pts[:, :g] = np.clip(q, lower[:g] - SCREEN_TAIL_SDS * s, upper[:g] + SCREEN_TAIL_SDS * s)
    return pts


def prior_range(problem) -> tuple[np.ndarray, np.ndarray]:
    """``(lower, upper)`` of the gain columns widened by :data:`SCREEN_TAIL_SDS` tail widths
    (the box itself for another prior): where :func:`prior_points` looks and a MAP found there
    may lie (the force-noise reference is clipped to it, no longer to the box)."""
    lower, upper = np.asarray(problem.lower, float), np.asarray(problem.upper, float)
    g = 2 * problem.sim.n_joints
    st = problem.settings or {}
    sigma, space = st.get("prior_sigma"), st.get("prior_space", "log")
    lo, hi = lower[:g].copy(), upper[:g].copy()
    if problem.model is None and sigma and space == "log":
        s = float(sigma) * (hi - lo)
        lo, hi = lo - SCREEN_TAIL_SDS * s, hi + SCREEN_TAIL_SDS * s
    return lo, hi


def screen_starts(ev, problem, n_screen: int, n_starts: int, seed: int, substeps):
    """``(starts [n_starts, D], pts [n_screen, D])``: the global screen every first fit of the
    start pipeline takes (:func:`treeinfer.inference.fast.fast_posterior`, the force-noise
    reference, the integration floor's MAP): ``n_screen`` points of the prior, its tails included
    (:func:`prior_points`), ranked by :func:`treeinfer.inference.start_steps.screen` at
    ``substeps``; the best ``n_starts`` start the LM, unstable ones last. ``pts`` (noise columns
    set) for a caller that ranks them again under another model."""
    from .start_steps import screen

    lp, pts = screen(ev, prior_points(problem, n_screen, seed), substeps)
    return pts[np.argsort(np.where(np.isfinite(lp), -lp, np.inf))[:n_starts]], pts
