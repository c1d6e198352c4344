"""The uniform sampler interface shared by every treeinfer sampler.

Every sampler is a :class:`SamplingAlgorithm` of two pure, jittable functions
(nothing is jitted inside the library; the caller or :func:`treeinfer.inference.samplers.run` jits):

* ``init(rng_key, positions [P, D]) -> state`` -- evaluates the target once at
  the initial particles (one batched call);
* ``step(rng_key, state) -> (state, info)`` -- one iteration for all ``P``
  particles/chains, with exactly one batched target evaluation.

States and infos are NamedTuples. Every state has ``position [P, D]`` and
``logdensity [P]`` (of that position; ``-inf`` for a failed particle); every
info has the scalars ``mean_logdensity`` (over finite particles) and
``n_nonfinite``. This is BlackJAX's ``SamplingAlgorithm(init, step)`` with the
argument order of ``init`` made uniform (key first, as in ``step``) plus a
``name`` and JSON-able ``settings`` for reproducibility records.
"""

from __future__ import annotations

import math
import types
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ...errors import ConfigError

__all__ = [
    "DataSamplingAlgorithm",
    "SamplingAlgorithm",
    "as_schedule",
    "check_positions",
    "count_nonfinite",
    "finite_mean",
]


class SamplingAlgorithm(NamedTuple):
    """``init(rng_key, positions [P, D]) -> State``; ``step(rng_key, State) -> (State, Info)``.

    name: sampler name (``"svgd"``, ``"nnsvgd"``, ``"sgld"``, ``"sghmc"``, ``"mh"``).
    settings: hyperparameters as plain JSON-able values (recorded by ``run``).
    """

    init: Callable[[jax.Array, jax.Array], Any]
    step: Callable[[jax.Array, Any], tuple[Any, Any]]
    name: str = ""
    settings: Mapping[str, Any] = types.MappingProxyType({})


class DataSamplingAlgorithm(NamedTuple):
    """A sampler whose target takes the observations as an argument, so that the programs
    :func:`treeinfer.inference.samplers.run` compiles take them as one too: another data set of the
    same shapes (one shape bucket, :mod:`treeinfer.sim.startup`) reuses the compiled program, in the
    process (a :class:`~treeinfer.sim.program_cache.ProgramCache`) and across processes (the
    persistent compile cache), where a :class:`SamplingAlgorithm` closing over the data embeds
    them in the program as constants.

    build: ``data -> SamplingAlgorithm``, pure and traceable (``data`` may be a tracer); every
      call builds the same sampler on other data.
    data: the pytree of arrays to run on (e.g. the padded observations,
      :meth:`treeinfer.inference.problem.Problem.data_sampler`).
    name, settings: as :class:`SamplingAlgorithm`'s (the sampler ``build`` makes).
    """

    build: Callable[[Any], SamplingAlgorithm]
    data: Any
    name: str = ""
    settings: Mapping[str, Any] = types.MappingProxyType({})


def as_schedule(value, what: str) -> tuple[Callable[[jax.Array], jax.Array], Any]:
    """A positive float or a schedule ``step_count -> float`` (e.g. an optax schedule).

    Returns ``(schedule, record)`` where ``record`` is the float, or the
    schedule's repr (a callable cannot be recorded exactly).
    """
    if callable(value):
        return value, repr(value)
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(
            f"{what} must be a positive number or a schedule, got {value!r}"
        ) from None
    if not (math.isfinite(v) and v > 0):
        raise ConfigError(f"{what} must be a positive number, got {value!r}")
    return (lambda count: jnp.asarray(v)), v


def positive(value, what: str, allow_zero: bool = False) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{what} must be a number, got {value!r}") from None
    if not math.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        raise ConfigError(f"{what} must be {'>= 0' if allow_zero else '> 0'}, got {value!r}")
    return v


def finite_mean(x: jax.Array) -> jax.Array:
    """Mean over the finite entries of ``x`` (NaN when there are none)."""
    ok = jnp.isfinite(x)
    return jnp.sum(jnp.where(ok, x, 0.0)) / jnp.sum(ok)


def count_nonfinite(x: jax.Array) -> jax.Array:
    return jnp.sum(~jnp.isfinite(x)).astype(jnp.int32)


def check_positions(positions, what: str = "initial positions") -> jax.Array:
    """``positions`` as a floating ``[P, D]`` array (ConfigError otherwise)."""
    positions = jnp.asarray(positions)
    if positions.ndim != 2 or positions.shape[0] < 1 or positions.shape[1] < 1:
        raise ConfigError(f"{what} must have shape [P, D] with P, D >= 1, got {positions.shape}")
    if not jnp.issubdtype(positions.dtype, jnp.floating):
        positions = positions.astype(jnp.float32)
    return positions


def as_settings_value(x):
    """Plain-Python version of a hyperparameter for the settings record."""
    if isinstance(x, (np.ndarray, jax.Array)) or hasattr(x, "tolist"):
        return np.asarray(x).tolist()
    return x


def preconditioned_drift(optimizer, grad, opt_state, position, step_size):
    """Gradient to hand a BlackJAX diffusion so that ``step_size * drift`` is the
    optimiser's update of the ascent direction (``optimizer=None``: the gradient itself).

    Returns ``(drift [P, D], new_opt_state)``.
    """
    if optimizer is None:
        return grad, opt_state
    updates, opt_state = optimizer.update(-grad, opt_state, position)  # optax minimises
    return updates / step_size, opt_state
