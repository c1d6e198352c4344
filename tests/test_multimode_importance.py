"""The start pipeline's pooled importance sampling over several modes
(:func:`treeinfer.inference.start_steps.multimode_importance`) against a closed-form bimodal
posterior, with and without proposals that overlap."""

import numpy as np
import pytest
from scipy import stats

from treeinfer.inference.start_steps import multimode_importance

W, MU, SD = 0.3, np.array([-3.0, 3.0]), 0.5  # 0.7 N(-3, 0.5) + 0.3 N(3, 0.5), and N(0, 1) in y


def log_density(x):
    x = np.atleast_2d(x)
    left = np.log(1 - W) + stats.norm.logpdf(x[:, 0], MU[0], SD)
    right = np.log(W) + stats.norm.logpdf(x[:, 0], MU[1], SD)
    return np.logaddexp(left, right) + stats.norm.logpdf(x[:, 1])


@pytest.mark.parametrize(
    "modes",
    [
        [[-3.0, 0.0], [3.0, 0.0]],  # one proposal per mode
        # a third start on the left mode, off its centre: its proposal overlaps the first one's
        # (modes on one ridge of the multi-start fit); pooled by evidence shares the overlap
        # counted twice, and dropping it lost what only it covered
        [[-3.0, 0.0], [3.0, 0.0], [-2.2, 0.3]],
        [[-3.0, 0.0], [3.0, 0.0], [-3.0, 1.8]],  # overlapping in x only: never merged
    ],
)
def test_pooled_weights_give_the_closed_form_mixture(modes):
    cov = np.diag([SD**2, 1.0])
    imp, idx = multimode_importance(
        log_density, np.array(modes), cov, 1500, 200, 0, 7.0, 4, 800.0, 400.0
    )
    w = np.exp(imp.log_weights)
    assert imp.ok, imp.reason
    assert len(imp.draws) == len(w) == len(imp.log_density)
    np.testing.assert_allclose(imp.log_density, log_density(imp.draws), rtol=1e-12)
    right = float(np.sum(w[imp.draws[:, 0] > 0]))
    assert abs(right - W) < 0.03, right
    mean = np.sum(w[:, None] * imp.draws, axis=0)
    np.testing.assert_allclose(mean, [(1 - W) * MU[0] + W * MU[1], 0.0], atol=0.1)
    var0 = np.sum(w * (imp.draws[:, 0] - mean[0]) ** 2)
    exact = SD**2 + (1 - W) * W * (MU[1] - MU[0]) ** 2
    assert abs(var0 - exact) < 0.1 * exact
    # the particles: resampled from the weighted draws
    assert np.allclose(imp.theta, imp.draws[idx])
    assert abs(np.mean(imp.theta[:, 0] > 0) - W) < 0.1


def test_distinct_modes_keeps_the_finals_along_a_ridge():
    """The multi-start fit's finals on one curved ridge lie within 2 sd of each other in the
    best's Laplace covariance (the weak direction's sd is large); each one more than
    MODE_SEPARATION sd from the others in some coordinate is a mode of its own, so the polish
    and the mixture proposal cover the ridge, not only the end the best slid to."""
    from types import SimpleNamespace

    from treeinfer.inference.start_steps import MAX_MODES, MODE_GAP, distinct_modes

    finals = np.array([[0.0, 0.0], [0.8, 0.1], [1.6, 0.3], [1.65, 0.3], [3.0, 0.0]])
    values = np.array([0.0, 1.0, 2.6, 2.7, MODE_GAP + 1.0])  # -log p
    fit = SimpleNamespace(finals=finals, values=values, theta=finals[0])
    kept = distinct_modes(fit, np.eye(2))
    # the near-duplicate (1.65) and the one beyond MODE_GAP are left out
    np.testing.assert_array_equal(kept, finals[:3])
    assert MAX_MODES >= 3
    # a point 0.4 sd from the best is the same mode
    fit2 = SimpleNamespace(finals=finals[:1] + [[0.0], [0.4]], values=values[:2], theta=finals[0])
    assert len(distinct_modes(fit2, np.eye(2))) == 1
