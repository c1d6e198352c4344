"""experiments/stem_pushes.py's NUTS wrapper (BlackJAX, window adaptation from the Laplace start)
against a closed-form posterior: a correlated 3-D Gaussian's mean and covariance."""

import types

import jax
import jax.numpy as jnp
import numpy as np

from experiments.stem_pushes import _nuts_draws


def test_nuts_draws_recover_correlated_gaussian():
    cov = np.array([[1.0, 0.5, 0.0], [0.5, 2.0, 0.3], [0.0, 0.3, 0.5]])
    prec, mu = np.linalg.inv(cov), np.array([0.3, -0.2, 0.1])

    def log_density(x):  # [N, 3] -> [N]
        d = x - mu
        return -0.5 * jnp.einsum("ni,ij,nj->n", d, prec, d)

    def value_and_grad(x):
        return log_density(x), jax.grad(lambda y: log_density(y).sum())(x)

    problem = types.SimpleNamespace(
        log_density=jax.jit(log_density),
        value_and_grad=jax.jit(value_and_grad),
        lower=-5.0 * np.ones(3),
        upper=5.0 * np.ones(3),
    )
    args = types.SimpleNamespace(
        walkers=4, warmup=200, steps=500, draws=2000, max_doublings=4, laplace="values"
    )
    theta, rhat, acc, _, n_div = _nuts_draws(problem, args, seed=0)
    assert theta.shape == (2000, 3)
    assert np.all(rhat < 1.05) and n_div == 0 and acc > 0.6
    # 2000 draws: standard error of each mean <= sqrt(2 / 2000) ~ 0.03 (ESS >= draws / 2)
    np.testing.assert_allclose(theta.mean(0), mu, atol=0.12)
    np.testing.assert_allclose(np.cov(theta.T), cov, atol=0.25)
