"""Simulation-based calibration (SBC, Talts et al. 2018) of treeinfer's posteriors.

SBC checks the whole inference pipeline against its own generative model: draw parameters
``theta* ~ prior``, simulate a data set ``y ~ p(y | theta*)``, run inference on ``y`` and record
the rank of ``theta*_d`` among ``L`` posterior draws, for every parameter ``d``. If the draws come
from the exact posterior, every rank is uniform on ``{0, ..., L}`` (over prior draws); a
U-shaped histogram means over-confident posteriors, a hump under-confident ones, a slope bias.

Modules (all names importable from ``treeinfer.calibration`` as before the split):

* :mod:`.stats`: ranks, fractional ranks, coverage of central intervals, uniformity tests
  (chi-square and Kolmogorov-Smirnov, Bonferroni at 1%), :class:`SBCResult`, exact draws from
  the smoothed box prior (:func:`sample_smoothed_box`);
* :mod:`.plots`: rank histograms, expected-coverage plot, :func:`write_outputs`;
* :mod:`.config`: :class:`SBCConfig`, :func:`draw_truths`;
* :mod:`.smc`: :func:`tempered_smc`, the sampler (adaptive tempered SMC from the prior, vmapped
  over data sets; its docstring says why SMC and not MCMC from a mode);
* :mod:`.programs`: the batched, jitted program of each sampler (``smc``, ``mh``, ``svgd``);
* :mod:`.study`: :func:`run_tree_sbc` (truths, noisy data, the program over chunks of data
  sets, ranks) and :func:`config_record`;
* :mod:`.figures`: posterior std / Cramer-Rao ratios and predictive-band coverage of unseen
  test pulls.

Samplers: ``smc`` (default) gives nearly exact draws including separated local modes; ``mh``
(Adam to the best of P modes, then random-walk MH chains there) is kept for comparison: it
failed SBC on the GPU (R = 2 Kp[parent] chi-square p = 8e-4; R = 3 every parameter, 95%
intervals covering 71-84%) because ~10% (R = 2) to ~30% (R = 3) of data sets sat in a wrong
local mode. ``svgd`` ranks the final SVGD particles (SVGD's own calibration). NNSVGD is not
offered: its target adds the learned inequality prior, which the truths would have to be drawn
from as well.
"""

from __future__ import annotations

from .config import SBC_LIKELIHOODS, SBC_SAMPLERS, SBCConfig, draw_truths
from .plots import plot_coverage, plot_rank_histograms, write_outputs
from .programs import build_program
from .stats import (
    ALPHA,
    COVERAGE_LEVELS,
    SBCResult,
    binomial_band,
    coverage_table,
    default_bins,
    fractional_ranks,
    rank_coverage,
    rank_uniformity,
    result_json,
    sample_smoothed_box,
    sbc_ranks,
    summarize_sbc,
)
from .study import SAMPLER_NOTES, config_record, run_tree_sbc


def __getattr__(name):  # the sampler imports JAX and BlackJAX: load it only when asked for
    if name in ("SMCInfo", "tempered_smc"):
        from . import smc

        return getattr(smc, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "ALPHA",
    "COVERAGE_LEVELS",
    "SAMPLER_NOTES",
    "SBC_LIKELIHOODS",
    "SBC_SAMPLERS",
    "SBCConfig",
    "SBCResult",
    "SMCInfo",
    "binomial_band",
    "build_program",
    "config_record",
    "coverage_table",
    "default_bins",
    "draw_truths",
    "fractional_ranks",
    "plot_coverage",
    "plot_rank_histograms",
    "rank_coverage",
    "rank_uniformity",
    "result_json",
    "run_tree_sbc",
    "sample_smoothed_box",
    "sbc_ranks",
    "summarize_sbc",
    "tempered_smc",
    "write_outputs",
]
