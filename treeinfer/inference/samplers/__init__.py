"""Samplers with one BlackJAX-style interface, and the driver that runs them.

Every sampler is a :class:`SamplingAlgorithm` ``(init, step, name, settings)``:
``init(rng_key, positions [P, D]) -> state`` and
``step(rng_key, state) -> (state, info)``, pure and jittable, one batched
target evaluation per step. Gradient samplers take a batched
``value_and_grad_fn(theta [P, D]) -> (log p [P], grad [P, D])``; Metropolis-
Hastings takes a batched ``logdensity_fn(theta [P, D]) -> [P]``.

:func:`run` drives any of them in jitted ``lax.scan`` chunks with progress,
tracing, checkpoint callbacks and exact resume; :data:`REGISTRY` lists every sampler
(constructor, default options, target kind, whether it needs the NN prior);
:func:`build_sampler` builds one by name with treeinfer's options and :func:`make_sampler` with
raw constructor hyperparameters.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from typing import NamedTuple

from ...errors import ConfigError
from ...model.gradients import LogDensityFn, ValueAndGradFn
from .base import DataSamplingAlgorithm, SamplingAlgorithm
from .driver import RunResult, init_key, iteration_key, run
from .mh import MHInfo, mh
from .sghmc import SGHMCInfo, SGHMCState, sghmc
from .sgld import SGLDInfo, SGLDState, sgld
from .svgd import SVGDInfo, SVGDState, median_length_scale, nnsvgd, stein_direction, svgd

__all__ = [
    "LOG_DENSITY",
    "REGISTRY",
    "SAMPLERS",
    "SAMPLER_NAMES",
    "VALUE_AND_GRAD",
    "SamplerSpec",
    "DataSamplingAlgorithm",
    "build_sampler",
    "sampler_options",
    "sampler_spec",
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


def __getattr__(name):
    # BlackJAX's RWState (mh's chain state), imported with blackjax on first use
    if name == "RWState":
        from .mh import RWState

        return RWState
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


VALUE_AND_GRAD = "value_and_grad"
LOG_DENSITY = "log_density"


def _svgd_options(opts: dict, box_width) -> dict:
    # warmup (learning-rate ramp, e.g. for --init laplace) only when asked: not a default, so
    # runs without it record the same options as before
    warm = {"warmup": opts["warmup"]} if opts.get("warmup") else {}
    return {"learning_rate": opts["learning_rate"], **warm}


def _langevin_options(opts: dict, box_width) -> dict:
    import optax

    return {"step_size": opts["step_size"], "optimizer": optax.adam(opts["learning_rate"])}


def _sghmc_options(opts: dict, box_width) -> dict:
    # true SGHMC by default (no optimiser); learning_rate=... restores the paper's Adam drift
    if opts.get("learning_rate") is None:
        return {"step_size": opts["step_size"], "alpha": opts["alpha"]}
    return {**_langevin_options(opts, box_width), "alpha": opts["alpha"]}


def _mh_options(opts: dict, box_width) -> dict:
    import jax.numpy as jnp

    # proposal_scale is a share of each (log) prior box width [D]; a [D, D] matrix is the
    # proposal's Cholesky factor in theta units (e.g. treeinfer.inference.laplace.mh_proposal), as
    # it is
    scale = jnp.asarray(opts["proposal_scale"])
    if scale.ndim == 2:
        return {"proposal_scale": scale}
    return {"proposal_scale": jnp.asarray(scale * box_width)}


class SamplerSpec(NamedTuple):
    """One entry of :data:`REGISTRY`.

    Attributes:
      constructor: ``ctor(target_fn, **hyperparameters) -> SamplingAlgorithm``.
      defaults: treeinfer's options, tuned for theta in log units (a prior box a few units wide).
      target: :data:`VALUE_AND_GRAD` (batched value and gradient) or :data:`LOG_DENSITY`.
      nn_prior: whether its target includes the learned parent-stiffer-than-child prior.
      hyperparameters: ``(options, box_width [D]) -> constructor keywords``.
      family: ``"svgd"`` (interacting particles) or ``"mcmc"`` (one chain per particle).
    """

    constructor: Callable[..., SamplingAlgorithm]
    defaults: dict
    target: str
    nn_prior: bool
    hyperparameters: Callable[[dict, object], dict]
    family: str


REGISTRY: dict[str, SamplerSpec] = {
    "nnsvgd": SamplerSpec(
        nnsvgd, {"learning_rate": 0.1}, VALUE_AND_GRAD, True, _svgd_options, "svgd"
    ),
    "svgd": SamplerSpec(svgd, {"learning_rate": 0.1}, VALUE_AND_GRAD, False, _svgd_options, "svgd"),
    # The paper's gradient baselines: "an Adam optimizer with a small learning rate guides the
    # descent"; the Langevin noise is kept.
    "sgld": SamplerSpec(
        sgld,
        {"step_size": 1e-4, "learning_rate": 0.05},
        VALUE_AND_GRAD,
        False,
        _langevin_options,
        "mcmc",
    ),
    # SGHMC: step 1e-2 with heavy friction (alpha * eps = 0.1), no Adam. Measured by
    # experiments/sghmc_defaults.py (8 chains x 200 iterations from the uniform start): chains
    # travel 0.21 / 0.70 box widths on two_branch / three_branch (the former defaults, step 1e-4
    # with Adam 0.05 and alpha 0.1: 0.019 / 0.019) and reach log p -23 / -61 (former -166 / -242).
    "sghmc": SamplerSpec(
        sghmc,
        {"step_size": 1e-2, "alpha": 10.0, "learning_rate": None},
        VALUE_AND_GRAD,
        False,
        _sghmc_options,
        "mcmc",
    ),
    "mh": SamplerSpec(mh, {"proposal_scale": 0.05}, LOG_DENSITY, False, _mh_options, "mcmc"),
}
"""THE sampler registry: every sampler treeinfer offers, by name (CLI order)."""

SAMPLER_NAMES: tuple[str, ...] = tuple(REGISTRY)

SAMPLERS: dict[str, Callable[..., SamplingAlgorithm]] = {
    n: s.constructor for n, s in REGISTRY.items()
}
"""Sampler constructors by name. ``mh`` takes a log-density, the others a value-and-grad
function."""


def sampler_spec(name: str) -> SamplerSpec:
    """The registry entry of ``name`` (case-insensitive); ConfigError naming the choices."""
    key = str(name).lower()
    if key not in REGISTRY:
        raise ConfigError(f"sampler: unknown '{name}'; choose one of {', '.join(REGISTRY)}")
    return REGISTRY[key]


def sampler_options(name: str, **overrides) -> dict:
    """The registry's default options of ``name`` updated with ``overrides``."""
    return {**sampler_spec(name).defaults, **overrides}


def build_sampler(
    name: str,
    *,
    value_and_grad_fn: ValueAndGradFn | None = None,
    logdensity_fn: LogDensityFn | None = None,
    box_width=None,
    **options,
) -> SamplingAlgorithm:
    """The sampler ``name`` with treeinfer's options (registry defaults updated by ``options``),
    wired to the target its registry entry asks for. ``box_width`` [D]: the prior box's width in
    theta units (MH's proposal scale is a share of it)."""
    spec = sampler_spec(name)
    hyper = spec.hyperparameters(sampler_options(name, **options), box_width)
    return make_sampler(
        name, value_and_grad_fn=value_and_grad_fn, logdensity_fn=logdensity_fn, **hyper
    )


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
