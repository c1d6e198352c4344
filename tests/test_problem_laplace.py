"""The Laplace start of any problem (:func:`treeinfer.inference.laplace.problem_laplace`): the MAP
and the Hessian of the log-density's values, checked on a Gaussian of known mean and covariance, and
the MH proposal built from it. ``--init laplace`` for the static model with a soft taper tie runs in
``tests/test_tie.py``'s CLI test."""

from __future__ import annotations

from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np

from treeinfer.inference.laplace import (
    mh_proposal,
    problem_laplace,
    problem_laplace_particles,
    value_hessian,
)


def _gaussian_problem(mean, cov, lower, upper):
    prec = jnp.asarray(np.linalg.inv(cov), jnp.float32)
    mu = jnp.asarray(mean, jnp.float32)

    def log_density(theta):
        d = jnp.asarray(theta, jnp.float32) - mu
        return -0.5 * jnp.einsum("pi,ij,pj->p", d, prec, d)

    def value_and_grad(theta):
        d = jnp.asarray(theta, jnp.float32) - mu
        return log_density(theta), -(d @ prec)

    return SimpleNamespace(
        lower=np.asarray(lower, float),
        upper=np.asarray(upper, float),
        log_density=log_density,
        value_and_grad=value_and_grad,
    )


def test_laplace_of_a_gaussian_recovers_its_mean_and_covariance():
    mean = np.array([1.0, -0.5, 0.2])
    a = np.array([[0.3, 0.0, 0.0], [0.1, 0.05, 0.0], [-0.02, 0.01, 0.2]])
    cov = a @ a.T  # correlated, stds 0.05 .. 0.3
    prob = _gaussian_problem(mean, cov, [-3, -3, -3], [3, 3, 3])
    lap = problem_laplace(prob, n_starts=16, seed=1, box_precision=False)
    np.testing.assert_allclose(lap.theta, mean, atol=1e-3)
    np.testing.assert_allclose(lap.cov, cov, rtol=2e-2, atol=2e-4)
    # the box's precision only adds 12 / width^2
    boxed = problem_laplace(prob, n_starts=16, seed=1)
    np.testing.assert_allclose(
        np.linalg.inv(boxed.cov) - np.linalg.inv(cov), np.diag([12 / 36.0] * 3), atol=0.05
    )
    # draws have that covariance; the MH proposal is 2.38 / sqrt(D) of its Cholesky factor
    x = np.asarray(problem_laplace_particles(jax.random.key(0), lap, 20000))
    np.testing.assert_allclose(np.cov(x.T), lap.cov, rtol=0.05, atol=5e-4)
    chol = mh_proposal(lap.cov)
    np.testing.assert_allclose(chol @ chol.T, 2.38**2 / 3 * lap.cov, rtol=1e-6, atol=1e-9)


def test_value_hessian_of_a_quadratic_is_exact():
    h = np.array([[-4.0, 1.0], [1.0, -2.0]])
    prob = SimpleNamespace(
        log_density=lambda th: 0.5 * jnp.einsum("pi,ij,pj->p", th, jnp.asarray(h), th) + 3.0
    )
    np.testing.assert_allclose(value_hessian(prob, [0.3, -0.2], [0.1, 0.2]), h, atol=1e-3)


def test_a_hessian_difference_outside_the_density_gets_the_box_spread():
    """A MAP near a wall of the density (-inf past x1 = 0.2: a rollout that goes unstable, a
    prior edge): the differences that cross it are not finite; that direction gets no
    curvature, i.e. the box's 12 / width^2, and the other keeps its own (1 / 0.3^2). Before,
    numpy's eigh raised 'Eigenvalues did not converge' on the NaN."""
    base = _gaussian_problem([0.0, 0.15], np.diag([0.3**2, 0.1**2]), [-3, -3], [3, 3])

    def log_density(theta):
        t = jnp.asarray(theta, jnp.float32)
        return jnp.where(t[:, 1] > 0.2, -jnp.inf, base.log_density(t))

    # the fit's own gradient sees no wall (it stays inside); the Hessian's differences do
    prob = SimpleNamespace(lower=base.lower, upper=base.upper, log_density=log_density,
                           value_and_grad=base.value_and_grad)  # fmt: skip
    lap = problem_laplace(prob, n_starts=16, seed=0)
    assert np.all(np.isfinite(lap.cov))
    np.testing.assert_allclose(lap.theta, [0.0, 0.15], atol=2e-3)  # 0.06 steps cross the wall
    prec = np.linalg.inv(lap.cov)
    np.testing.assert_allclose(prec[0, 0], 1 / 0.3**2 + 12 / 36.0, rtol=0.05)
    np.testing.assert_allclose(prec[1, 1], 12 / 36.0, rtol=0.05)
