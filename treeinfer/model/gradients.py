"""Log-density composition and gradient estimators.

Conventions (shared by priors, likelihood and samplers):

* A **log-density term** is a batched function ``logdensity(theta [P, D]) -> [P]``
  returning ``log p`` (uphill: larger is more probable) for each of ``P``
  particles. Rows are independent; the batch is the primitive because the
  simulator-backed likelihood evaluates all rows in one call.
* A **value-and-grad function** is ``value_and_grad(theta [P, D]) -> (value [P], grad [P, D])``
  with ``grad = d log p / d theta`` (uphill).
* Terms compose by addition, optax-style: ``combine(prior, likelihood)``.
* A particle whose log-density is not finite (``-inf``, ``+inf`` or NaN, e.g. a
  blown-up rollout) gets value ``-inf`` and gradient ``0``; nothing non-finite
  leaks into other particles.

Black-box terms (the likelihood) get central finite differences
(:func:`central_difference`); differentiable terms (priors) get exact
autodiff (:func:`autodiff_value_and_grad`); :func:`combined_value_and_grad`
sums both.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp

from ..errors import ConfigError

__all__ = [
    "GRADIENT_METHODS",
    "LogDensityFn",
    "ValueAndGradFn",
    "autodiff_value_and_grad",
    "central_difference",
    "central_difference_jacobian",
    "combine",
    "combined_value_and_grad",
    "default_rel_step",
    "jvp_combined_value_and_grad",
    "jvp_value_and_grad",
    "likelihood_value_and_grad",
    "finite_difference_jvp",
    "mask_nonfinite",
]

LogDensityFn = Callable[[jax.Array], jax.Array]
"""``theta [P, D] -> log p [P]`` (batched over particles)."""

ValueAndGradFn = Callable[[jax.Array], tuple[jax.Array, jax.Array]]
"""``theta [P, D] -> (log p [P], d log p / d theta [P, D])``."""


def combine(*terms: LogDensityFn) -> LogDensityFn:
    """Sum of log-density terms: ``combine(f, g)(theta) == f(theta) + g(theta)``.

    Each term maps ``theta [P, D] -> [P]``. With no terms the result is the flat
    (zero) log-density.
    """
    terms = tuple(terms)
    for i, t in enumerate(terms):
        if not callable(t):
            raise ConfigError(
                f"combine: term {i} is {type(t).__name__}, not a log-density function"
            )

    def logdensity(theta: jax.Array) -> jax.Array:
        total = jnp.zeros(jnp.shape(theta)[:1], dtype=jnp.result_type(theta, jnp.float32))
        for t in terms:
            total = total + t(theta)
        return total

    return logdensity


def mask_nonfinite(value: jax.Array, grad: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Set ``value=-inf, grad=0`` for every particle whose value or gradient is not finite.

    value: [P]; grad: [P, D]. Other particles are untouched (elementwise ``where``).
    """
    bad = ~jnp.isfinite(value) | ~jnp.all(jnp.isfinite(grad), axis=-1)
    value = jnp.where(bad, -jnp.inf, value)
    grad = jnp.where(bad[:, None], jnp.zeros_like(grad), grad)
    return value, grad


def default_rel_step(dtype) -> float:
    """``eps ** (1/3)`` of ``dtype``: the step that balances truncation (~h^2) and
    round-off (~eps/h) error of a central difference; ~4.9e-3 in float32, ~6e-6 in float64."""
    return float(jnp.finfo(dtype).eps) ** (1.0 / 3.0)


def central_difference(
    logdensity_batch: LogDensityFn,
    rel_step: float | None = None,
    scale: float | jax.Array | None = None,
) -> ValueAndGradFn:
    """Central finite-difference value-and-gradient of a black-box batched log-density.

    For ``theta [P, D]`` the function builds the ``P * (2D + 1)`` points
    ``theta_p``, ``theta_p + h_pd e_d`` and ``theta_p - h_pd e_d``, evaluates
    ``logdensity_batch`` **once** on the stacked ``[P * (2D + 1), D]`` array, and
    returns ``value = f(theta)`` and ``grad_d = (f(theta + h e_d) - f(theta - h e_d)) / (2 h)``.
    The step actually used is ``(theta + h) - (theta - h)`` as represented in
    floating point, which removes the representation error of ``h``.

    Step size ``h_pd``:

    * ``scale=None`` (default): absolute step ``h = rel_step`` in every
      coordinate. This is the right choice when theta is a logarithm (treeinfer
      samples ``log Kp``, ``log Kd``): a fixed step in ``log K`` is a relative step
      ``exp(h) - 1 ~ h`` in ``K``, so it is scale-free.
    * ``scale`` given (float or ``[D]``): relative step
      ``h_pd = rel_step * max(|theta_pd|, scale_d)``, for parameters in their
      natural units; ``scale`` is the magnitude below which the step stops shrinking.

    ``rel_step=None`` uses ``eps ** (1/3)`` of theta's dtype (~4.9e-3 in float32).
    If the black box is noisier than round-off (e.g. a long simulation), a
    larger step is better: the error is ~ ``h^2 f''' / 6 + noise / h``.

    Non-finite handling: if the centre value or any perturbed value of a
    particle is ``-inf``/``+inf``/NaN, that particle gets value ``-inf`` and
    gradient ``0``. Other particles are unaffected.

    Returns ``value_and_grad(theta [P, D]) -> (value [P], grad [P, D])``.
    """
    if rel_step is not None and not (float(rel_step) > 0.0):
        raise ConfigError(f"central_difference: rel_step must be > 0, got {rel_step}")
    if scale is not None and not bool(jnp.all(jnp.asarray(scale) > 0)):
        raise ConfigError(f"central_difference: scale must be > 0, got {scale}")

    def value_and_grad(theta: jax.Array) -> tuple[jax.Array, jax.Array]:
        theta = jnp.asarray(theta)
        if theta.ndim != 2:
            raise ConfigError(
                f"central_difference: theta must have shape [P, D], got {theta.shape}"
            )
        if not jnp.issubdtype(theta.dtype, jnp.floating):
            theta = theta.astype(jnp.float32)
        n_particles, dim = theta.shape
        step = default_rel_step(theta.dtype) if rel_step is None else rel_step
        if scale is None:
            h = jnp.full_like(theta, step)
        else:
            h = step * jnp.maximum(jnp.abs(theta), jnp.asarray(scale, theta.dtype))
        eye = jnp.eye(dim, dtype=theta.dtype)
        offsets = h[:, :, None] * eye[None, :, :]  # [P, D(direction), D(coordinate)]
        plus = theta[:, None, :] + offsets  # [P, D, D]
        minus = theta[:, None, :] - offsets
        points = jnp.concatenate([theta[:, None, :], plus, minus], axis=1)  # [P, 2D+1, D]
        f = logdensity_batch(points.reshape(n_particles * (2 * dim + 1), dim))
        f = jnp.reshape(f, (n_particles, 2 * dim + 1))
        f0, fp, fm = f[:, 0], f[:, 1 : dim + 1], f[:, dim + 1 :]
        # Exact distance between the two evaluation points, as represented.
        two_h = jnp.diagonal(plus - minus, axis1=1, axis2=2)  # [P, D]
        ok = jnp.isfinite(f0) & jnp.all(jnp.isfinite(fp) & jnp.isfinite(fm), axis=1)
        # Replace non-finite inputs before arithmetic so no NaN is ever produced.
        fp = jnp.where(ok[:, None], fp, 0.0)
        fm = jnp.where(ok[:, None], fm, 0.0)
        grad = (fp - fm) / two_h
        return mask_nonfinite(jnp.where(ok, f0, -jnp.inf), grad)

    return value_and_grad


def autodiff_value_and_grad(logdensity_batch: LogDensityFn) -> ValueAndGradFn:
    """Exact value-and-gradient of a differentiable batched log-density.

    Uses one reverse pass of ``sum_p logdensity(theta)[p]``, which equals the
    per-particle gradients because rows are independent. Particles with a
    non-finite value or gradient get ``(-inf, 0)``.
    """

    def value_and_grad(theta: jax.Array) -> tuple[jax.Array, jax.Array]:
        theta = jnp.asarray(theta)
        value, vjp = jax.vjp(logdensity_batch, theta)
        (grad,) = vjp(jnp.ones_like(value))
        return mask_nonfinite(value, grad)

    return value_and_grad


def combined_value_and_grad(
    fd_terms: Sequence[LogDensityFn] = (),
    autodiff_terms: Sequence[LogDensityFn] = (),
    rel_step: float | None = None,
    scale: float | jax.Array | None = None,
) -> ValueAndGradFn:
    """Value-and-gradient of ``sum(fd_terms) + sum(autodiff_terms)``.

    The black-box ``fd_terms`` (the simulator likelihood) are summed first and
    differenced together by :func:`central_difference`, so they share one
    batched evaluation of ``P * (2D + 1)`` points; the ``autodiff_terms``
    (priors) get exact gradients. ``rel_step``/``scale`` go to
    :func:`central_difference`.
    """
    fd_terms, autodiff_terms = tuple(fd_terms), tuple(autodiff_terms)
    if not fd_terms and not autodiff_terms:
        raise ConfigError("combined_value_and_grad: give at least one log-density term")
    fd = (
        central_difference(combine(*fd_terms), rel_step=rel_step, scale=scale) if fd_terms else None
    )
    ad = autodiff_value_and_grad(combine(*autodiff_terms)) if autodiff_terms else None

    def value_and_grad(theta: jax.Array) -> tuple[jax.Array, jax.Array]:
        parts = [vg(theta) for vg in (fd, ad) if vg is not None]
        value = sum(p[0] for p in parts)
        grad = sum(p[1] for p in parts)
        return mask_nonfinite(value, grad)

    return value_and_grad


# ---- forward-mode (exact) gradients of the simulator likelihood ------------------------------
# (issue 15 item 1; kept in its own section: another section below/above may wrap the batched
# simulator in a custom_jvp.)
#
# The fused simulator is pure JAX, so its exact derivative is available. With D = 2R parameters
# and one scalar output per particle, forward mode pushes the D tangent directions through the
# rollout side by side (``vmap`` over ``jax.jvp`` with the primal unbatched: the rollout itself
# runs once). The fused pull carries a ``custom_jvp`` (``treeinfer.sim.fused_backend``,
# ``treeinfer.sim.sensitivity``): each step's state Jacobian is computed once, independent of
# the tangent, so under this ``vmap`` all D directions share it and each adds only a few
# multiply-adds per joint (2.2 rollouts per particle for D = 6 on the standard problem, against
# 13 for central differences; ``benchmarks/gradient_cost.py``). Reverse mode would need the
# whole [P, B, T, substeps] state trajectory kept for the backward pass; forward mode keeps only
# the current step, like the rollout itself.

GRADIENT_METHODS = ("fd", "jvp")


def jvp_value_and_grad(logdensity_batch: LogDensityFn) -> ValueAndGradFn:
    """Exact value-and-gradient of a batched log-density by forward-mode autodiff.

    ``logdensity_batch(theta [P, D]) -> [P]`` must be differentiable JAX (e.g. the Boltzmann
    likelihood on the fused simulator). Rows are independent, so the tangent ``e_d`` given to
    every row at once returns ``d log p_p / d theta_pd`` for all particles: the D basis tangents
    run in one ``vmap``-ed ``jax.jvp``, sharing one primal rollout and, on the fused simulator,
    each step's Jacobian (cost measured in ``python -m benchmarks.gradient_cost``).

    Non-finite handling as :func:`central_difference`: a particle whose value or gradient is
    not finite (unstable rollout) gets ``(-inf, 0)``.

    Returns ``value_and_grad(theta [P, D]) -> (value [P], grad [P, D])``.
    """

    def value_and_grad(theta: jax.Array) -> tuple[jax.Array, jax.Array]:
        theta = jnp.asarray(theta)
        if theta.ndim != 2:
            raise ConfigError(
                f"jvp_value_and_grad: theta must have shape [P, D], got {theta.shape}"
            )
        if not jnp.issubdtype(theta.dtype, jnp.floating):
            theta = theta.astype(jnp.float32)
        n_particles, dim = theta.shape
        basis = jnp.broadcast_to(
            jnp.eye(dim, dtype=theta.dtype)[:, None, :], (dim, n_particles, dim)
        )
        push = lambda tangent: jax.jvp(logdensity_batch, (theta,), (tangent,))
        value, directional = jax.vmap(push, out_axes=(None, 0))(basis)  # [P], [D, P]
        return mask_nonfinite(value, directional.T)

    return value_and_grad


def likelihood_value_and_grad(
    loglik: LogDensityFn, method: str = "fd", rel_step: float | None = None
) -> ValueAndGradFn:
    """The simulator likelihood's value-and-grad by ``method``: ``"fd"`` (central differences,
    the paper's black-box route and the default) or ``"jvp"`` (exact forward mode)."""
    if method == "fd":
        return central_difference(loglik, rel_step=rel_step)
    if method == "jvp":
        return jvp_value_and_grad(loglik)
    raise ConfigError(f"gradients: expected one of {', '.join(GRADIENT_METHODS)}, got {method!r}")


def jvp_combined_value_and_grad(
    simulator_terms: Sequence[LogDensityFn] = (),
    autodiff_terms: Sequence[LogDensityFn] = (),
) -> ValueAndGradFn:
    """:func:`combined_value_and_grad` with the simulator terms differentiated exactly by
    forward mode (:func:`jvp_value_and_grad`) instead of central differences; the other terms
    (priors) by reverse-mode autodiff as there."""
    simulator_terms, autodiff_terms = tuple(simulator_terms), tuple(autodiff_terms)
    if not simulator_terms and not autodiff_terms:
        raise ConfigError("jvp_combined_value_and_grad: give at least one log-density term")
    parts = []
    if simulator_terms:
        parts.append(jvp_value_and_grad(combine(*simulator_terms)))
    if autodiff_terms:
        parts.append(autodiff_value_and_grad(combine(*autodiff_terms)))

    def value_and_grad(theta: jax.Array) -> tuple[jax.Array, jax.Array]:
        out = [vg(theta) for vg in parts]
        return mask_nonfinite(sum(o[0] for o in out), sum(o[1] for o in out))

    return value_and_grad


# =========================================================================================
# Black boxes that JAX can differentiate: a custom_jvp whose derivative is the batched
# central difference (issue 11). numpyro / BlackJAX / jax.grad code differentiates through
# the wrapped function unchanged; the black box is still called ONCE per derivative, on the
# stacked [N * (2D + 1), D] points, exactly as in :func:`central_difference`.
# =========================================================================================


def central_difference_jacobian(
    fn_batch: Callable[[jax.Array], jax.Array],
    theta: jax.Array,
    rel_step: float | None = None,
) -> tuple[jax.Array, jax.Array]:
    """Value and central-difference Jacobian of a batched black box, in one batched call.

    Args:
      fn_batch: ``theta [M, D] -> out [M, *S]`` (rows independent; any float output shape).
      theta: ``[N, D]`` points.
      rel_step: absolute step in every coordinate (theta in log units: a relative step in the
        natural parameter); None: ``eps ** (1/3)`` of theta's dtype, as :func:`central_difference`.

    Returns:
      ``(value [N, *S], jac [N, *S, D])`` with ``jac[..., d] = (f(theta + h e_d) - f(theta - h e_d))
      / (2 h)`` (the exact distance between the two evaluation points as represented). Non-finite
      outputs propagate (a NaN/inf output at a perturbed point gives a NaN/inf Jacobian entry);
      :func:`mask_nonfinite` then drops that particle downstream.
    """
    theta = jnp.asarray(theta)
    if theta.ndim != 2:
        raise ConfigError(f"central_difference_jacobian: theta must be [N, D], got {theta.shape}")
    n, dim = theta.shape
    step = default_rel_step(theta.dtype) if rel_step is None else rel_step
    offsets = step * jnp.eye(dim, dtype=theta.dtype)  # [D(direction), D(coordinate)]
    plus = theta[:, None, :] + offsets[None]
    minus = theta[:, None, :] - offsets[None]
    points = jnp.concatenate([theta[:, None, :], plus, minus], axis=1)  # [N, 2D+1, D]
    out = fn_batch(points.reshape(n * (2 * dim + 1), dim))
    out = out.reshape((n, 2 * dim + 1) + out.shape[1:])
    two_h = jnp.diagonal(plus - minus, axis1=1, axis2=2)  # [N, D]
    two_h = two_h.reshape((n, dim) + (1,) * (out.ndim - 2))
    jac = (out[:, 1 : dim + 1] - out[:, dim + 1 :]) / two_h  # [N, D, *S]
    return out[:, 0], jnp.moveaxis(jac, 1, -1)


def finite_difference_jvp(
    fn_batch: Callable[[jax.Array], jax.Array], rel_step: float | None = None
) -> Callable[[jax.Array], jax.Array]:
    """Wrap a batched black box ``theta [N, D] -> out [N, *S]`` so JAX can differentiate it.

    The result is a ``jax.custom_jvp`` function: its value is ``fn_batch(theta)``, its JVP is
    ``J(theta) @ t`` with ``J`` from :func:`central_difference_jacobian` (one batched call of
    ``fn_batch`` on ``N * (2D + 1)`` points, which also gives the value). The JVP is linear in
    the tangent, so reverse mode (``jax.grad``, ``jax.vjp``) works by transposition: numpyro's
    NUTS, BlackJAX kernels and ``autodiff_value_and_grad`` all differentiate through it.

    Use it for the simulator alone (``out = tau [N, B, T]``) and put the differentiable parts
    (noise model, priors, extra columns such as ``log sigma``) outside it: those then get exact
    gradients and cost no extra simulations. Higher derivatives are not supported (the JVP
    rule is not itself differentiable in a meaningful way).
    """

    @jax.custom_jvp
    def wrapped(theta):
        return fn_batch(theta)

    @wrapped.defjvp
    def _jvp(primals, tangents):
        (theta,), (t,) = primals, tangents
        value, jac = central_difference_jacobian(fn_batch, theta, rel_step)
        t = jnp.asarray(t, jac.dtype).reshape((t.shape[0],) + (1,) * (jac.ndim - 2) + (t.shape[1],))
        return value, jnp.sum(jac * t, axis=-1)

    return wrapped
