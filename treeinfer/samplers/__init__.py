"""Samplers with one BlackJAX-style interface, and the driver that runs them.

Every sampler is a :class:`SamplingAlgorithm` ``(init, step, name, settings)``:
``init(rng_key, positions [P, D]) -> state`` and
``step(rng_key, state) -> (state, info)``, pure and jittable, one batched
target evaluation per step. Gradient samplers take a batched
``value_and_grad_fn(theta [P, D]) -> (log p [P], grad [P, D])``; Metropolis-
Hastings takes a batched ``logdensity_fn(theta [P, D]) -> [P]``.

:func:`run` drives any of them in jitted ``lax.scan`` chunks with progress,
tracing, checkpoint callbacks and exact resume; :func:`make_sampler` builds one by name.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable

from ..errors import ConfigError
from ..gradients import LogDensityFn, ValueAndGradFn
from .base import SamplingAlgorithm
from .driver import RunResult, init_key, iteration_key, run
from .mh import MHInfo, RWState, mh
from .sghmc import SGHMCInfo, SGHMCState, sghmc
from .sgld import SGLDInfo, SGLDState, sgld
from .svgd import SVGDInfo, SVGDState, median_length_scale, nnsvgd, stein_direction, svgd

__all__ = [
    "SAMPLERS",
    "MHInfo",
    "RWState",
    "RunResult",
    "SGHMCInfo",
    "SGHMCState",
    "SGLDInfo",
    "SGLDState",
    "SVGDInfo",
    "SVGDState",
    "SamplingAlgorithm",
    "init_key",
    "iteration_key",
    "make_sampler",
    "median_length_scale",
    "mh",
    "nnsvgd",
    "run",
    "sghmc",
    "sgld",
    "stein_direction",
    "svgd",
]

SAMPLERS: dict[str, Callable[..., SamplingAlgorithm]] = {
    "svgd": svgd,
    "nnsvgd": nnsvgd,
    "sgld": sgld,
    "sghmc": sghmc,
    "mh": mh,
}
"""Sampler constructors by name. ``mh`` takes a log-density, the others a value-and-grad function."""


def make_sampler(
    name: str,
    *,
    value_and_grad_fn: ValueAndGradFn | None = None,
    logdensity_fn: LogDensityFn | None = None,
    **hyperparameters,
) -> SamplingAlgorithm:
    """Build the sampler ``name`` (one of :data:`SAMPLERS`).

    Gradient samplers (``svgd``, ``nnsvgd``, ``sgld``, ``sghmc``) need
    ``value_and_grad_fn``; ``mh`` needs ``logdensity_fn``. ``hyperparameters``
    go to the constructor (e.g. ``learning_rate=...`` for SVGD,
    ``step_size=...`` for SGLD/SGHMC, ``proposal_scale=...`` for MH).
    """
    key = str(name).lower()
    if key not in SAMPLERS:
        raise ConfigError(f"unknown sampler {name!r}; choose one of {', '.join(SAMPLERS)}")
    ctor = SAMPLERS[key]
    try:  # unknown / missing hyperparameters are the user's mistake, not a bug
        inspect.signature(ctor).bind(None, **hyperparameters)
    except TypeError as exc:
        raise ConfigError(f"sampler {key!r}: {exc}") from None
    if key == "mh":
        if logdensity_fn is None:
            raise ConfigError("sampler 'mh' needs logdensity_fn (a batched log-density)")
        return ctor(logdensity_fn, **hyperparameters)
    if value_and_grad_fn is None:
        raise ConfigError(f"sampler {key!r} needs value_and_grad_fn (batched value and gradient)")
    return ctor(value_and_grad_fn, **hyperparameters)
