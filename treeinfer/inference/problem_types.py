"""The inference problem's types: :class:`Problem` (everything the samplers need about one
posterior target) and :class:`DataTarget` (that target with the observations as an argument).
Built by :func:`treeinfer.inference.problem.make_problem`."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, NamedTuple

import numpy as np

from ..data.trajectories import Observations
from ..sim import Simulator
from ..tree.description import Tree
from . import samplers as _samplers


class DataTarget(NamedTuple):
    """The problem's target with the observations as an argument (:func:`make_problem`'s
    ``shape_bucket``).

    built_for: the problem's ``value_and_grad`` it was built with; a problem whose target was
      replaced since (e.g. :func:`treeinfer.inference.sequential.with_prior`) no longer uses it.
    target: ``data -> (value_and_grad, log_density)``, the same functions as the problem's on
      ``data`` (traceable: ``data`` may be a jitted program's argument).
    data: the training observations padded to ``shape`` and masked, as a pytree of arrays
      (:meth:`treeinfer.model.likelihood.LikelihoodTerms.data_of`).
    shape: ``(B', T')`` the bucket.
    """

    built_for: Callable
    target: Callable
    data: Any
    shape: tuple[int, int]


@dataclass(frozen=True, eq=False)
class Problem:
    """Everything the samplers need about one inference problem.

    Attributes:
      tree, sim, obs: the tree, its compiled simulator, the stacked training trajectories.
      kT: Boltzmann temperature (the value given, or "auto"'s result; for the generative
        likelihoods only the Boltzmann training-fit report uses it).
      labels: ``Kp[j]``..., ``Kd[j]``..., then the noise columns (``sigma_x``...; see
        :func:`treeinfer.model.likelihood.noise_columns`) of theta.
      lower, upper: [D] the prior box in theta (log) units (initial box for noise columns).
      noise: the :class:`~treeinfer.model.likelihood.LikelihoodTerms` (likelihood kind, fixed or
        inferred noise, description) -- what predictions need for the predictive band.
      log_likelihood, log_prior: batched terms ``theta [N, D] -> [N]``.
      value_and_grad: ``theta [P, D] -> (log p [P], grad [P, D])`` of the whole target.
      log_density: ``theta [P, D] -> [P]``, the whole target (for MH and metrics).
      settings: what built it (recorded next to results).
      model: None (the dynamic rollout of theta = [log Kp, log Kd]) or the
        :class:`treeinfer.inference.static.Model` (static model, or stiffness only) theta is mapped
        by.
    """

    tree: Tree
    sim: Simulator
    obs: Observations
    kT: float
    labels: tuple[str, ...]
    lower: np.ndarray
    upper: np.ndarray
    log_likelihood: Callable
    log_prior: Callable
    value_and_grad: Callable
    log_density: Callable
    nn_prior: bool
    settings: dict = field(default_factory=dict)
    noise: Any = (
        None  # treeinfer.model.likelihood.LikelihoodTerms: the likelihood choice and its noise
    )
    model: Any = (
        None  # treeinfer.inference.static.Model when not the dynamic model of [log Kp, log Kd]
    )
    data_target: Any = None  # DataTarget: the samplers' programs take the data as an argument
    spec: Any = None  # the ProblemSpec it was built from (treeinfer.inference.spec)
    # [S, D] starting points for the start pipeline's MAP fit found while building the problem
    # (the force-noise reference's fit, treeinfer.inference.start_pipeline), None: it screens the
    # box
    start_hint: Any = None

    @property
    def dim(self) -> int:
        return len(self.labels)

    def data_sampler(self, name: str = "nnsvgd", **options):
        """:meth:`sampler` with the observations as its programs' argument: a
        :class:`treeinfer.inference.samplers.DataSamplingAlgorithm` on :attr:`data_target`, or None
        when the problem has none (or its target was replaced since it was built)."""
        dt = self.data_target
        if dt is None or dt.built_for is not self.value_and_grad:
            return None
        # the constructor's hyperparameters on the host, once: arrays made here (MH's proposal
        # scale) are concrete, so the settings record can read them inside a trace
        spec = _samplers.sampler_spec(name)
        hyper = spec.hyperparameters(
            _samplers.sampler_options(name, **options), self.upper - self.lower
        )

        def build(data):
            value_and_grad, log_density = dt.target(data)
            return _samplers.make_sampler(
                name, value_and_grad_fn=value_and_grad, logdensity_fn=log_density, **hyper
            )

        host = build(dt.data)  # name and settings (nothing is traced here)
        return _samplers.DataSamplingAlgorithm(build, dt.data, host.name, host.settings)

    def sampler(self, name: str = "nnsvgd", **options) -> _samplers.SamplingAlgorithm:
        """The sampler ``name`` (see :data:`treeinfer.inference.samplers.REGISTRY`) wired to this
        target, with the registry's default options updated by ``options``."""
        return _samplers.build_sampler(
            name,
            value_and_grad_fn=self.value_and_grad,
            logdensity_fn=self.log_density,
            box_width=self.upper - self.lower,
            **options,
        )
