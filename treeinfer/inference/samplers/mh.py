"""Random-walk Metropolis-Hastings, many independent chains (one per particle).

Gaussian random-walk proposals ``x' = x + L z`` (BlackJAX's
``random_walk.normal``) and BlackJAX's Rosenbluth-Metropolis-Hastings kernel
(``random_walk.build_rmh``) for the accept/reject step, ``vmap``-ed over chains.

Adapter: BlackJAX's kernel evaluates ``logdensity_fn`` on one chain's
proposal; our log-density is batched (the simulator evaluates all chains in one
call). So we draw all proposals first, evaluate them in **one** batched call,
and hand each chain's precomputed proposal and log-density to the vmapped
BlackJAX kernel through constant ``transition_generator`` / ``logdensity_fn``
closures. The chains' states are BlackJAX's ``RWState(position, logdensity)``
with a leading particle axis.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ...errors import ConfigError
from .base import (
    SamplingAlgorithm,
    as_settings_value,
    check_positions,
    count_nonfinite,
    finite_mean,
)

if TYPE_CHECKING:  # blackjax (0.3 s) is imported where it is used
    from blackjax.mcmc.random_walk import RWState

__all__ = ["MHInfo", "RWState", "mh"]


class MHInfo(NamedTuple):
    """acceptance_rate [P]: acceptance probability of this step's proposal per chain;
    is_accepted [P]; mean_acceptance_rate, mean_logdensity (finite chains), n_nonfinite: scalars."""

    acceptance_rate: jax.Array
    is_accepted: jax.Array
    mean_acceptance_rate: jax.Array
    mean_logdensity: jax.Array
    n_nonfinite: jax.Array


def _sanitize(logdensity: jax.Array) -> jax.Array:
    """NaN/+inf log-densities (failed evaluations) become -inf: always rejected."""
    return jnp.where(jnp.isfinite(logdensity), logdensity, -jnp.inf)


def mh(
    logdensity_fn: Callable[[jax.Array], jax.Array], proposal_scale, name: str = "mh"
) -> SamplingAlgorithm:
    """Random-walk MH on a batched ``logdensity_fn(theta [P, D]) -> [P]``.

    Args:
      proposal_scale: proposal standard deviation per coordinate ``[D]`` (or a
        float for all), theta units; or a ``[D, D]`` matrix ``L`` (proposal
        covariance ``L L^T``). ~``2.4 / sqrt(D)`` times the posterior standard
        deviation gives the classic ~25-45% acceptance.
    """
    from blackjax.mcmc import random_walk
    from blackjax.mcmc.random_walk import RWState

    scale = np.asarray(proposal_scale, dtype=np.float64)
    if scale.ndim > 2 or not np.all(np.isfinite(scale)):
        raise ConfigError(
            f"mh: proposal_scale must be a finite float, [D] vector or [D, D] matrix, got {scale!r}"
        )
    if scale.ndim < 2 and not np.all(scale > 0):
        raise ConfigError(f"mh: proposal_scale must be > 0, got {scale.tolist()}")
    kernel = random_walk.build_rmh()
    settings = {"proposal_scale": as_settings_value(scale)}

    def _check_dim(dim: int):
        if scale.ndim >= 1 and scale.shape[0] != dim:
            raise ConfigError(
                f"mh: proposal_scale has {scale.shape[0]} coordinates, theta has {dim}"
            )

    def init(rng_key, positions) -> RWState:
        del rng_key
        positions = check_positions(positions)
        _check_dim(positions.shape[1])
        return RWState(positions, _sanitize(logdensity_fn(positions)))

    def step(rng_key, state: RWState) -> tuple[RWState, MHInfo]:
        x = state.position
        n_chains, dim = x.shape
        _check_dim(dim)
        sigma = (
            jnp.broadcast_to(jnp.asarray(scale, x.dtype), (dim,))
            if scale.ndim < 2
            else jnp.asarray(scale, x.dtype)
        )
        propose = random_walk.normal(sigma)
        key_move, key_accept = jax.random.split(rng_key)
        x_prop = x + jax.vmap(propose)(jax.random.split(key_move, n_chains), x)
        ld_prop = _sanitize(logdensity_fn(x_prop))  # one batched evaluation

        def one_chain(key, chain_state, x_new, ld_new):
            return kernel(key, chain_state, lambda _x: ld_new, lambda _k, _x: x_new)

        new_state, rw_info = jax.vmap(one_chain)(
            jax.random.split(key_accept, n_chains), state, x_prop, ld_prop
        )
        info = MHInfo(
            acceptance_rate=rw_info.acceptance_rate,
            is_accepted=rw_info.is_accepted,
            mean_acceptance_rate=jnp.mean(rw_info.acceptance_rate),
            mean_logdensity=finite_mean(new_state.logdensity),
            n_nonfinite=count_nonfinite(new_state.logdensity),
        )
        return RWState(new_state.position, new_state.logdensity), info

    return SamplingAlgorithm(init, step, name, settings)


def __getattr__(name):
    # BlackJAX's chain state, re-exported without importing blackjax (0.3 s) with this module
    if name == "RWState":
        from blackjax.mcmc.random_walk import RWState

        return RWState
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
