"""Study configuration: sizes, :class:`StudyConfig`, :func:`study_config` (split from
:mod:`experiments.common`, which re-exports every name)."""

from __future__ import annotations

import dataclasses
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:  # run as `python experiments/<study>.py` from anywhere
    sys.path.insert(0, str(ROOT))

from treeinfer.errors import ConfigError
from treeinfer.inference import REGISTRY, SAMPLER_NAMES
from treeinfer.model import NOISE_KINDS, check_sigma  # noqa: E402

EXAMPLES = ROOT / "treeinfer" / "examples"
RESULTS = Path(__file__).resolve().parent / "results"
SIZES = ("tiny", "cpu", "full")
STUDIES = ("baselines", "nn_prior", "noise", "grasp")
ALL_SAMPLERS = SAMPLER_NAMES  # the registry's samplers, in its order
SAMPLER_LABELS = {name: name.upper() for name in REGISTRY}  # table and figure labels

# Modules whose code decides a posterior; a change to any of them invalidates the posterior cache.
_POSTERIOR_MODULES = (
    "treeinfer.inference.problem",
    "treeinfer.model.likelihood",
    "treeinfer.sim",
    "treeinfer.model.priors",
    "treeinfer.model.gradients",
    "treeinfer.tree.description",
    "treeinfer.tree.export",
    "treeinfer.data.trajectories",
    "treeinfer.inference.samplers",
)


# ==== configuration ===============================================================================
@dataclass(frozen=True)
class StudyConfig:
    """Everything that defines one study run (recorded in ``results.json``).

    Attributes:
      study, size: which study, which size (``tiny`` for tests, ``cpu`` for this machine in
        minutes, ``full`` for the paper's scale on a GPU).
      tree: a built-in example name (``treeinfer/examples/<tree>.yaml``) or a path.
      dt: s between samples; duration: s per trajectory (T = duration / dt samples).
      n_train, n_test: training / unseen test trajectories.
      profile_kind, peak_range: the random force profiles (:func:`treeinfer.data.random_specs`;
        N for the peaks).
      n_particles, n_iterations: the same for every sampler (paper: "all hyper-parameters ...
        similar across the algorithms").
      samplers: the samplers run (one condition each, except in the noise and grasp studies).
      sampler_options: per-sampler overrides of :data:`treeinfer.inference.REGISTRY` defaults.
      kT, eta: likelihood temperature and inequality-prior slope (None: the library default).
      likelihood: ``boltzmann`` (the paper's loss, default) or a generative noise model
        (``gaussian``, ``student_t``, ``ar1``: :mod:`treeinfer.model.noise`); then the headline band
        is the predictive band (simulations + fitted noise).
      noise_displacement: m, fixed sigma_x of the generative likelihoods (None: inferred as an
        extra theta column).
      noise_levels: relative noise sigma (noise study; see :func:`add_relative_noise`).
      grasp_locations, n_test_per_location: grasp study, test fractions of the branch length.
      level: credible level of the predictive intervals.
      n_plot: test trajectories drawn per row in the band grids.
    """

    study: str
    size: str
    tree: str = "three_branch"
    dt: float = 0.02
    duration: float = 1.0
    n_train: int = 2
    n_test: int = 8
    profile_kind: str = "mixed"
    peak_range: tuple[float, float] = (2.0, 8.0)
    n_particles: int = 12
    n_iterations: int = 50
    samplers: tuple[str, ...] = ("nnsvgd",)
    sampler_options: dict = field(default_factory=dict)
    kT: float | None = None
    eta: float | None = None
    likelihood: str = "boltzmann"
    noise_displacement: float | None = None
    noise_levels: tuple[float, ...] = (0.0,)
    grasp_locations: tuple[float, ...] = ()
    n_test_per_location: int = 0
    level: float = 0.95
    n_plot: int = 3

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


# Shared by every study of a size, so that data, posteriors and prediction shapes are shared.
BASE_SIZES: dict[str, dict[str, Any]] = {
    # the test-suite size: the 2-branch example compiles about twice as fast as the 3-branch one
    "tiny": dict(
        tree="two_branch",
        dt=0.02,
        duration=0.4,
        n_train=1,
        n_test=4,
        n_particles=6,
        n_iterations=3,
        n_plot=2,
    ),
    # minutes on a loaded 2-core CPU: compile time dominates (about a minute per sampler program)
    "cpu": dict(
        tree="three_branch",
        dt=0.02,
        duration=1.0,
        n_train=2,
        n_test=8,
        n_particles=12,
        n_iterations=50,
    ),
    # the paper's set-up (R = 3, 5 training and 25 unseen test trajectories), for a GPU
    "full": dict(
        tree="three_branch",
        dt=0.01,
        duration=3.0,
        n_train=5,
        n_test=25,
        n_particles=128,
        n_iterations=300,
    ),
}

STUDY_SIZES: dict[str, dict[str, dict[str, Any]]] = {
    "baselines": {s: dict(samplers=ALL_SAMPLERS) for s in SIZES},
    "nn_prior": {s: dict(samplers=("nnsvgd", "svgd")) for s in SIZES},
    "noise": {
        "tiny": dict(noise_levels=(0.0, 0.05)),
        "cpu": dict(noise_levels=(0.0, 0.02, 0.1)),
        "full": dict(noise_levels=(0.0, 0.01, 0.02, 0.05, 0.1)),
    },
    # n_test_per_location * 4 == n_test keeps the prediction batch the shape of the other studies
    "grasp": {
        "tiny": dict(grasp_locations=(0.25, 0.5, 0.75, 1.0), n_test_per_location=1),
        "cpu": dict(grasp_locations=(0.25, 0.5, 0.75, 1.0), n_test_per_location=2),
        "full": dict(grasp_locations=(0.25, 0.5, 0.75, 1.0), n_test_per_location=25),
    },
}


def study_config(study: str, size: str, **overrides) -> StudyConfig:
    """The configuration of ``study`` at ``size``, with ``overrides`` (None values ignored)."""
    if study not in STUDIES:
        raise ConfigError(f"study: unknown '{study}'; choose one of {', '.join(STUDIES)}")
    if size not in SIZES:
        raise ConfigError(f"--size: unknown '{size}'; choose one of {', '.join(SIZES)}")
    kw = {**BASE_SIZES[size], **STUDY_SIZES[study][size]}
    kw.update({k: v for k, v in overrides.items() if v is not None})
    cfg = StudyConfig(study=study, size=size, **kw)
    _check_config(cfg)
    return cfg


def _check_config(cfg: StudyConfig) -> None:
    bad = [s for s in cfg.samplers if s not in ALL_SAMPLERS]
    if bad or not cfg.samplers:
        raise ConfigError(f"samplers: unknown {bad}; choose from {', '.join(ALL_SAMPLERS)}")
    if any(not (0.0 <= s < 1.0) for s in cfg.noise_levels):
        raise ConfigError(
            "noise levels: must be in [0, 1) (relative to each signal's peak), "
            f"got {cfg.noise_levels}"
        )
    if any(not (0.0 < g <= 1.0) for g in cfg.grasp_locations):
        raise ConfigError(
            "grasp locations: must be in (0, 1] (fractions of the branch length), "
            f"got {cfg.grasp_locations}"
        )
    for name in ("n_train", "n_test", "n_iterations"):
        if getattr(cfg, name) < 1:
            raise ConfigError(f"{name}: must be at least 1, got {getattr(cfg, name)}")
    if cfg.grasp_locations and not (1 <= cfg.n_test_per_location <= cfg.n_test):
        raise ConfigError(
            f"n_test_per_location: must be in 1..n_test ({cfg.n_test}), "
            f"got {cfg.n_test_per_location}"
        )
    if cfg.likelihood not in ("boltzmann",) + NOISE_KINDS:
        raise ConfigError(
            f"likelihood: expected one of boltzmann, {', '.join(NOISE_KINDS)}, "
            f"got {cfg.likelihood!r}"
        )
    if cfg.noise_displacement is not None:
        check_sigma(cfg.noise_displacement, "noise_displacement")
    if cfg.n_particles < 2:
        raise ConfigError(
            f"n_particles: need at least 2 for a predictive distribution, got {cfg.n_particles}"
        )


def tree_path(name: str) -> Path:
    p = Path(name)
    return p if p.suffix in (".yaml", ".yml", ".json") else EXAMPLES / f"{name}.yaml"


class Context(NamedTuple):
    """What a study's ``main`` hands around: its config, seed, cache, output folder, progress."""

    cfg: StudyConfig
    seed: int
    cache: Path | None
    out: Path
    progress: bool
    sims: Any = None  # the study's treeinfer.runs.SimulatorCache
