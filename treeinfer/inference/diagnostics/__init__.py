"""Convergence diagnostics and ArviZ export for sampler output on plain arrays.

* MCMC-type samplers (Metropolis-Hastings, SGLD, SGHMC) run ``P`` independent
  particles; each particle is treated as one chain, so ArviZ's rank-normalised
  split R-hat and bulk/tail ESS (Vehtari et al. 2021) apply directly.
* SVGD / NNSVGD particles interact and are not Markov chains; R-hat/ESS do not
  apply. Their diagnostics are the log-density plateau and the kernel
  bandwidth.

Thresholds (all overridable in :func:`convergence_warnings`):
R-hat > 1.05 (looser than Vehtari et al.'s 1.01, which needs longer chains than
simulator-based runs usually afford; 1.1 is the classical Gelman-Rubin cut);
bulk or tail ESS below 100 per chain (Vehtari et al. 2021: total ESS at least
100 x number of chains); SVGD mean log-density still rising by more than 1%
over the last 10% of iterations; bandwidth collapsed to its floor; more than
10% of particles with an unstable (non-finite) simulation.

Beyond those (issue 11): :func:`find_stragglers` flags stuck particles (log density far
below the bulk, or far outside the prior box) with counts and warnings, and
:func:`reinit_stragglers` / :class:`ReinitStragglers` / :func:`drop_stragglers` are the
remedies; :func:`kernel_stein_discrepancy` (IMQ kernel, standardised particles) and
:func:`moment_change` measure SVGD convergence, :class:`ConvergenceCriterion` stops a run
early; :func:`mcmc_draws` / :func:`mcmc_summary` summarise MCMC runs from the post-warm-up
trace of all chains; :func:`prior_edge_mass` warns when posterior mass piles up at a box edge.

ArviZ is reached through :mod:`treeinfer.inference.diagnostics.arviz_compat` (ArviZ 0.2x and 1.x),
imported lazily: it is slow to import.

Modules: :mod:`.core` (ArviZ export, MCMC and SVGD diagnostics, warnings), :mod:`.stragglers`
(stuck particles and remedies), :mod:`.convergence` (Stein discrepancy, moment change, early
stopping, MCMC summaries from the trace, prior-edge mass). Every name is importable from
``treeinfer.inference.diagnostics`` as before the split.
"""

from __future__ import annotations

from .convergence import (
    MAX_EDGE_SHARE,
    ConvergenceCriterion,
    kernel_stein_discrepancy,
    mcmc_draws,
    mcmc_summary,
    moment_change,
    prior_edge_mass,
)
from .core import (
    MAX_KSD_FALL,
    MAX_REL_RISE,
    MAX_UNSTABLE_FRACTION,
    MIN_ESS_PER_CHAIN,
    RHAT_MAX,
    WINDOW,
    convergence_warnings,
    mcmc_diagnostics,
    save_inference_data,
    svgd_diagnostics,
    to_inference_data,
)
from .core import _labels as _labels
from .stragglers import (
    FALSE_ALARM,
    MAX_BOX_EXCESS,
    Z_MAX,
    ReinitStragglers,
    StragglerReport,
    chi2_gap,
    drop_stragglers,
    find_stragglers,
    reinit_stragglers,
    straggler_mask,
)

__all__ = [
    "FALSE_ALARM",
    "MAX_BOX_EXCESS",
    "MAX_EDGE_SHARE",
    "MAX_KSD_FALL",
    "MAX_REL_RISE",
    "MAX_UNSTABLE_FRACTION",
    "MIN_ESS_PER_CHAIN",
    "RHAT_MAX",
    "WINDOW",
    "Z_MAX",
    "ConvergenceCriterion",
    "ReinitStragglers",
    "StragglerReport",
    "chi2_gap",
    "convergence_warnings",
    "drop_stragglers",
    "find_stragglers",
    "kernel_stein_discrepancy",
    "mcmc_diagnostics",
    "mcmc_draws",
    "mcmc_summary",
    "moment_change",
    "prior_edge_mass",
    "reinit_stragglers",
    "save_inference_data",
    "straggler_mask",
    "svgd_diagnostics",
    "to_inference_data",
]
