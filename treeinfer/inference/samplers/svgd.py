"""Stein variational gradient descent (Liu & Wang 2016), paper section "SVGD".

Each step moves all particles along the Stein direction

    phi(x_i) = 1/n sum_j [ k(x_j, x_i) grad log p(x_j) + grad_{x_j} k(x_j, x_i) ]

with the RBF kernel ``k(x, y) = exp(-||x - y||^2 / h)`` (BlackJAX's
``rbf_kernel``; the paper's ``exp(-||x - y||^2 / (2 sigma^2))`` with
``h = 2 sigma^2``) and ``h`` from the median heuristic
``h = median_{i<j} ||x_i - x_j||^2 / log n`` of the *current* particles.
The update ``-phi`` is handed to an optax optimiser (Adam by default), as in
BlackJAX and the paper.

Why not ``blackjax.svgd`` itself: it calls a per-particle gradient under a
double ``vmap`` (n^2 calls), while our gradient is one batched
finite-difference evaluation of all particles; its step takes no key, returns
no info, and updates the bandwidth *after* the step by mutating a (default,
shared) dict, so step 1 uses ``h = 1``; and one particle or collapsed
particles give a NaN/zero bandwidth. We reuse its ``rbf_kernel`` and
``median_heuristic`` (on a fresh dict each step) and guard the result.
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING, Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ...errors import ConfigError
from ...model.gradients import ValueAndGradFn
from ..diagnostics import kernel_stein_discrepancy
from .base import SamplingAlgorithm, check_positions, count_nonfinite, finite_mean, positive

if TYPE_CHECKING:  # annotations only: optax is imported where it is used
    import optax

__all__ = [
    "WARMUP_START_DIVISOR",
    "SVGDInfo",
    "SVGDState",
    "median_length_scale",
    "nnsvgd",
    "stein_direction",
    "svgd",
]

WARMUP_START_DIVISOR = 20.0  # a warm-up starts at learning_rate / 20


class SVGDState(NamedTuple):
    """position [P, D]; logdensity [P] and logdensity_grad [P, D] at ``position``;
    opt_state: the optax optimiser state."""

    position: jax.Array
    logdensity: jax.Array
    logdensity_grad: jax.Array
    opt_state: Any


class SVGDInfo(NamedTuple):
    """bandwidth: RBF ``h`` used by this step (theta units squared);
    mean_logdensity: mean finite log p of the new particles;
    grad_norm: mean ||grad log p|| over the new particles;
    n_nonfinite: new particles whose log p is not finite;
    ksd: IMQ kernelized Stein discrepancy of the new particles on standardised coordinates
    (:func:`treeinfer.inference.diagnostics.kernel_stein_discrepancy`; its plateau marks
    convergence; O(P^2 D) from the gradients already at hand, no extra target evaluation)."""

    bandwidth: jax.Array
    mean_logdensity: jax.Array
    grad_norm: jax.Array
    n_nonfinite: jax.Array
    ksd: jax.Array


def median_length_scale(particles: jax.Array, min_length_scale: float = 1e-6) -> jax.Array:
    """Median-heuristic ``h`` of ``particles [P, D]``, floored at ``min_length_scale``.

    One particle has no pairwise distances: ``h = 1`` (the kernel term then
    vanishes anyway and SVGD is gradient ascent). Collapsed particles
    (median distance 0) get the floor instead of ``h = 0`` (NaN kernel).
    """
    if particles.shape[0] < 2:
        return jnp.asarray(1.0, particles.dtype)
    from blackjax.vi import svgd as _bj_svgd

    # Fresh dict each call: BlackJAX writes the result into the dict it is given.
    h = _bj_svgd.median_heuristic({}, particles)["length_scale"]
    return jnp.where(jnp.isfinite(h) & (h > min_length_scale), h, min_length_scale).astype(
        particles.dtype
    )


def stein_direction(particles: jax.Array, grads: jax.Array, length_scale) -> jax.Array:
    """SVGD direction ``phi [P, D]`` (uphill) for particles ``[P, D]`` with
    ``grads = grad log p [P, D]`` and RBF length scale ``h``."""
    from blackjax.vi import svgd as _bj_svgd

    kernel = functools.partial(_bj_svgd.rbf_kernel, length_scale=length_scale)
    k_and_dk = jax.vmap(  # over i (second argument)
        jax.vmap(jax.value_and_grad(kernel), in_axes=(0, None)),  # over j (first argument)
        in_axes=(None, 0),
    )
    k, dk = k_and_dk(particles, particles)  # k[i, j] = k(x_j, x_i); dk[i, j] = d/dx_j k(x_j, x_i)
    return (k @ grads + dk.sum(axis=1)) / particles.shape[0]


def svgd(
    value_and_grad_fn: ValueAndGradFn,
    learning_rate: float = 1e-2,
    optimizer: optax.GradientTransformation | None = None,
    length_scale: float | None = None,
    min_length_scale: float = 1e-6,
    name: str = "svgd",
    warmup: int = 0,
) -> SamplingAlgorithm:
    """SVGD with an RBF kernel and median-heuristic bandwidth.

    Args:
      value_and_grad_fn: batched ``theta [P, D] -> (log p [P], grad [P, D])``,
        e.g. :func:`treeinfer.model.gradients.combined_value_and_grad`.
      learning_rate: Adam learning rate (theta units per step), used when
        ``optimizer`` is None.
      optimizer: any optax transformation applied to ``-phi`` (it minimises);
        ``optax.sgd(eps)`` gives the plain update ``x += eps * phi``.
      length_scale: fixed RBF ``h``; None (default) recomputes the median
        heuristic from the current particles before every update.
      min_length_scale: floor for the heuristic (collapsed particles).
      name: recorded sampler name.
      warmup: iterations over which Adam's learning rate ramps linearly from
        ``learning_rate / 20`` up to ``learning_rate`` (``optax.linear_schedule``; 0: constant).
        For particles that start near the posterior (``--init laplace``): Adam's first steps
        move every coordinate by about the learning rate whatever its gradient, which scatters
        particles that already have the right spread. Only with ``optimizer=None``.

    The key passed to ``step`` is ignored: SVGD is deterministic, so exactly
    identical initial particles stay identical (start from a spread).
    """
    import optax

    lr = positive(learning_rate, "svgd: learning_rate")
    min_ls = positive(min_length_scale, "svgd: min_length_scale")
    if length_scale is not None:
        length_scale = positive(length_scale, "svgd: length_scale")
    if isinstance(warmup, bool) or not isinstance(warmup, (int, np.integer)) or warmup < 0:
        raise ConfigError(f"svgd: warmup must be an integer >= 0, got {warmup!r}")
    if warmup and optimizer is not None:
        raise ConfigError("svgd: warmup ramps the default Adam; give it in your own optimizer")
    rate = optax.linear_schedule(lr / WARMUP_START_DIVISOR, lr, int(warmup)) if warmup else lr
    opt = optax.adam(rate) if optimizer is None else optimizer
    if not isinstance(opt, optax.GradientTransformation):
        raise ConfigError(
            f"svgd: optimizer must be an optax GradientTransformation, got {type(opt).__name__}"
        )
    settings = {
        "optimizer": "adam" if optimizer is None else "custom",
        "learning_rate": lr if optimizer is None else None,
        "length_scale": "median_heuristic" if length_scale is None else length_scale,
        "min_length_scale": min_ls,
        **({"warmup": int(warmup)} if warmup else {}),
    }

    def init(rng_key, positions) -> SVGDState:
        del rng_key
        positions = check_positions(positions)
        logdensity, grad = value_and_grad_fn(positions)
        return SVGDState(positions, logdensity, grad, opt.init(positions))

    def step(rng_key, state: SVGDState) -> tuple[SVGDState, SVGDInfo]:
        del rng_key  # deterministic
        x = state.position
        h = (
            median_length_scale(x, min_ls)
            if length_scale is None
            else jnp.asarray(length_scale, x.dtype)
        )
        phi = stein_direction(x, state.logdensity_grad, h)
        updates, opt_state = opt.update(-phi, state.opt_state, x)  # optax descends: ascend phi
        x_new = optax.apply_updates(x, updates)
        logdensity, grad = value_and_grad_fn(x_new)
        info = SVGDInfo(
            bandwidth=h,
            mean_logdensity=finite_mean(logdensity),
            grad_norm=jnp.mean(jnp.linalg.norm(grad, axis=-1)),
            n_nonfinite=count_nonfinite(logdensity),
            ksd=kernel_stein_discrepancy(
                x_new, jnp.where(jnp.isfinite(logdensity)[:, None], grad, jnp.nan)
            ),
        )
        return SVGDState(x_new, logdensity, grad, opt_state), info

    return SamplingAlgorithm(init, step, name, settings)


def nnsvgd(
    value_and_grad_fn: ValueAndGradFn,
    learning_rate: float = 1e-2,
    optimizer: optax.GradientTransformation | None = None,
    length_scale: float | None = None,
    min_length_scale: float = 1e-6,
    name: str = "nnsvgd",
    warmup: int = 0,
) -> SamplingAlgorithm:
    """NNSVGD (the paper's method): :func:`svgd` recorded under the name ``"nnsvgd"``.

    The algorithm is plain SVGD; what makes it NNSVGD is the target, which the
    caller composes to include the neural-network inequality prior, e.g.
    ``combined_value_and_grad(fd_terms=[likelihood],
    autodiff_terms=[box_prior, inequality_prior(net, pairs)])``. Arguments as for :func:`svgd`.
    """
    return svgd(
        value_and_grad_fn, learning_rate, optimizer, length_scale, min_length_scale, name, warmup
    )
