"""The batched LM fit's stopping rules (treeinfer.inference.fast_fit) are in nats, not relative to
the objective's size: a log density of a few thousand nats (the standard problem's 4,220) must not
let a start stop on a step that still gains tenths of a nat."""

import types

import numpy as np
import pytest

from treeinfer.inference import fast_fit
from treeinfer.inference.fast_fit import fit_map_batched


class _RosenbrockEvaluator:
    """A stand-in for BatchEvaluator (Boltzmann objective ``sum_g ||r_g|| / kT - lp``): residuals
    of Rosenbrock's valley ``r = [10 (y - x^2), 1 - x]`` (minimum at (1, 1), reached along a curved
    ridge in many small steps) and a constant log prior ``offset`` that only makes |f| large."""

    boltzmann = True
    kT = 1.0
    n_gains = 2
    substeps = 1

    def __init__(self, offset: float):
        self.offset = offset
        self.problem = types.SimpleNamespace(lower=np.full(2, -5.0), upper=np.full(2, 5.0))

    def evaluate(self, pts, substeps=None):
        x, y = pts[:, 0], pts[:, 1]
        r = np.stack([10.0 * (y - x**2), 1.0 - x], axis=1)[:, None, :]  # [N, G=1, T=2]
        return r, np.ones(len(pts), bool), np.full(len(pts), -self.offset)


@pytest.mark.parametrize("offset", [0.0, 5000.0])
def test_a_large_objective_does_not_stop_the_fit_on_the_ridge(offset):
    starts = np.array([[-1.2, 1.0], [-0.5, 1.5]])
    fit = fit_map_batched(_RosenbrockEvaluator(offset), starts, max_iterations=300)
    # the same answer whatever the constant: the optimum of the valley
    np.testing.assert_allclose(fit.theta, [1.0, 1.0], atol=0.02)
    assert fit.neg_log_posterior == pytest.approx(offset, abs=0.05)


def test_the_old_relative_rule_stopped_short(monkeypatch):
    # the rules as they were (relative only): with |f| = 5000 a step gaining < 0.5 nats counted as
    # converged, and the start stopped far from the optimum (what the nats caps prevent)
    monkeypatch.setattr(fast_fit, "STEP_NATS", np.inf)
    monkeypatch.setattr(fast_fit, "AGREE_NATS", np.inf)
    fit = fit_map_batched(_RosenbrockEvaluator(5000.0), np.array([[-1.2, 1.0]]), 300)
    assert np.max(np.abs(fit.theta - 1.0)) > 0.1
