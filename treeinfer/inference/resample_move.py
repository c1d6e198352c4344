"""Resample-move: importance draws whose weights are not trusted, refined by Metropolis moves
at the posterior (random-walk and independence sweeps) until the particle cloud stops changing.

The start pipeline (:mod:`treeinfer.inference.fast`) ends with importance sampling from the
MAP's Laplace/Student-t proposal. When the weights fail their check (Pareto k_hat > 0.5: the
proposal misses part of the posterior), the particles used to go to NNSVGD for up to 200
iterations. Two reasons not to by default:

* cost: an NNSVGD iteration takes a black-box gradient per particle, ``2D + 1`` rollouts, so
  200 iterations of 64 particles are ~140,000 rollouts (213-331 s on two cores of the device
  machine in ``experiments/default_calibration.py``), where one Metropolis sweep of 256 chains
  is 256 rollouts and 10-30 sweeps do;
* calibration: SVGD with a few dozen particles under-disperses in four or more dimensions
  (its repulsion weakens with the dimension; Ba et al. 2021), while Metropolis chains target the
  posterior exactly; started from resampled importance draws they begin near it, so a short
  burn-in suffices.

This is the resample-move step of sequential Monte Carlo (Gilks and Berzuini 2001; Chopin 2002) at
temperature 1: systematic resampling by the importance weights
(:func:`treeinfer.inference.importance.systematic_resample`), then sweeps of a Gaussian random walk
whose covariance is the cloud's own (scaled by ``2.38 / sqrt(D)``, the scale tuned between sweeps
towards 30% acceptance; adapting a population kernel from the population keeps every chain's target
the posterior, as in BlackJAX's SMC kernels). Every second sweep (``independent_every``) proposes
instead from a Student-t (df 8) fitted to the cloud, accepted with the independence sampler's ratio
``p(x') q(x) / (p(x) q(x'))``: a chain that accepts jumps anywhere in the posterior's bulk at once,
where a random-walk step moves it a fraction of a standard deviation. On the standard problem's
seed-1 data (k_hat 0.58) the cloud settled in 16 sweeps (37 s on the 2-core box) instead of 44 (87
s), the same posterior within its Monte Carlo error; on a 7-D banana
(``tests/test_resample_move.py`` has the smaller cases) the random walk alone did not settle in 80
sweeps on 5 of 6 seeds, mixed sweeps in 20-28, both with the banana's thin arms under-explored
(a column's std off by up to 50%; `/tmp`-only probe, from a proposal half as wide and shifted by
half a std): a thin curved ridge is where resample-move is weakest. Written on the host instead of
with ``blackjax.rmh`` because the log density is the start pipeline's NumPy-batched rollout
program (:class:`treeinfer.inference.fast_evaluator.BatchEvaluator`): one call per sweep for every
chain, no new program to compile.

Stopping: after ``min_sweeps``, every ``check_every`` sweeps the cloud's mean and std per column are
compared with those ``check_every`` sweeps before; the cloud is converged when the largest mean
change is below ``tol`` of the std and the largest std change below ``tol`` of it (or below
:data:`NOISE_Z` Monte Carlo standard errors of ``n`` chains, ``sqrt(2 / n)`` sd and ``sqrt(1 / n)``,
when those are larger: two clouds of independent draws differ by that much, so a fixed tolerance
below it stops only chains that barely decorrelate) twice in a row, at least ``min_moved`` of the
chains have accepted a move (copies of one draw have separated), and the chains have travelled: the
mean over chains of their summed squared jumps, in units of the cloud's covariance, is at least
``min_travel`` times D (a cloud whose chains barely move also "stops changing": with a proposal far
too wide the acceptance, and with it every step, shrinks towards zero). Otherwise, after
``max_sweeps``, ``ok`` is False and says why."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ..errors import ConfigError

__all__ = ["MoveResult", "resample_move"]

TARGET_ACCEPT = 0.3
# the chains' mean summed squared jump per dimension, in units of the cloud's covariance, before
# the cloud may count as settled: one (the value before) let a cloud that was too narrow stop
# after 12-24 sweeps while still widening slowly, a change per check below ``tol``; SBC of the
# default command (experiments/results/sbc_default_h200/) gave truths' z-scores an rms of 2.2
# after it. A chain that has travelled several of the cloud's standard deviations in every
# direction has forgotten the importance draw it started from.
MIN_TRAVEL = 4.0
# sweeps before the cloud counts as not settled (was 80, then the sampler ran; SBC of the default
# command: the two fits where it did ended with the truths 4-6 sd out; a sweep is N rollouts, an
# NNSVGD iteration 2D + 1 per particle, so 80 more sweeps cost less than 10 NNSVGD iterations of
# 64 particles)
MAX_SWEEPS = 160
# every INDEPENDENT_EVERY-th sweep proposes from a Student-t (INDEPENDENT_DF) fitted to the cloud
# instead of a random-walk step (resample_move's ``independent_every``; 0: never)
INDEPENDENT_EVERY = 2
INDEPENDENT_DF = 8.0
# the independence proposal's scale relative to the cloud: wider than the target is where an
# independence sampler is safe (narrower, the target's tails are never proposed), and a cloud
# resampled from importance weights that failed their check starts narrower than the posterior:
# fitted to the cloud itself, the proposal let it widen only by random-walk steps (SBC data set 6
# of experiments/results/sbc_default_s16_lobes/: settled after 12 sweeps with the truth 5.8 sd
# out, 4.1 after 124)
INDEPENDENT_SCALE = 1.5
# a cloud counts as unchanged when it moved by less than this many Monte Carlo standard errors
NOISE_Z = 2.5


class MoveResult(NamedTuple):
    """Result of :func:`resample_move`.

    theta: [P, D] particles (P of the chains, without replacement). log_density: [P].
    chains: [N, D] every chain's last state; chain_log_density: [N]. ok: converged (module
    docstring); reason: why not ("" when ok). sweeps: Metropolis sweeps run. acceptance: mean
    acceptance of the random-walk sweeps (independent_acceptance: of the independence sweeps,
    NaN when none ran). moved: share of chains that accepted at least one move.
    change: ``(mean change / std, relative std change)`` at the last check. travel: the chains'
    mean summed squared jump over D, in units of the cloud's covariance.
    """

    theta: np.ndarray
    log_density: np.ndarray
    chains: np.ndarray
    chain_log_density: np.ndarray
    ok: bool
    reason: str
    sweeps: int
    acceptance: float
    moved: float
    change: tuple
    travel: float = 0.0
    independent_acceptance: float = math.nan

    def settings(self) -> dict:
        """JSON-ready record of the diagnostics."""
        return {
            "method": "resample_move",
            "chains": int(len(self.chains)),
            "sweeps": int(self.sweeps),
            "acceptance": float(self.acceptance),
            "independent_acceptance": None
            if math.isnan(self.independent_acceptance)
            else float(self.independent_acceptance),
            "moved": float(self.moved),
            "mean_change_sd": float(self.change[0]),
            "std_change": float(self.change[1]),
            "travel": float(self.travel),
            "ok": bool(self.ok),
            "reason": self.reason,
        }

    def describe(self) -> str:
        """One line for the log."""
        return (
            f"{len(self.chains)} chains x {self.sweeps} Metropolis sweeps "
            f"(acceptance {100 * self.acceptance:.0f}% random-walk"
            + (
                ""
                if math.isnan(self.independent_acceptance)
                else f", {100 * self.independent_acceptance:.0f}% independence"
            )
            + f", {100 * self.moved:.0f}% of chains moved, "
            f"travel {self.travel:.1f} sd^2; "
            f"last change: mean {self.change[0]:.3f} sd, std {100 * self.change[1]:.1f}%)"
        )


def _cloud_chol(x: np.ndarray) -> np.ndarray:
    """Cholesky factor of the cloud's covariance, regularised relative to its diagonal."""
    c = np.atleast_2d(np.cov(x.T))
    d = np.diag(c).copy()
    d[~(d > 0)] = 1e-8
    c = c + np.diag(1e-6 * d + 1e-12)
    try:
        return np.linalg.cholesky(c)
    except np.linalg.LinAlgError:
        return np.diag(np.sqrt(d))


def _change(a: tuple, b: tuple) -> tuple[float, float]:
    """``(max |mean_a - mean_b| / std_b, max |std_a / std_b - 1|)`` over columns."""
    (ma, sa), (mb, sb) = a, b
    sb = np.where(sb > 0, sb, 1.0)
    return float(np.max(np.abs(ma - mb) / sb)), float(np.max(np.abs(sa / sb - 1.0)))


def resample_move(
    log_density,
    draws,
    log_weights,
    draws_log_density,
    n_particles: int,
    n_chains: int | None = None,
    seed: int = 0,
    min_sweeps: int = 8,
    max_sweeps: int = MAX_SWEEPS,
    check_every: int = 4,
    tol: float = 0.15,
    min_moved: float = 0.9,
    min_travel: float = MIN_TRAVEL,
    independent_every: int = INDEPENDENT_EVERY,
) -> MoveResult:
    """Resample importance draws by their weights, then Metropolis sweeps until stable.

    Args:
      log_density: ``[M, D] -> [M]`` NumPy log posterior density (``-inf``/NaN where the
        simulation is unstable), called once per sweep with every chain.
      draws: ``[M, D]`` importance draws; log_weights: ``[M]`` their (normalised or not) log
        weights; draws_log_density: ``[M]`` log density at the draws (no re-evaluation).
      n_particles: P particles returned. n_chains: N chains (default ``4 P``).
      seed: of the resampling, the moves and the choice of the P returned chains.
      min_sweeps, max_sweeps, check_every, tol, min_moved, min_travel: the stopping rule
        (module docstring).
      independent_every: every this many sweeps an independence sweep (a Student-t fitted to
        the cloud, :data:`INDEPENDENT_EVERY`); 0: random-walk sweeps only.
    """
    draws = np.atleast_2d(np.asarray(draws, float))
    lw = np.asarray(log_weights, float)
    lpd = np.asarray(draws_log_density, float)
    n_chains = 4 * int(n_particles) if n_chains is None else int(n_chains)
    for name, v in (("n_particles", n_particles), ("n_chains", n_chains)):
        if not (isinstance(v, (int, np.integer)) and v >= 2):
            raise ConfigError(f"{name}: must be an integer >= 2, got {v!r}")
    if n_particles > n_chains:
        raise ConfigError(f"n_particles ({n_particles}) must not exceed n_chains ({n_chains})")
    if not (1 <= min_sweeps <= max_sweeps) or check_every < 1:
        raise ConfigError(
            f"sweeps: need 1 <= min_sweeps <= max_sweeps and check_every >= 1, got "
            f"{min_sweeps}, {max_sweeps}, {check_every}"
        )
    ok_w = np.isfinite(lw) & np.isfinite(lpd)
    if not ok_w.any():
        raise ConfigError("resample_move: no importance draw with a finite weight")
    from .importance import _draw_log_density, systematic_resample

    rng = np.random.default_rng([int(seed), 104729])
    idx = systematic_resample(rng, np.where(ok_w, lw, -np.inf), n_chains)
    x, lp = draws[idx].copy(), lpd[idx].copy()
    n, d = x.shape
    log_s = math.log(2.38 / math.sqrt(d))
    moved = np.zeros(n, bool)
    jumped = np.zeros(n)  # summed squared jumps, in the cloud's covariance
    accepted, independent_accepted, stats = [], [], []
    change, calm = (math.inf, math.inf), 0
    tol_mean = max(tol, NOISE_Z * math.sqrt(2.0 / n))
    tol_std = max(tol, NOISE_Z * math.sqrt(1.0 / n))
    ok, reason, sweeps = False, "", 0
    for sweeps in range(1, max_sweeps + 1):
        chol = _cloud_chol(x)
        independent = independent_every > 0 and sweeps % independent_every == 0
        if independent:
            # the cloud's own Student-t as an independence proposal: a chain that accepts
            # jumps anywhere in the posterior's bulk at once (a random-walk step moves it a
            # fraction of a standard deviation), so the cloud forgets its importance draws in
            # a few sweeps where the posterior is near-elliptical; the random-walk sweeps
            # between them keep the chains moving where it is not (a curved ridge)
            centre, cov = x.mean(axis=0), INDEPENDENT_SCALE**2 * (chol @ chol.T)
            xp, lq_p = _draw_log_density(rng, centre, cov, n, INDEPENDENT_DF)
            lq_x = _draw_log_density(None, centre, cov, 0, INDEPENDENT_DF, x)[1]
        else:
            xp = x + math.exp(log_s) * rng.standard_normal((n, d)) @ chol.T
        lpp = np.asarray(log_density(xp), float)
        lpp = np.where(np.isnan(lpp), -np.inf, lpp)
        with np.errstate(invalid="ignore"):
            ratio = np.where(np.isfinite(lpp), lpp - lp, -np.inf)
            if independent:
                ratio = ratio + lq_x - lq_p
        acc = np.log(rng.random(n)) < ratio
        z2 = np.sum(np.linalg.solve(chol, (xp - x).T) ** 2, axis=0)
        jumped += np.where(acc, z2, 0.0)
        x[acc], lp[acc] = xp[acc], lpp[acc]
        moved |= acc
        rate = float(acc.mean())
        if independent:
            independent_accepted.append(rate)
        else:
            accepted.append(rate)
            log_s += 1.5 * (rate - TARGET_ACCEPT)
        stats.append((x.mean(axis=0), x.std(axis=0, ddof=1)))
        if sweeps >= min_sweeps and sweeps % check_every == 0 and sweeps > check_every:
            change = _change(stats[-1], stats[-1 - check_every])
            # the change between two independent clouds of n chains is itself ~sqrt(2 / n) sd
            # in the mean (sqrt(1 / n) in the std): a tolerance below that noise stops only
            # clouds whose chains barely decorrelate between checks, the slow-mixing ones
            calm = calm + 1 if change[0] < tol_mean and change[1] < tol_std else 0
            if calm >= 2 and moved.mean() >= min_moved and jumped.mean() / d >= min_travel:
                ok = True
                break
    if not ok:
        reason = (
            f"the cloud still changed after {sweeps} sweeps (mean by {change[0]:.2f} sd, std "
            f"by {100 * change[1]:.0f}%; {100 * moved.mean():.0f}% of chains moved, travel "
            f"{jumped.mean() / d:.2f} sd^2 of {min_travel:g} needed)"
        )
    keep = np.sort(rng.choice(n, size=int(n_particles), replace=False))
    return MoveResult(
        x[keep], lp[keep], x, lp, ok, reason, sweeps,
        float(np.mean(accepted)) if accepted else math.nan, float(moved.mean()), change,
        float(jumped.mean() / d),
        float(np.mean(independent_accepted)) if independent_accepted else math.nan,
    )  # fmt: skip
