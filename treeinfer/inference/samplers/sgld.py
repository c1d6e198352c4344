"""Stochastic gradient Langevin dynamics, one chain per particle.

    x_{t+1} = x_t + eps_t grad log p(x_t) + sqrt(2 T eps_t) xi,   xi ~ N(0, I)

(BlackJAX's ``overdamped_langevin`` integrator, used as is). With a
finite-difference gradient the "stochastic gradient" is a deterministic
approximation; for a small step the chains sample ``p^(1/T)`` up to an
``O(eps)`` discretisation bias (no Metropolis correction).

Why not ``blackjax.sgld`` itself: its step is ``(key, position, minibatch,
step_size)`` and returns a bare position; we need the uniform
``(key, state) -> (state, info)``, a step counter for the schedule, and the
log-density of the current particles, so the state carries the value and
gradient from the previous batched evaluation (one evaluation per step).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, NamedTuple

import jax
import jax.numpy as jnp

from ...errors import ConfigError
from ...model.gradients import ValueAndGradFn
from .base import (
    SamplingAlgorithm,
    as_schedule,
    check_positions,
    count_nonfinite,
    finite_mean,
    positive,
    preconditioned_drift,
)

if TYPE_CHECKING:  # annotations only: optax is imported where it is used
    import optax

__all__ = ["SGLDInfo", "SGLDState", "sgld"]


class SGLDState(NamedTuple):
    """position [P, D]; logdensity [P], logdensity_grad [P, D] at position;
    step: iterations done (int32, drives the step-size schedule);
    opt_state: optional optimiser state (``()`` when unused)."""

    position: jax.Array
    logdensity: jax.Array
    logdensity_grad: jax.Array
    step: jax.Array
    opt_state: Any


class SGLDInfo(NamedTuple):
    """step_size used; mean finite log p, mean ||grad||, non-finite count of the new particles."""

    step_size: jax.Array
    mean_logdensity: jax.Array
    grad_norm: jax.Array
    n_nonfinite: jax.Array


def sgld(
    value_and_grad_fn: ValueAndGradFn,
    step_size=1e-3,
    temperature: float = 1.0,
    optimizer: optax.GradientTransformation | None = None,
    name: str = "sgld",
) -> SamplingAlgorithm:
    """SGLD with ``P`` independent chains.

    Args:
      value_and_grad_fn: batched ``theta [P, D] -> (log p [P], grad [P, D])``.
      step_size: ``eps`` (theta units^2 per unit log-density gradient), a
        float or a schedule ``step_count -> eps`` (e.g. an optax schedule or
        Welling & Teh's ``a * (b + t) ** -gamma``).
      temperature: ``T``; 1 samples the target, 0 is gradient ascent.
      optimizer: None (default) for true SGLD. An optax optimiser (e.g.
        ``optax.adam(1e-3)``) replaces the drift ``eps * grad`` by the
        optimiser's update while keeping the noise ``sqrt(2 T eps)``: the
        "Adam with a small learning rate guides the descent" variant of the
        paper's baselines. It is a heuristic, not an asymptotically exact sampler.
    """
    schedule, step_record = as_schedule(step_size, "sgld: step_size")
    temperature = positive(temperature, "sgld: temperature", allow_zero=True)
    import optax
    from blackjax.sgmcmc import diffusions

    if optimizer is not None and not isinstance(optimizer, optax.GradientTransformation):
        raise ConfigError(
            f"sgld: optimizer must be an optax GradientTransformation, "
            f"got {type(optimizer).__name__}"
        )
    integrator = diffusions.overdamped_langevin()
    settings = {
        "step_size": step_record,
        "temperature": temperature,
        "optimizer": None if optimizer is None else "custom",
    }

    def init(rng_key, positions) -> SGLDState:
        del rng_key
        positions = check_positions(positions)
        logdensity, grad = value_and_grad_fn(positions)
        opt_state = () if optimizer is None else optimizer.init(positions)
        return SGLDState(positions, logdensity, grad, jnp.zeros((), jnp.int32), opt_state)

    def step(rng_key, state: SGLDState) -> tuple[SGLDState, SGLDInfo]:
        eps = jnp.asarray(schedule(state.step), state.position.dtype)
        drift, opt_state = preconditioned_drift(
            optimizer, state.logdensity_grad, state.opt_state, state.position, eps
        )
        x_new = integrator(rng_key, state.position, drift, eps, temperature)
        logdensity, grad = value_and_grad_fn(x_new)
        info = SGLDInfo(
            step_size=eps,
            mean_logdensity=finite_mean(logdensity),
            grad_norm=jnp.mean(jnp.linalg.norm(grad, axis=-1)),
            n_nonfinite=count_nonfinite(logdensity),
        )
        return SGLDState(x_new, logdensity, grad, state.step + 1, opt_state), info

    return SamplingAlgorithm(init, step, name, settings)
