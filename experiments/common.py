"""Shared machinery of the paper's sim-to-sim studies (``experiments/<study>.py``).

One study = one :class:`StudyConfig` (sizes ``tiny`` / ``cpu`` / ``full``), synthetic data with
known parameters (:func:`make_data`), one posterior per condition (:func:`posterior`), the
paper's metrics on unseen test trajectories (:func:`evaluate`), and a results folder
(:func:`write_results`: ``results.json``, ``results.md``, PNGs, written atomically).

Sim-to-sim protocol (paper, "Sim-to-sim"):

* **Ground truth** comes from plain MuJoCo (C, float64: :func:`treeinfer.sim.reference.simulate_reference`),
  an execution path independent of the batched MJX simulator (float32) that inference uses; only
  the force-deformation trajectories pass from one to the other. True parameters are drawn by
  :func:`treeinfer.synthetic.default_true_params` (log-uniform in the middle third of the prior box,
  parent >= child), as ``treeinfer simulate`` does.
* **Training and test sets** use different force profiles drawn from independent seed streams
  (``numpy.random.SeedSequence(seed).spawn``): the test trajectories are never seen by inference.
* **Seeds**: ``--seed S`` fixes the true parameters, the profiles, the noise and the sampler
  key; the same seed gives the same numbers (JAX on one device is deterministic).

Compute on a small CPU: MJX compiles every new program for 30-120 s, so the studies share
everything they can. All studies of one size use the same tree, true parameters and training
set, and a posterior is cached on disk under a key of everything that determines it
(:func:`posterior`): NNSVGD and SVGD of the baselines are reused by the NN-prior study, NNSVGD by
the noise study's sigma = 0 and by the grasp study. Predictions of a study go through one
jitted call whose shape is the same in every study of a size.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import hashlib
import importlib.metadata
import json
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:  # run as `python experiments/<study>.py` from anywhere
    sys.path.insert(0, str(ROOT))

from treeinfer import __version__
from treeinfer._io import atomic_save, atomic_write_json, atomic_write_text, staged_output_dir
from treeinfer.errors import ConfigError, OutputExistsError, SimulationError, TreeinferError
from treeinfer.samplers import REGISTRY, SAMPLER_NAMES, sampler_options

EXAMPLES = ROOT / "treeinfer" / "examples"
RESULTS = Path(__file__).resolve().parent / "results"
SIZES = ("tiny", "cpu", "full")
STUDIES = ("baselines", "nn_prior", "noise", "grasp")
ALL_SAMPLERS = SAMPLER_NAMES  # the registry's samplers, in its order
SAMPLER_LABELS = {name: name.upper() for name in REGISTRY}  # table and figure labels

# Modules whose code decides a posterior; a change to any of them invalidates the posterior cache.
_POSTERIOR_MODULES = (
    "inference.py",
    "likelihood.py",
    "sim",
    "priors.py",
    "gradients.py",
    "tree.py",
    "export.py",
    "trajectories.py",
    "samplers",
)


# ==== configuration =================================================================================
@dataclass(frozen=True)
class StudyConfig:
    """Everything that defines one study run (recorded in ``results.json``).

    Attributes:
      study, size: which study, which size (``tiny`` for tests, ``cpu`` for this machine in
        minutes, ``full`` for the paper's scale on a GPU).
      tree: a built-in example name (``treeinfer/examples/<tree>.yaml``) or a path.
      dt: s between samples; duration: s per trajectory (T = duration / dt samples).
      n_train, n_test: training / unseen test trajectories.
      profile_kind, peak_range: the random force profiles (:func:`treeinfer.forces.random_specs`;
        N for the peaks).
      n_particles, n_iterations: the same for every sampler (paper: "all hyper-parameters ...
        similar across the algorithms").
      samplers: the samplers run (one condition each, except in the noise and grasp studies).
      sampler_options: per-sampler overrides of :data:`treeinfer.samplers.REGISTRY` defaults.
      kT, eta: likelihood temperature and inequality-prior slope (None: the library default).
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
            f"noise levels: must be in [0, 1) (relative to each signal's peak), got {cfg.noise_levels}"
        )
    if any(not (0.0 < g <= 1.0) for g in cfg.grasp_locations):
        raise ConfigError(
            f"grasp locations: must be in (0, 1] (fractions of the branch length), got {cfg.grasp_locations}"
        )
    for name in ("n_train", "n_test", "n_iterations"):
        if getattr(cfg, name) < 1:
            raise ConfigError(f"{name}: must be at least 1, got {getattr(cfg, name)}")
    if cfg.grasp_locations and not (1 <= cfg.n_test_per_location <= cfg.n_test):
        raise ConfigError(
            f"n_test_per_location: must be in 1..n_test ({cfg.n_test}), got {cfg.n_test_per_location}"
        )
    if cfg.n_particles < 2:
        raise ConfigError(
            f"n_particles: need at least 2 for a predictive distribution, got {cfg.n_particles}"
        )


def tree_path(name: str) -> Path:
    p = Path(name)
    return p if p.suffix in (".yaml", ".yml", ".json") else EXAMPLES / f"{name}.yaml"


# ==== command line ==================================================================================
def build_parser(study: str, description: str, epilog: str = "") -> argparse.ArgumentParser:
    """The options every study script shares: ``--size``, ``--out``, ``--seed``, caches, quiet."""
    p = argparse.ArgumentParser(
        prog=f"python experiments/{study}.py",
        description=description,
        epilog=epilog,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--size",
        choices=SIZES,
        default="cpu",
        help="tiny (tests), cpu (minutes here) or full (paper scale, GPU); default cpu",
    )
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        help=f"results folder (default experiments/results/{study}); replaced if it holds an earlier results.json",
    )
    p.add_argument(
        "--seed",
        type=int,
        default=0,
        help="seed of the true parameters, profiles, noise and samplers (default 0)",
    )
    p.add_argument("--particles", type=int, default=None, help="override the size's particle count")
    p.add_argument(
        "--iterations", type=int, default=None, help="override the size's iteration count"
    )
    p.add_argument(
        "--cache",
        type=Path,
        default=None,
        help="posterior cache folder (default $TREEINFER_CACHE/posteriors or ~/.cache/treeinfer/posteriors)",
    )
    p.add_argument(
        "--no-cache", action="store_true", help="neither read nor write cached posteriors"
    )
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    return p


def setup_jax() -> None:
    """Persistent XLA cache (MJX compiles slowly; a rerun of the same shapes skips it)."""
    import treeinfer

    treeinfer.enable_compilation_cache()


class Context(NamedTuple):
    """What a study's ``main`` hands around: its config, seed, cache, output folder, progress."""

    cfg: StudyConfig
    seed: int
    cache: Path | None
    out: Path
    progress: bool
    sims: Any = None  # the study's treeinfer.runs.SimulatorCache


def context_from_args(study: str, args: argparse.Namespace, **overrides) -> Context:
    cfg = study_config(
        study, args.size, n_particles=args.particles, n_iterations=args.iterations, **overrides
    )
    if args.no_cache:
        cache = None
    elif args.cache is not None:
        cache = args.cache
    else:
        from treeinfer.priors import default_cache_dir

        cache = default_cache_dir() / "posteriors"
    out = args.out if args.out is not None else RESULTS / study
    check_out(out)
    from treeinfer.runs import SimulatorCache

    return Context(cfg, int(args.seed), cache, Path(out), not args.quiet, SimulatorCache())


def check_out(out: Path) -> None:
    """Refuse a non-empty folder that does not hold an earlier study result (never clobber others' files)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise OutputExistsError(f"{out}: output path exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not (out / "results.json").exists():
        raise OutputExistsError(
            f"{out}: folder holds other files (no results.json); choose another --out"
        )


def run_main(fn, argv, study: str) -> int:
    """Run a study's ``main`` body with treeinfer's user-facing error handling (exit 2)."""
    try:
        return fn(argv)
    except TreeinferError as e:
        print(f"{study}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{study}: interrupted; nothing was written", file=sys.stderr)
        return 130


def say(ctx: Context, msg: str) -> None:
    if ctx.progress:
        from tqdm.auto import tqdm

        tqdm.write(f"[{ctx.cfg.study}] {msg}", file=sys.stderr)


# ==== synthetic data ================================================================================
class SyntheticData(NamedTuple):
    """A sim-to-sim data set.

    tree, sim: the tree (grasp at the training location) and its MJX simulator.
    kp, kd: [R] true gains (N m/rad, N m s/rad); theta: [2R] their natural logs.
    train, test: lists of :class:`~treeinfer.trajectories.Trajectory` (s, N, m, m/s).
    test_grasp: [n_test] fraction of the branch length where each test trajectory was recorded.
    train_specs, test_specs: the force profile specs (replayable with ``forces.from_spec``).
    """

    tree: Any
    sim: Any
    kp: np.ndarray
    kd: np.ndarray
    theta: np.ndarray
    train: list
    test: list
    test_grasp: np.ndarray
    train_specs: list
    test_specs: list

    def true_params(self) -> dict:
        from treeinfer.trajectories import true_params_record

        return true_params_record(self.tree, self.kp, self.kd, "experiments (default_true_params)")


def _simulator(path: str, dt: float, sims=None):
    """The tree and its simulator from ``sims`` (a :class:`treeinfer.runs.SimulatorCache`, one
    per study: jitted predictions are cached on the simulator's identity)."""
    from treeinfer.runs import SimulatorCache
    from treeinfer.tree import load_tree

    tree = load_tree(path)
    return tree, (SimulatorCache() if sims is None else sims).get(tree, dt)


def seed_streams(seed: int) -> dict[str, np.random.Generator]:
    """Independent generators of one seed: true parameters, training and test profiles."""
    names = ("params", "train", "test")
    return {
        n: np.random.default_rng(s)
        for n, s in zip(names, np.random.SeedSequence(int(seed)).spawn(len(names)))
    }


def reference_trajectory(
    sim, kp, kd, force: np.ndarray, dt: float, source: str, grasp_fraction=None
):
    """Ground truth of one pull from plain MuJoCo (float64), as a Trajectory."""
    from treeinfer.sim.reference import simulate_reference
    from treeinfer.trajectories import Trajectory, validate_trajectory

    tau, tau_dot = simulate_reference(sim, kp, kd, force, grasp_fraction)
    if not (np.all(np.isfinite(tau)) and np.max(np.abs(tau)) < sim.max_displacement):
        raise SimulationError(
            f"{source}: the ground-truth simulation blew up; lower the peak forces"
        )
    t = np.arange(len(force), dtype=float) * dt
    return validate_trajectory(Trajectory(t, np.asarray(force, float), tau, tau_dot, source))


def make_data(cfg: StudyConfig, seed: int, sims=None) -> SyntheticData:
    """Ground truth, training set and unseen test set of ``cfg`` (see the module docstring).

    The grasp study's test set is its first ``n_test_per_location`` test profiles pulled at each
    of ``cfg.grasp_locations``; every other study's is ``n_test`` profiles at the tree's grasp."""
    from treeinfer.forces import from_spec, random_specs
    from treeinfer.synthetic import default_true_params

    tree, sim = _simulator(str(tree_path(cfg.tree)), float(cfg.dt), sims)
    rng = seed_streams(seed)
    kp, kd = default_true_params(tree, rng["params"])
    train_specs = random_specs(
        cfg.profile_kind, cfg.n_train, cfg.duration, cfg.peak_range, rng["train"]
    )
    test_specs = random_specs(
        cfg.profile_kind, cfg.n_test, cfg.duration, cfg.peak_range, rng["test"]
    )
    train = [
        reference_trajectory(
            sim, kp, kd, from_spec(s, cfg.duration, cfg.dt), cfg.dt, f"train_{i:03d}"
        )
        for i, s in enumerate(train_specs)
    ]
    if cfg.grasp_locations:
        specs = test_specs[: cfg.n_test_per_location]
        grasp = np.repeat(np.asarray(cfg.grasp_locations, float), len(specs))
        specs = specs * len(cfg.grasp_locations)
        test_specs = specs
    else:
        grasp = np.full(len(test_specs), tree.grasp_fraction)
    test = [
        reference_trajectory(
            sim, kp, kd, from_spec(s, cfg.duration, cfg.dt), cfg.dt, f"test_{i:03d}", float(g)
        )
        for i, (s, g) in enumerate(zip(test_specs, grasp))
    ]
    theta = np.log(np.concatenate([kp, kd]))
    return SyntheticData(tree, sim, kp, kd, theta, train, test, grasp, train_specs, test_specs)


def noise_sigmas(data: SyntheticData, level: float) -> tuple[float, float]:
    """(sigma_force N, sigma_displacement m) of relative noise ``level``: ``level`` times the
    largest absolute force / displacement over the clean training and test trajectories."""
    trajs = data.train + data.test
    f_peak = max(float(np.max(np.abs(t.force))) for t in trajs)
    x_peak = max(float(np.max(np.abs(t.displacement))) for t in trajs)
    return level * f_peak, level * x_peak


def add_relative_noise(data: SyntheticData, level: float, seed: int) -> tuple[SyntheticData, dict]:
    """``data`` with white Gaussian noise on force and displacement of every training and test
    trajectory (:func:`treeinfer.trajectories.add_noise`, velocities then differentiated from the
    noisy displacement, as for a recording). The generator is seeded by ``(seed, level)``, so a
    level's noise does not depend on which other levels are run."""
    from treeinfer.trajectories import add_noise

    sf, sx = noise_sigmas(data, level)
    info = {"level": level, "sigma_force_N": sf, "sigma_displacement_m": sx}
    if level == 0:
        return data, info
    rng = np.random.default_rng([int(seed), 0x5EED, round(level * 1e6)])
    noisy = lambda ts: [add_noise(t, sf, sx, rng)._replace(source=t.source) for t in ts]
    return data._replace(train=noisy(data.train), test=noisy(data.test)), info


# ==== inference ======================================================================================
def make_problem(cfg: StudyConfig, data: SyntheticData, nn_prior: bool):
    from treeinfer.inference import make_problem as _make_problem

    kw = {}
    if cfg.kT is not None:
        kw["kT"] = cfg.kT
    if cfg.eta is not None:
        kw["eta"] = cfg.eta
    return _make_problem(data.tree, data.train, nn_prior=nn_prior, sim=data.sim, **kw)


class PosteriorRun(NamedTuple):
    """One sampler's result.

    theta: [P, D] final particles (natural logs of Kp, Kd). log_density: [P] there.
    trace_logdensity: [n, P]; trace_iterations: [n]. elapsed_s: sampler wall time (when it ran).
    from_cache: loaded from the posterior cache. settings: what produced it. key: cache key.
    """

    theta: np.ndarray
    log_density: np.ndarray
    trace_logdensity: np.ndarray
    trace_iterations: np.ndarray
    elapsed_s: float
    from_cache: bool
    settings: dict
    key: str


@functools.lru_cache(maxsize=1)
def _source_digest() -> str:
    """Hash of the posterior-deciding treeinfer sources, read once per process (the code this
    process runs, even if the files change while it runs)."""
    h = hashlib.sha256()
    pkg = ROOT / "treeinfer"
    for name in _POSTERIOR_MODULES:
        p = pkg / name
        files = sorted(p.rglob("*.py")) if p.is_dir() else [p]
        for f in files:
            h.update(str(f.relative_to(pkg)).encode())
            h.update(f.read_bytes())
    return h.hexdigest()[:16]


def _data_digest(problem) -> str:
    h = hashlib.sha256()
    for a in (problem.obs.force, problem.obs.displacement, problem.obs.velocity, problem.obs.mask):
        h.update(np.ascontiguousarray(np.asarray(a, np.float64)).tobytes())
    return h.hexdigest()[:16]


def posterior_key(
    problem, sampler: str, n_particles: int, n_iterations: int, seed: int, options: dict
) -> tuple[str, dict]:
    """Cache key and its description: everything that determines the sampler's output."""
    from treeinfer.tree import tree_to_dict

    desc = {
        "sampler": sampler,
        "sampler_options": sampler_options(sampler, **options),
        "n_particles": int(n_particles),
        "n_iterations": int(n_iterations),
        "seed": int(seed),
        "problem": {k: v for k, v in problem.settings.items()},
        "tree": tree_to_dict(problem.tree),
        "data": _data_digest(problem),
        "treeinfer": __version__,
        "source": _source_digest(),
        "jax": importlib.metadata.version("jax"),
        "mujoco_mjx": importlib.metadata.version("mujoco-mjx"),
    }
    blob = json.dumps(desc, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:24], desc


def _load_cached(path: Path, key: str) -> PosteriorRun | None:
    try:
        with np.load(path, allow_pickle=False) as z:
            settings = json.loads(str(z["settings"]))
            return PosteriorRun(
                np.asarray(z["theta"]),
                np.asarray(z["log_density"]),
                np.asarray(z["trace_logdensity"]),
                np.asarray(z["trace_iterations"]),
                float(z["elapsed_s"]),
                True,
                settings,
                key,
            )
    except (OSError, KeyError, ValueError):
        return None  # unreadable or from an older layout: recompute


def posterior(
    problem, sampler: str, cfg: StudyConfig, seed: int, cache: Path | None, progress: bool
) -> PosteriorRun:
    """:func:`treeinfer.inference.infer` with the study's particles, iterations and sampler
    options, or the identical run loaded from ``cache`` (see :func:`posterior_key`)."""
    from treeinfer.inference import infer

    options = dict(cfg.sampler_options.get(sampler, {}))
    key, desc = posterior_key(problem, sampler, cfg.n_particles, cfg.n_iterations, seed, options)
    path = None if cache is None else Path(cache) / f"{sampler}-{key}.npz"
    if path is not None and path.exists():
        hit = _load_cached(path, key)
        if hit is not None:
            return hit
    post = infer(
        problem,
        sampler,
        n_particles=cfg.n_particles,
        n_iterations=cfg.n_iterations,
        seed=seed,
        progress=progress,
        **options,
    )
    settings = {**desc, "infer": post.settings}
    run = PosteriorRun(
        np.asarray(post.theta, float),
        np.asarray(post.log_density, float),
        np.asarray(post.run.trace_logdensity, float),
        np.asarray(post.run.trace_iterations),
        float(post.run.elapsed_s),
        False,
        settings,
        key,
    )
    if path is not None:
        with atomic_save(path) as tmp, open(tmp, "wb") as f:
            np.savez(
                f,
                theta=run.theta,
                log_density=run.log_density,
                trace_logdensity=run.trace_logdensity,
                trace_iterations=run.trace_iterations,
                elapsed_s=run.elapsed_s,
                settings=json.dumps(settings, sort_keys=True, default=str),
            )
    return run


# ==== evaluation =====================================================================================
class Predictions(NamedTuple):
    """Rollouts of every particle on the training and the test forces.

    train_tau: [P, n_train, T]; test_tau: [P, n_test, T] m. valid: [P] stable on all of them.
    train_loglik: [P, n_train] Boltzmann log-likelihood ``-L_b / kT`` of each training trajectory
    (-inf for an unstable particle)."""

    train_tau: np.ndarray
    test_tau: np.ndarray
    valid: np.ndarray
    train_loglik: np.ndarray


def predict_all(problem, theta: np.ndarray, data: SyntheticData) -> Predictions:
    """One batched prediction of ``theta`` on the training and test forces (one compiled shape
    per size: the grasp fraction is always passed per profile)."""
    from treeinfer.evaluation import rollout_loglik
    from treeinfer.inference import predict
    from treeinfer.sim import Rollout

    n_train = len(data.train)
    forces = np.stack([t.force for t in data.train + data.test])
    grasp = np.concatenate([np.full(n_train, data.tree.grasp_fraction), data.test_grasp])
    r = predict(data.sim, theta, forces, grasp_fraction=grasp)
    tau, tau_dot, stable = (np.asarray(a) for a in (r.tau, r.tau_dot, r.stable))
    train = Rollout(tau[:, :n_train], tau_dot[:, :n_train], stable[:, :n_train])
    ll = rollout_loglik(train, problem.obs, problem.kT, dtype=float)
    return Predictions(tau[:, :n_train], tau[:, n_train:], stable.all(axis=1), ll)


def metrics_for(
    pred: Predictions, theta: np.ndarray, data: SyntheticData, problem, cfg: StudyConfig, idx=None
) -> dict:
    """The paper's metrics on test trajectories ``idx`` (default all) plus the posterior against the
    truth, as :func:`treeinfer.metrics.summarize` reports them; ``{"error": ...}`` when fewer than
    two particles simulate stably (no predictive distribution)."""
    from treeinfer.metrics import summarize

    idx = np.arange(len(data.test)) if idx is None else np.asarray(idx)
    gt = np.stack([data.test[i].displacement for i in idx])
    try:
        m = summarize(
            pred.test_tau[:, idx],
            gt,
            valid=pred.valid,
            level=cfg.level,
            log_likelihood=pred.train_loglik,
            particles=None,
            truth=None,
        )
        theta_ok = pred.valid & np.all(np.isfinite(pred.train_loglik), axis=1)
        m.update(parameter_metrics(problem, theta, data, cfg, theta_ok))
    except (SimulationError, ConfigError) as e:
        return {
            "error": str(e),
            "n_valid_particles": int(pred.valid.sum()),
            "n_particles": int(pred.valid.size),
        }
    m["n_test_trajectories"] = len(idx)
    m["n_train_trajectories"] = len(data.train)
    m["posterior_nll_per_point"] = m["posterior_nll"] / float(
        pred.train_tau.shape[1] * pred.train_tau.shape[2]
    )
    return m


def interval_metrics(pred: Predictions, gt: np.ndarray, cfg: StudyConfig) -> dict:
    """CI width, % outside and predictive NLL of the test predictions against another ground
    truth ``gt [n_test, T]`` (e.g. the noise-free displacement in the noise study)."""
    from treeinfer.metrics import summarize

    try:
        m = summarize(pred.test_tau, gt, valid=pred.valid, level=cfg.level)
    except (SimulationError, ConfigError) as e:
        return {"error": str(e)}
    keys = (
        "ci_width",
        "pct_outside",
        "fraction_outside",
        "predictive_nll",
        "predictive_nll_per_point",
        "n_points",
    )
    return {k: m[k] for k in keys}


def parameter_metrics(
    problem, theta: np.ndarray, data: SyntheticData, cfg: StudyConfig, valid
) -> dict:
    """Posterior ``theta [P, D]`` vs the truth in log space (``parameters``,
    ``truth_in_joint_region``, ``mean_abs_log_error``, ``n_params_in_interval``)."""
    from treeinfer.metrics import posterior_vs_truth

    chk = posterior_vs_truth(theta, data.theta, cfg.level, valid)  # theta is already ln K
    labels = list(problem.labels)
    params = {
        lab: {
            "mean": float(chk.mean[i]),
            "truth": float(data.theta[i]),
            "abs_error": float(chk.abs_error[i]),
            "lower": float(chk.lower[i]),
            "upper": float(chk.upper[i]),
            "in_interval": bool(chk.in_marginal[i]),
        }
        for i, lab in enumerate(labels)
    }
    return {
        "parameters": params,
        "parameter_space": "log",
        "truth_in_joint_region": chk.in_joint,
        "mean_abs_log_error": float(np.mean(chk.abs_error)),
        "n_params_in_interval": int(np.sum(chk.in_marginal)),
        "n_params": len(labels),
    }


def evaluate(
    problem, run: PosteriorRun, data: SyntheticData, cfg: StudyConfig, groups: dict | None = None
) -> tuple[Predictions, dict]:
    """Predict with the posterior and compute the metrics, over all test trajectories or per group
    (``{name: test indices}``, e.g. per grasp location)."""
    pred = predict_all(problem, run.theta, data)
    if groups is None:
        return pred, metrics_for(pred, run.theta, data, problem, cfg)
    return pred, {
        name: metrics_for(pred, run.theta, data, problem, cfg, idx) for name, idx in groups.items()
    }


def inference_record(run: PosteriorRun) -> dict:
    ld = run.log_density[np.isfinite(run.log_density)]
    return {
        "sampler_wall_s": run.elapsed_s,
        "from_cache": run.from_cache,
        "cache_key": run.key,
        "sampler_options": run.settings.get("sampler_options"),
        "n_particles": run.settings.get("n_particles"),
        "n_iterations": run.settings.get("n_iterations"),
        "final_mean_log_density": float(ld.mean()) if ld.size else None,
        "n_nonfinite_final": int(np.sum(~np.isfinite(run.log_density))),
    }


# ==== bands and plots =================================================================================
class Bands(NamedTuple):
    """Predictive bands of a few test trajectories: lower/upper/mean/gt [k, T], samples [k, S, T]."""

    lower: np.ndarray
    upper: np.ndarray
    mean: np.ndarray
    gt: np.ndarray
    samples: np.ndarray


def bands_for(
    pred: Predictions, data: SyntheticData, idx: Sequence[int], level: float, max_samples: int = 10
) -> Bands:
    from treeinfer.metrics import predictive_interval

    idx = np.asarray(idx)
    gt = np.stack([data.test[i].displacement for i in idx])
    tau = pred.test_tau[:, idx]
    if pred.valid.sum() >= 2:
        lo, hi, mean = (np.asarray(a, float) for a in predictive_interval(tau, level, pred.valid))
        samples = np.moveaxis(tau[pred.valid][:max_samples], 0, 1)
    else:  # no predictive distribution: draw the ground truth alone
        lo = hi = mean = np.full(gt.shape, np.nan)
        samples = np.full((len(idx), 1, gt.shape[-1]), np.nan)
    return Bands(lo, hi, mean, gt, samples)


def band_grid(
    rows: dict[str, Bands],
    dt: float,
    level: float,
    col_labels: Sequence[str],
    title: str,
    transpose: bool = False,
):
    """Rows = conditions, columns = test trajectories (paper Fig. 3/5 layout); ``transpose``
    puts the conditions in columns instead (Fig. 6: one column per grasp location)."""
    from treeinfer.plots import plot_band_grid

    names = list(rows)
    stack = lambda f: np.stack([getattr(rows[n], f) for n in names])
    arrays = [stack(f) for f in ("lower", "upper", "mean", "gt", "samples")]
    row_labels, col_labels = names, list(col_labels)
    if transpose:
        arrays = [np.swapaxes(a, 0, 1) for a in arrays]
        row_labels, col_labels = col_labels, row_labels
    t = np.arange(arrays[0].shape[-1]) * dt
    fig, _ = plot_band_grid(
        t,
        *arrays,
        row_labels=row_labels,
        col_labels=col_labels,
        suptitle=title,
        ylabel=f"displacement [m] ({level:.0%} band, grey)",
    )
    return fig


def metric_figure(names: Sequence[str], conditions: Sequence[dict], title: str, keys=None):
    """Bars of CI width, % GT outside and predictive NLL per condition (NaN for failed ones)."""
    from treeinfer.plots import metric_bars

    keys = keys or {
        "95% CI width [m]": "ci_width",
        "% GT outside": "pct_outside",
        "NLL / test point [nats]": "predictive_nll_per_point",
    }
    values = {
        lab: [c.get(k, np.nan) if "error" not in c else np.nan for c in conditions]
        for lab, k in keys.items()
    }
    fig, _ = metric_bars(list(names), values, separate=True, title=title)
    return fig


def pair_figure(sets: dict[str, np.ndarray], labels: Sequence[str], truth: np.ndarray, title: str):
    """Pair plot of log-parameter particles of several posteriors with the truth (paper Fig. 4)."""
    from treeinfer.plots import pair_plot

    fig, _ = pair_plot(sets, [f"ln {lab}" for lab in labels], truth, title=title)
    return fig


# ==== results =========================================================================================
def versions() -> dict:
    from treeinfer.runs import versions as run_versions

    v = run_versions(extended=True)
    v["mujoco-mjx"] = v.pop("mujoco_mjx")  # results.json spells it as the distribution does
    return v


def data_record(data: SyntheticData, problem) -> dict:
    return {
        "tree": data.tree.name,
        "grasp_branch": data.tree.grasp_branch,
        "train_grasp_fraction": data.tree.grasp_fraction,
        "true_params": data.true_params(),
        "train_profiles": list(data.train_specs),
        "test_profiles": list(data.test_specs),
        "test_grasp_fractions": [float(g) for g in data.test_grasp],
        "n_steps": int(data.train[0].n_steps),
        "dt_s": float(data.train[0].dt),
        "ground_truth": "plain MuJoCo C (float64), treeinfer.sim.reference.simulate_reference",
        "inference_simulator": {
            "engine": f"{problem.sim.backend} ({np.dtype(problem.sim.dtype).name})",
            "substeps": problem.sim.substeps,
            "sim_dt_s": problem.sim.sim_dt,
        },
        "problem": problem.settings,
    }


METRIC_NOTES = """\
Metric definitions (all on unseen test trajectories unless noted):

- **95% CI width** [m]: per test time step, the central 95% interval of a 1-D Gaussian KDE
  (Scott's rule) over the particles' predicted displacements (`treeinfer.metrics.predictive_interval`);
  the width is averaged over all test points (trajectories x time steps).
- **% GT outside**: share of ground-truth test points outside that interval, in percent.
- **NLL / test point**: negative log density of each ground-truth test point under the same
  per-step KDE, averaged over points (nats; `treeinfer.metrics.predictive_nll`). The total over
  all points is `predictive_nll` in results.json.
- **Posterior NLL (train)**: our reading of the paper's Table I "Nll of the estimated posterior
  from the training trajectories": minus the particle average of the Boltzmann log-likelihood
  `-sum_b L_b(theta) / kT` over the training trajectories (`treeinfer.metrics.posterior_nll`);
  its scale depends on kT and on the number and length of the trajectories.
- **|log error|**: mean over the 2R parameters of |posterior mean of ln K - ln K_true|
  (0.1 is about 10% off); **in 95%**: how many true parameters lie inside the posterior's
  marginal 95% interval.
"""


def fmt(v, spec: str = ".3g") -> str:
    if v is None:
        return "n/a"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, float) and not math.isfinite(v):
        return "n/a"
    return format(v, spec)


def markdown_table(headers: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    lines = ["| " + " | ".join(headers) + " |", "|" + "|".join("---" for _ in headers) + "|"]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


METRIC_HEADERS = [
    "95% CI width [m]",
    "% GT outside",
    "NLL / test point",
    "posterior NLL (train)",
    "|log error|",
    "in 95%",
    "valid particles",
]


def metric_cells(m: dict) -> list[str]:
    if "error" in m:
        return ["failed"] * (len(METRIC_HEADERS) - 1) + [
            f"{m.get('n_valid_particles', 0)}/{m.get('n_particles', '?')}"
        ]
    return [
        fmt(m["ci_width"], ".3f"),
        fmt(m["pct_outside"], ".1f"),
        fmt(m["predictive_nll_per_point"], ".2f"),
        fmt(m.get("posterior_nll"), ".4g"),
        fmt(m.get("mean_abs_log_error"), ".2f"),
        f"{m.get('n_params_in_interval', 0)}/{m.get('n_params', 0)}",
        f"{m['n_valid_particles']}/{m['n_particles']}",
    ]


def parameter_table(
    conditions: Sequence[tuple[str, dict]], labels: Sequence[str], truth: np.ndarray
) -> str:
    """Posterior mean (and 95% interval) of each ln K per condition, truth in the first row."""
    rows = [["truth"] + [fmt(float(t), ".2f") for t in truth]]
    for name, m in conditions:
        if "parameters" not in m:
            rows.append([name] + ["n/a"] * len(labels))
            continue
        cells = []
        for lab in labels:
            p = m["parameters"][lab]
            mark = "" if p["in_interval"] else " *"
            cells.append(f"{p['mean']:.2f} [{p['lower']:.2f}, {p['upper']:.2f}]{mark}")
        rows.append([name] + cells)
    return (
        markdown_table(["ln K"] + list(labels), rows)
        + "\n\n(* truth outside the 95% marginal interval)"
    )


def config_line(cfg: StudyConfig, data: SyntheticData, problem, test: str | None = None) -> str:
    test = test or f"{len(data.test)} unseen test"
    return (
        f"size `{cfg.size}`: tree `{data.tree.name}` (R = {data.tree.n_inferred}), {cfg.n_particles} particles, "
        f"{cfg.n_iterations} iterations, {len(data.train)} training and {test} "
        f"trajectories of {data.train[0].n_steps} samples at {cfg.dt:g} s, kT = {problem.kT:g}, "
        f"{problem.sim.backend} simulator, {problem.sim.substeps} substeps of {problem.sim.sim_dt * 1e3:.3g} ms"
    )


def write_results(
    ctx: Context, record: dict, markdown: str, figures: dict[str, Any], t0: float
) -> Path:
    """Write ``results.json`` (record + config + seed + versions + wall time), ``results.md`` and
    the PNG figures into ``ctx.out`` atomically (a staged folder renamed into place)."""
    from treeinfer.plots import save_figure

    record = {
        "study": ctx.cfg.study,
        "size": ctx.cfg.size,
        "seed": ctx.seed,
        "config": ctx.cfg.to_dict(),
        "versions": versions(),
        "command": " ".join([Path(sys.argv[0]).name] + sys.argv[1:])
        if sys.argv and sys.argv[0]
        else None,
        **record,
        "figures": sorted(figures),
        "wall_time_s": time.perf_counter() - t0,
        "cpu_time_s": cpu_seconds(),
    }
    md = markdown + (
        f"\n\nWall time: {record['wall_time_s']:.0f} s, process CPU time {record['cpu_time_s']:.0f} s "
        f"(seed {ctx.seed}; {record['versions'].get('jax_backend', '?')} backend).\n"
    )
    with staged_output_dir(ctx.out, force=True, what="results") as stage:
        for name, fig in figures.items():
            save_figure(fig, stage / name)
        atomic_write_json(stage / "results.json", record)
        atomic_write_text(stage / "results.md", md)
    return ctx.out


def cpu_seconds() -> float:
    """User + system CPU seconds of this process so far (all threads)."""
    import resource

    ru = resource.getrusage(resource.RUSAGE_SELF)
    return float(ru.ru_utime + ru.ru_stime)


def progress_bar(ctx: Context, total: int):
    from tqdm.auto import tqdm

    return tqdm(
        total=total,
        desc=ctx.cfg.study,
        unit="step",
        disable=not ctx.progress,
        position=None,
        leave=True,
    )
