"""Finite-difference and autodiff value-and-gradient estimators vs closed forms."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from treeinfer.errors import ConfigError
from treeinfer.model.gradients import (
    autodiff_value_and_grad,
    central_difference,
    combine,
    combined_value_and_grad,
    default_rel_step,
)

KEY = jax.random.key(0)
THETA = jax.random.normal(KEY, (16, 3))

# Closed forms: (logdensity [P, D] -> [P], gradient [P, D] -> [P, D]).
A = jnp.array([[2.0, 0.3, -0.1], [0.3, 1.0, 0.2], [-0.1, 0.2, 0.5]])  # SPD precision
MU = jnp.array([0.5, -1.0, 0.25])


def quad(t):
    return -jnp.sum(1.5 * t**2 + t, axis=1)


def quad_grad(t):
    return -(3.0 * t + 1.0)


def sinprod(t):
    return jnp.prod(jnp.sin(t), axis=1)


def sinprod_grad(t):
    s, c = jnp.sin(t), jnp.cos(t)
    d = t.shape[1]
    return jnp.stack(
        [
            c[:, i] * jnp.prod(jnp.delete(s, i, axis=1, assume_unique_indices=True), axis=1)
            for i in range(d)
        ],
        axis=1,
    )


def gauss(t):
    d = t - MU
    return -0.5 * jnp.einsum("pi,ij,pj->p", d, A, d)


def gauss_grad(t):
    return -(t - MU) @ A


CASES = [(quad, quad_grad), (sinprod, sinprod_grad), (gauss, gauss_grad)]


@pytest.mark.parametrize("f,grad", CASES, ids=["quadratic", "sin-product", "gaussian"])
def test_central_difference_matches_closed_form(f, grad):
    value, g = jax.jit(central_difference(f))(THETA)
    np.testing.assert_allclose(value, f(THETA), rtol=1e-6)
    # float32, h ~ 4.9e-3: truncation h^2 |f'''|/6 ~ 1e-5, round-off eps |f| / h ~ 1e-4
    np.testing.assert_allclose(g, grad(THETA), atol=2e-3, rtol=2e-3)


@pytest.mark.parametrize("f,grad", CASES, ids=["quadratic", "sin-product", "gaussian"])
def test_autodiff_matches_closed_form(f, grad):
    value, g = jax.jit(autodiff_value_and_grad(f))(THETA)
    np.testing.assert_allclose(value, f(THETA), rtol=1e-6)
    np.testing.assert_allclose(g, grad(THETA), atol=1e-5, rtol=1e-5)


def test_relative_step_with_scale():
    theta = jnp.array([[100.0, 0.01], [-3.0, 2.0]])
    _, g = jax.jit(central_difference(sinprod, scale=1.0))(theta)
    np.testing.assert_allclose(g, sinprod_grad(theta), atol=5e-3)
    with pytest.raises(ConfigError):
        central_difference(sinprod, scale=-1.0)
    with pytest.raises(ConfigError):
        central_difference(sinprod, rel_step=0.0)


def test_error_decreases_like_h_squared():
    # float64 so round-off does not mask the truncation error.
    with jax.enable_x64(True):
        t = jnp.asarray(np.random.default_rng(1).normal(size=(8, 3)), jnp.float64)
        errs = []
        steps = [0.2, 0.1, 0.05, 0.025]
        for h in steps:
            _, g = jax.jit(central_difference(sinprod, rel_step=h))(t)
            errs.append(float(jnp.max(jnp.abs(g - sinprod_grad(t)))))
        orders = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
        np.testing.assert_allclose(orders, 2.0, atol=0.1)
        assert default_rel_step(jnp.float64) == pytest.approx(6.06e-6, rel=0.01)
    assert default_rel_step(jnp.float32) == pytest.approx(4.92e-3, rel=0.01)


def test_fd_agrees_with_autodiff_on_random_points():
    t = jax.random.uniform(jax.random.key(3), (64, 4), minval=-2, maxval=2)

    def f(t):
        return jnp.sum(jnp.cos(t) * t[:, ::-1], axis=1) - jnp.sum(t**2, axis=1) ** 1.5 / 10

    v1, g1 = jax.jit(central_difference(f))(t)
    v2, g2 = jax.jit(autodiff_value_and_grad(f))(t)
    np.testing.assert_allclose(v1, v2, rtol=1e-6)
    np.testing.assert_allclose(g1, g2, atol=3e-3, rtol=3e-3)


def test_one_batched_call_of_stacked_points():
    calls = []

    def f(t):
        calls.append(t.shape)  # Python side effect: runs at trace time only
        return gauss(t)

    vg = jax.jit(central_difference(f))
    vg(THETA)
    vg(THETA + 1.0)  # cached: no retrace
    assert calls == [(16 * (2 * 3 + 1), 3)]


def test_nonfinite_particles_are_isolated():
    # -inf where theta_0 > 1 (a "blown-up" region), NaN where theta_1 < -1.5.
    def f(t):
        v = gauss(t)
        v = jnp.where(t[:, 0] > 1.0, -jnp.inf, v)
        return jnp.where(t[:, 1] < -1.5, jnp.nan, v)

    h = 5e-3
    theta = jnp.array(
        [
            [0.0, 0.0, 0.0],  # fine
            [2.0, 0.0, 0.0],  # centre -inf
            [1.0 - h / 2, 0.0, 0.0],  # centre fine, + perturbation -inf
            [0.0, -2.0, 0.0],  # NaN
            [0.3, 0.4, -0.2],  # fine
        ]
    )
    ok = np.array([0, 4])
    value, g = jax.jit(central_difference(f, rel_step=h))(theta)
    assert np.all(np.isfinite(g))
    np.testing.assert_array_equal(np.isfinite(value), [True, False, False, False, True])
    assert np.all(value[~np.isfinite(value)] == -np.inf)
    np.testing.assert_array_equal(g[1:4], 0.0)
    np.testing.assert_allclose(g[ok], gauss_grad(theta[ok]), atol=2e-3)
    np.testing.assert_allclose(value[ok], gauss(theta[ok]), rtol=1e-6)

    value, g = autodiff_value_and_grad(f)(theta)
    assert np.all(np.isfinite(g)) and value[1] == -np.inf and value[3] == -np.inf
    np.testing.assert_allclose(g[ok], gauss_grad(theta[ok]), rtol=1e-5)


def test_combine_and_combined_value_and_grad():
    logp = combine(quad, sinprod, gauss)
    np.testing.assert_allclose(logp(THETA), quad(THETA) + sinprod(THETA) + gauss(THETA), rtol=1e-6)
    assert combine()(THETA).shape == (16,)

    calls = []

    def likelihood(t):
        calls.append(1)
        return sinprod(t) + quad(t)

    vg = jax.jit(combined_value_and_grad(fd_terms=[likelihood, sinprod], autodiff_terms=[gauss]))
    value, g = vg(THETA)
    assert len(calls) == 1  # both FD terms share one batched evaluation
    np.testing.assert_allclose(value, 2 * sinprod(THETA) + quad(THETA) + gauss(THETA), rtol=1e-5)
    np.testing.assert_allclose(
        g, 2 * sinprod_grad(THETA) + quad_grad(THETA) + gauss_grad(THETA), atol=3e-3
    )
    with pytest.raises(ConfigError):
        combined_value_and_grad()
    with pytest.raises(ConfigError):
        combine(quad, 3.0)
