"""``--init laplace``'s printed spread is the spread its particles are drawn with.

The CLI used to print the fit's own covariance, which is unbounded in a column the loss does
not see: ``treeinfer demo --likelihood gaussian`` printed a std of 2.45e+04 for log sigma_x
(the Boltzmann LM fit has no curvature there), while the particles were drawn with the prior
box's spread in that column. ``laplace.particle_covariance`` is now the one place both use."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from treeinfer.inference.laplace import laplace_particles, particle_covariance
from treeinfer.inference.mapfit import MapFit


def _fit(norm_cov=None):
    hess = np.diag([100.0, 0.0])  # the second column: no curvature from the loss
    return MapFit(
        theta=np.array([0.2, 1.0]),
        cov=np.diag([0.01, 1e6]),
        hessian=hess,
        neg_log_posterior=0.0,
        starts=np.zeros((1, 2)),
        finals=np.zeros((1, 2)),
        values=np.zeros(1),
        converged=np.ones(1, bool),
        iterations=1,
        lower=np.array([-1.0, -1.0]),
        upper=np.array([1.0, 5.0]),
        n_model=2,
        settings={},
        norm_cov=norm_cov,
    )


def test_spread_is_the_fit_plus_the_box_and_the_draws_follow_it():
    fit = _fit()
    # precision 100 + 12 / 2^2 and 0 + 12 / 6^2 (a uniform's variance width^2 / 12)
    want = np.array([1.0 / np.sqrt(103.0), np.sqrt(3.0)])
    np.testing.assert_allclose(np.sqrt(np.diag(particle_covariance(fit))), want, rtol=1e-9)
    draws = np.asarray(laplace_particles(jax.random.key(0), fit, 40000))
    np.testing.assert_allclose(draws.std(axis=0), want, rtol=0.03)
    np.testing.assert_allclose(draws.mean(axis=0), fit.theta, atol=0.03)


def test_the_boltzmann_matched_covariance_is_used_when_present():
    fit = _fit(norm_cov=np.diag([0.04, 1e8]))  # unbounded in the unseen column, as in the demo
    want = np.array([1.0 / np.sqrt(25.0 + 3.0), np.sqrt(3.0)])
    assert np.sqrt(np.diag(particle_covariance(fit))) == pytest.approx(want, rel=1e-6)
