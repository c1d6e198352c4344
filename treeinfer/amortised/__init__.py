"""Amortised posteriors (issue 31 §2): a neural posterior estimator of one tree, trained once on
simulations drawn from the prior and the noise model, that gives the posterior of a new
recording in milliseconds; ``treeinfer infer --amortised`` checks it on the spot against the
simulator (Pareto-smoothed importance weights) and falls back to the simulator-based path when
the check fails.

Modules: :mod:`.config` (the pull layout, training settings, the tree's fingerprint),
:mod:`.simulations` (training data from the batched simulator and the recordings' features),
:mod:`.network` (the summary network and the conditional flow, flowjax), :mod:`.space` (the
flow's coordinates: the prior's probit map), :mod:`.fastpath` (the trained estimator in NumPy:
a recording's posterior with nothing to compile), :mod:`.estimator` (train, save, load, refuse,
draw),
:mod:`.check` (the on-the-spot check and the run layer's start), :mod:`.calibration` (expected
coverage on held-out simulated data sets).

May import: treeinfer.inference, treeinfer.model, treeinfer.sim, treeinfer.data, treeinfer.tree,
treeinfer.io, treeinfer.errors (the calibration layer's place: above inference, below runs and
the command line, which pass its start to :func:`treeinfer.runs.run_inference`). flowjax (the
optional extra ``amortise``) only in :mod:`.network`, imported when a model is built.
"""

from ..io.lazy import lazy_package

_EXPORTS = {
    "AmortiseConfig": "config",
    "PullLayout": "config",
    "TrainConfig": "config",
    "Amortised": "estimator",
    "train": "estimator",
    "save": "estimator",
    "load": "estimator",
    "amortised_start": "check",
    "CheckReport": "check",
    "expected_coverage": "calibration",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_package(
    __name__,
    _EXPORTS,
    (
        "calibration",
        "check",
        "config",
        "estimator",
        "fastpath",
        "network",
        "simulations",
        "space",
    ),
)
