"""The typed problem specification: how to build a posterior target, validated once.

:func:`treeinfer.inference.problem.make_problem` takes a tree, the training data and one
:class:`ProblemSpec` (or its fields as keywords, which build one). Every option is checked when
the spec is made, so a typo or an impossible value is a :class:`~treeinfer.errors.ConfigError`
naming the field before anything is compiled, and a spec can be kept, compared, changed
(``spec.replace(noise_force=None)``) and recorded (``spec.as_dict()``).

    spec = ProblemSpec(likelihood="gaussian", noise_force="auto", backend="fused")
    problem = make_problem(tree, trajectories, spec)
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import ConfigError
from ..model.boltzmann import DEFAULT_KT
from ..model.prior_terms import DEFAULT_ETA, DEFAULT_PRIOR_SIGMA
from ..model.temperature import check_kT
from ..sim import BACKENDS, FORCE_INTERPS

GRADIENTS = ("fd", "jvp", "autodiff")  # how make_problem differentiates the simulator likelihood
LIKELIHOODS = ("gaussian", "student_t", "ar1", "boltzmann")
PRIOR_SPACES = ("log", "linear")
MODEL_KINDS = ("dynamic", "static")
DEFAULT_LIKELIHOOD = "gaussian"
# a force-noise estimate below this share of the largest recorded force is float rounding
CLEAN_FORCE = 1e-9


def _positive(name: str, value, allow_none: bool = True):
    if value is None and allow_none:
        return
    if isinstance(value, bool) or not isinstance(value, (int, float, np.number)):
        raise ConfigError(f"{name}: must be a positive number, got {value!r}")
    if not (np.isfinite(value) and value > 0):
        raise ConfigError(f"{name}: must be a positive finite number, got {value!r}")


def _one_of(name: str, value, allowed) -> None:
    if value not in allowed:
        raise ConfigError(f"{name}: expected one of {', '.join(allowed)}, got {value!r}")


@dataclass(frozen=True)
class ProblemSpec:
    """Every option of :func:`~treeinfer.inference.problem.make_problem`, checked once.

    Likelihood and noise:
      likelihood: ``"gaussian"`` (None, the default: recorded = simulated + white noise,
        sigma_x inferred jointly), ``"student_t"`` or ``"ar1"`` (generative noise models,
        :mod:`treeinfer.model.noise`), or ``"boltzmann"`` (the paper's loss with temperature
        ``kT``). A ``kT`` other than the default without ``likelihood`` is refused (before issue
        27 it meant the Boltzmann loss).
      kT: Boltzmann temperature, a number or ``"auto"`` (from the data's noise estimate).
      noise_displacement: m, fixed displacement noise sigma_x for the generative likelihoods
        (None: inferred as an extra column of theta), or the noise ``kT="auto"`` uses.
      noise_force: ``"default"`` (``"auto"`` where the likelihood and model offer the term and
        the data let it be estimated, else off: :func:`default_noise_force`), None (off), or the
        recorded force's noise std (N, ``"P%"`` of the largest recorded force, or ``"auto"``).
        With the paper's dynamic model: the errors-in-variables term of
        :mod:`treeinfer.model.force_noise`; with ``model_kind="static"``: the load cell's noise
        read through each pull's compliance.
      noise_velocity: None (the velocity term off) or m/s, the velocity residual's noise std.
      force_noise_reference: ``[2R]`` log gains where the force-noise Jacobian is taken (None:
        :func:`treeinfer.model.force_noise_reference.reference_theta`'s MAP fit);
        force_noise_rule: how it was chosen (recorded).
      integration_error: None, or the simulator's discretisation error measured at the MAP
        (:class:`treeinfer.model.integration_error.IntegrationError`; the run layer measures it,
        :mod:`treeinfer.inference.integration_floor`): a floor under the displacement noise.

    Priors:
      nn_prior: add the learned inequality prior (NNSVGD's target); False gives SVGD's.
      eta: inequality penalty slope (nats per unit of log-gain the child exceeds its parent).
      prior_sigma: the smoothed box's edge width; prior_space: ``"log"`` (box on log K) or
        ``"linear"`` (box on K, with the log-Jacobian). nn_seed: the network's seed.

    Gradients:
      gradient: ``"fd"`` (central differences, the paper's black-box route), ``"jvp"`` (exact
        forward-mode sensitivities) or ``"autodiff"`` (reverse mode; for checks).
      rel_step: finite-difference step in log units (default ~5e-3 for float32).

    Simulator (when no simulator is passed to make_problem):
      backend, force_interp, substeps, max_sim_dt, sim_tolerance (m; the step is
      accuracy-controlled on the training forces), model_file (a user's URDF/MJCF).
      grasp_fraction: where the training data were recorded (None: the tree's grasp).

    Model and pulls:
      model_kind: ``"dynamic"`` (the rollout) or ``"static"`` (equilibrium, stiffness only).
      direction, grasp_branch: each training pull's direction ([3] or [B, 3]) and grasped
        branch (None or B names). model: a prebuilt :class:`treeinfer.inference.static.Model`
        (overrides model_kind, direction and grasp_branch).

    Observations besides the grasp point:
      channels: :class:`treeinfer.data.channels.Channel` s (markers, inclinometers at named
        points; :func:`treeinfer.data.channels.read_channels`), each adding its own Gaussian term
        to a generative likelihood (:mod:`treeinfer.model.channels`). () (default): none.

    Programs:
      shape_bucket: None (data embedded in the samplers' programs), or ``(B', T')`` at least the
        data's ``[B, T]``: the programs take the data as an argument, padded and masked, so
        another data set of that bucket reuses them.
    """

    likelihood: str | None = None
    kT: float | str = DEFAULT_KT
    noise_displacement: float | None = None
    noise_force: Any = "default"
    noise_velocity: float | None = None
    force_noise_reference: Any = None
    force_noise_rule: str = "J at the given reference"
    integration_error: Any = None
    nn_prior: bool = True
    eta: float = DEFAULT_ETA
    prior_sigma: float = DEFAULT_PRIOR_SIGMA
    prior_space: str = "log"
    nn_seed: int = 0
    gradient: str = "fd"
    rel_step: float | None = None
    backend: str = "auto"
    force_interp: str = "linear"
    substeps: int | None = None
    max_sim_dt: float | None = None
    sim_tolerance: float | None = None
    model_file: Any = None
    grasp_fraction: float | None = None
    model_kind: str = "dynamic"
    direction: Any = None
    grasp_branch: Any = None
    model: Any = None
    shape_bucket: Any = None
    channels: tuple = ()

    def __post_init__(self):
        if self.likelihood is not None:
            _one_of("likelihood", self.likelihood, LIKELIHOODS)
        if not (isinstance(self.kT, str) and self.kT == "auto"):
            object.__setattr__(self, "kT", check_kT(self.kT))
        resolve_likelihood(self.likelihood, self.kT)  # a kT without a likelihood is refused
        _one_of("gradient", self.gradient, GRADIENTS)
        _one_of("prior_space", self.prior_space, PRIOR_SPACES)
        _one_of("model_kind", self.model_kind, MODEL_KINDS)
        _one_of("backend", self.backend, BACKENDS)
        _one_of("force_interp", self.force_interp, FORCE_INTERPS)
        if not (isinstance(self.prior_sigma, (int, float)) and self.prior_sigma > 0):
            raise ConfigError(f"prior_sigma: must be positive, got {self.prior_sigma!r}")
        for name in ("rel_step", "max_sim_dt", "sim_tolerance", "noise_displacement"):
            _positive(name, getattr(self, name))
        _positive("noise_velocity", self.noise_velocity)
        if not isinstance(self.eta, (int, float)) or isinstance(self.eta, bool) or self.eta < 0:
            raise ConfigError(f"eta: must be a non-negative number, got {self.eta!r}")
        if self.substeps is not None and (
            isinstance(self.substeps, bool) or not isinstance(self.substeps, (int, np.integer))
            or self.substeps < 1
        ):  # fmt: skip
            raise ConfigError(f"substeps: must be an integer >= 1, got {self.substeps!r}")
        if self.shape_bucket is not None:
            b = tuple(self.shape_bucket)
            if len(b) != 2 or not all(isinstance(n, (int, np.integer)) and n > 0 for n in b):
                raise ConfigError(f"shape_bucket: expected (B, T) positive integers, got {b!r}")
        if self.channels:
            from ..data.channels import Channel

            object.__setattr__(self, "channels", tuple(self.channels))
            if not all(isinstance(c, Channel) for c in self.channels):
                raise ConfigError("channels: expected treeinfer.data.channels.Channel items")
            if self.resolved_likelihood == "boltzmann":
                raise ConfigError(
                    "channels: observation channels need a generative likelihood (gaussian, "
                    "student_t, ar1), not the Boltzmann loss"
                )
        if self.noise_velocity is not None and self.resolved_likelihood == "boltzmann":
            raise ConfigError(
                "--noise-velocity: the velocity term belongs to a generative likelihood "
                "(gaussian, student_t, ar1); the Boltzmann loss has its own velocity term"
            )

    @property
    def resolved_likelihood(self) -> str:
        return resolve_likelihood(self.likelihood, self.kT)

    def replace(self, **changes) -> ProblemSpec:
        """A copy with ``changes`` (validated again)."""
        return dataclasses.replace(self, **changes)

    @classmethod
    def from_options(cls, spec: ProblemSpec | None = None, **options) -> ProblemSpec:
        """``spec`` updated by ``options`` (or a new spec from them); an unknown option is a
        ConfigError naming it and the known ones."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(options) - names)
        if unknown:
            raise ConfigError(
                f"make_problem: unknown option(s) {', '.join(unknown)}; known: "
                f"{', '.join(sorted(names))}"
            )
        if spec is None:
            return cls(**options)
        return spec.replace(**options) if options else spec


def resolve_likelihood(likelihood: str | None, kT=DEFAULT_KT) -> str:
    """``likelihood`` or, for None, the default (:data:`DEFAULT_LIKELIHOOD`). A ``kT`` other than
    the default meant the Boltzmann loss while that was the default (before issue 27); given
    without a likelihood it is refused with what to pass, rather than silently ignored."""
    if likelihood is not None:
        return likelihood
    if not (isinstance(kT, (int, float)) and not isinstance(kT, bool) and kT == DEFAULT_KT):
        raise ConfigError(
            f"kT={kT!r} sets the temperature of the Boltzmann loss, which is no longer the "
            f"default likelihood (now {DEFAULT_LIKELIHOOD!r}: recorded = simulated + noise, the "
            "noise inferred); pass likelihood='boltzmann' with kT to keep the paper's loss, or "
            "leave kT out"
        )
    return DEFAULT_LIKELIHOOD


def default_noise_force(noise_force, likelihood: str, supported: bool, obs):
    """``(noise_force, note)``: ``"default"`` resolved to ``"auto"`` (the recorded force's noise
    estimated from the data, an errors-in-variables term) where the likelihood is Gaussian, the
    model offers the term (``supported``: the paper's dynamic model or the static one) and the
    force noise can be estimated; otherwise None (off) and ``note`` says why (recorded as the
    problem setting ``noise_force_default``). Any other value is returned as given."""
    if not (isinstance(noise_force, str) and noise_force == "default"):
        return noise_force, None
    if likelihood != "gaussian":
        return None, None
    if not supported:
        return None, "off: this model (stiffness only, a tie or per-recording pulls) has no term"
    from ..model.force_noise import estimate_force_noise

    try:
        est = estimate_force_noise(obs)
    except ConfigError as e:
        return None, f"off: {str(e).removeprefix('noise_force: ')}"
    f = np.abs(np.asarray(obs.force, float)[np.asarray(obs.mask, bool)])
    if f.size and est.sigma < CLEAN_FORCE * float(f.max()):
        # rounding in the second differences of a noise-free force (7.6e-17 N on a simulated
        # ramp): a term of no size that would still cost its Jacobian
        return None, f"off: the recorded force looks noise-free (estimate {est.sigma:.3g} N)"
    return "auto", None
