"""Where to pull next: score candidate pulls by the expected information they bring.

Given posterior particles ``theta [P, D]`` (``log Kp``, ``log Kd`` of the inferred joints) from
the pulls made so far, and a Gaussian noise model on the recorded displacement (``sigma_x`` m,
white, on every sample), each candidate next pull ``c`` (grasp fraction on the grasped branch,
peak force, profile kind, optionally a pull direction) gets a score:

**Expected information gain (default).** ``EIG(c) = I(theta; y_c)``, the expected reduction of
the posterior entropy of theta from observing ``y_c = tau(theta, c) + eps``,
``eps ~ N(0, sigma_x^2 I_T)``. We use the Laplace / Fisher approximation

    EIG(c) ~= 0.5 * E_{theta ~ p}[ log det(I_D + Sigma F_c(theta)) ],
    F_c(theta) = J_c(theta)^T J_c(theta) / sigma_x^2,

with ``Sigma`` [D, D] the covariance of the particles and ``J_c(theta)`` [T, D] the sensitivity
of the displacement trajectory to theta, by central differences in log space (step ``h``:
``J[:, d] = (tau(theta + h e_d) - tau(theta - h e_d)) / 2h``). It is exact for a linear model
with a Gaussian prior (then F does not depend on theta and the formula is the closed form), and
the usual linearisation otherwise: it treats the posterior as Gaussian with covariance Sigma and
the simulator as linear over the posterior's width at each particle. It is not bounded by
``log P`` (as nested Monte Carlo is), so it still ranks pulls that are very informative.

Cost: ``M * 2D * C`` rollouts for ``C`` candidates and ``M`` particles (a seeded subsample of
the posterior, default 32), all in **one** jitted batched :func:`treeinfer.sim.simulate`
call, plus ``O(M C (T D^2 + D^3))`` arithmetic. E.g. 100 candidates, 32 particles and the
2-branch example (D = 4): 25,600 rollouts, about a second on a 2-core CPU after compiling.

**Nested Monte Carlo (check).** :func:`nested_mc_eig` is the prior-contrastive estimate
``mean_n [log p(y_n | theta_n) - log mean_m p(y_n | theta_m)]`` with ``y_n`` drawn at particle
``theta_n`` and the inner average over all particles (the own one included: a lower bound that
converges to the EIG as ``P`` grows; it cannot exceed ``log P``). ``P * C`` rollouts, no
linearisation; use it to check the Laplace ranking where the EIG is well below ``log P``.

**Target (``target=``).** The expected reduction of the predictive variance of a stated future
manipulation (a :class:`Target`: the displacement trajectory at grasp fraction ``g`` under a
profile with peak force ``F``), linearised: with ``G(theta)`` [T, D] the target's sensitivity,

    before = mean_t G_t Sigma G_t^T,   after_c = mean_t G_t Sigma'_c G_t^T,
    Sigma'_c = (Sigma^-1 + F_c)^-1 = S (I + S^T F_c S)^-1 S^T   (Sigma = S S^T),

averaged over particles; the score is ``before - after_c`` (m^2, the mean over the target's
samples of the variance removed) and ``band_std_after = sqrt(after_c)`` (m) is reported beside
it (a Gaussian 95% band is ``3.92`` times as wide). Cost: ``M * 2D * (C + 1)`` rollouts.

Candidates: :func:`candidate_grid` crosses grasp fractions, peak forces, profile kinds (keys of
:data:`treeinfer.data.forces.SHAPES`, with the standard timing of :data:`STANDARD_TIMING`) and
directions. A direction (``[3]`` unit vector, world frame) is passed to the simulator as
``direction=`` ``[C, 3]``; today's simulator pulls along gravity only, so a direction other than
``None`` raises :class:`~treeinfer.errors.ConfigError` until it gains that argument.

Everything here is generic in the forward model: the estimators take a batched
``forward(theta [N, D]) -> (tau [N, C, T], ok [N, C])``; :func:`simulator_forward` builds it from
a :class:`~treeinfer.sim.Simulator`.

Modules: :mod:`treeinfer.design.candidates` (candidates, targets),
:mod:`treeinfer.design.estimators` (estimators, the simulator as forward model),
:mod:`treeinfer.design.scoring` (ranking, table, plot). Import from here. A finished run as the
start (``treeinfer suggest``) is a service over a run folder, in :mod:`treeinfer.runs.suggest`:
it sits above this package (it loads the run), so it is not re-exported here.
"""

from __future__ import annotations

from .candidates import (
    STANDARD_TIMING,
    Candidate,
    Target,
    candidate_forces,
    candidate_grid,
    candidate_spec,
    parse_target,
)
from .candidates import (
    _check_candidate as _check_candidate,
)
from .estimators import (
    ForwardFn,
    fd_jacobian,
    laplace_eig,
    nested_mc_eig,
    nested_mc_eig_from_rollouts,
    particle_covariance,
    simulator_forward,
    target_variance,
)
from .estimators import (
    _accepts_direction as _accepts_direction,
)
from .scoring import Suggestions, plot_scores, score_candidates

__all__ = [
    "STANDARD_TIMING",
    "Candidate",
    "ForwardFn",
    "Suggestions",
    "Target",
    "candidate_forces",
    "candidate_grid",
    "candidate_spec",
    "fd_jacobian",
    "laplace_eig",
    "nested_mc_eig",
    "nested_mc_eig_from_rollouts",
    "parse_target",
    "particle_covariance",
    "plot_scores",
    "score_candidates",
    "simulator_forward",
    "target_variance",
]
