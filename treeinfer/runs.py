"""Run folders: what ``treeinfer infer`` writes, how it checkpoints and resumes, and how
``predict`` / ``evaluate`` read it back.

A finished run is one folder ``RUN/``::

    config.json      every option, the seed, treeinfer/jax/mujoco versions, the data files with
                     their sha256, the problem and sampler settings (enough to reproduce the run)
    tree.yaml        the tree that was inferred (a copy, so the run stands on its own)
    posterior.nc     ArviZ InferenceData: posterior ``theta`` (log Kp, log Kd) with the labels as
                     ``param`` coordinates; MCMC samplers store the whole trace, one chain per
                     particle; SVGD/NNSVGD the final particles as one chain of draws
    particles.csv    one row per final particle: Kp/Kd in natural units, log_density, stable
    trace.npz        positions [n, P, D], log_density [n, P], iterations [n], final theta [P, D],
                     per-iteration sampler diagnostics (``diag_<name>``, at ``diag_iterations``)
    summary.json     diagnostics, convergence warnings, unstable particles, posterior table,
                     fit to the training data (95% band width, share of points outside)
    plots/           trace.png, pairs.png (log10 Kp/Kd, truth marked if known), bands_train.png

Atomicity: the folder is built in a hidden staging sibling and renamed into place at the very
end (:func:`treeinfer._io.staged_output_dir`), so ``RUN/`` appears complete or not at all.

Checkpoints live *beside* the run, in ``RUN.partial/`` (never inside ``RUN/``)::

    RUN.partial/config.json      the run's config (written before sampling starts)
    RUN.partial/tree.yaml        the tree copy
    RUN.partial/checkpoint.npz   sampler state after the last completed checkpoint

``checkpoint.npz`` holds the sampler state pytree flattened with ``jax.tree_util``
(``leaf_<i>``; PRNG key leaves as ``jax.random.key_data``), the completed iteration count and
the config hash (in the JSON string ``meta``), and a coarse trace (state positions and
log-densities at every checkpoint so far). It is replaced atomically every ``checkpoint_every``
iterations and once more when sampling ends. ``RUN.partial/`` is removed once ``RUN/`` is in
place. ``treeinfer infer --resume RUN`` reads ``RUN.partial/``, refuses if a data file changed
(sha256) or the settings the code derives from the config changed, and continues with
``infer(..., initial_state=state, start_iteration=k)``: the final particles equal those of an
uninterrupted run bit for bit (the driver keys iteration ``i`` by ``fold_in(key, i)``).

A resumed run's trace has the coarse checkpoint entries up to the resume point and every
iteration after it (``trace.npz['iterations']`` says which); its per-iteration sampler
diagnostics cover the resumed part only.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import math
import os
import platform
import shutil
import time
import warnings
import zipfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import __version__
from ._io import (
    atomic_write_bytes,
    atomic_write_json,
    atomic_write_text,
    check_output_dir,
    staged_output_dir,
)
from .errors import ConfigError, OutputExistsError, SimulationError, TrajectoryFileError
from .trajectories import (
    Observations,
    Trajectory,
    read_trajectory_dir,
    stack_trajectories,
    validate_trajectory,
)
from .tree import Tree, dump_tree, load_tree, tree_to_dict

__all__ = [
    "CHECKPOINT_FILE",
    "Checkpoint",
    "Checkpointer",
    "FoldResult",
    "ForceProfile",
    "InferOutcome",
    "LoadedRun",
    "Prediction",
    "build_problem",
    "check_data_unchanged",
    "config_hash",
    "data_manifest",
    "evaluate_trajectories",
    "file_sha256",
    "flatten_state",
    "infer_config",
    "infer_posterior",
    "kfold",
    "kfold_splits",
    "load_checkpoint",
    "load_run",
    "mean_metrics",
    "partial_dir",
    "particles_csv",
    "posterior_table",
    "predict_run",
    "read_checkpoint_info",
    "read_force_profile",
    "read_json",
    "read_true_params",
    "run_inference",
    "sampler_settings",
    "save_checkpoint",
    "save_run",
    "simulator_for",
    "state_template",
    "unflatten_state",
    "versions",
    "write_json",
]

RUN_FORMAT = 1
CHECKPOINT_FORMAT = 1
CHECKPOINT_FILE = "checkpoint.npz"
PARTIAL_SUFFIX = ".partial"
TRUE_PARAMS_FILE = "true_params.json"
LEVEL = 0.95  # credible / predictive interval mass everywhere in the run folder
UNITS = {"Kp": "N m/rad", "Kd": "N m s/rad"}

# Options that do not change the sampled particles: left out of the config hash, so a resume
# may differ in them (max_unstable_share may even be overridden on --resume).
_UNHASHED_OPTIONS = ("out", "force", "max_unstable_share", "progress")


# ==== files, hashes, versions =====================================================================
def file_sha256(path: str | os.PathLike) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def data_manifest(directory: str | os.PathLike, pattern: str = "*.csv") -> list[dict]:
    """``[{name, sha256, bytes}]`` of the files :func:`read_trajectory_dir` reads, in its order."""
    directory = Path(directory)
    files = sorted(p for p in directory.glob(pattern) if p.is_file())
    return [{"name": p.name, "sha256": file_sha256(p), "bytes": p.stat().st_size} for p in files]


def versions() -> dict:
    import mujoco

    try:
        from importlib.metadata import version

        mjx = version("mujoco-mjx")
    except Exception:  # noqa: BLE001 -- not installed as a distribution: record that
        mjx = None
    return {
        "treeinfer": __version__,
        "jax": jax.__version__,
        "mujoco": mujoco.__version__,
        "mujoco_mjx": mjx,
        "numpy": np.__version__,
        "python": platform.python_version(),
    }


def _jsonable(o: Any) -> Any:
    """Plain JSON values; NaN/inf become None (strict JSON has no NaN)."""
    if isinstance(o, dict):
        return {str(k): _jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_jsonable(v) for v in o]
    if isinstance(o, Path):
        return str(o)
    if isinstance(o, (np.ndarray, jax.Array)):
        return _jsonable(np.asarray(o).tolist())
    if isinstance(o, np.generic):
        o = o.item()
    if isinstance(o, float) and not math.isfinite(o):
        return None
    return o


def write_json(path, obj) -> Path:
    return atomic_write_json(path, _jsonable(obj))


def read_json(path: Path, what: str) -> dict:
    try:
        d = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such file ({what})") from None
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"{path}: cannot read {what}: {e}") from None
    except json.JSONDecodeError as e:
        raise ConfigError(f"{path}, line {e.lineno}: invalid JSON in {what}: {e.msg}") from None
    if not isinstance(d, dict):
        raise ConfigError(f"{path}: {what} must be a JSON object")
    return d


def config_hash(config: dict) -> str:
    """sha256 of what determines the sampled particles: the options (less ``out``, ``force``,
    ``max_unstable_share``), the tree, the data files' hashes, and the problem and sampler
    settings the code derived from them."""
    ident = {
        "options": {k: v for k, v in config["options"].items() if k not in _UNHASHED_OPTIONS},
        "tree": tree_to_dict_json(config["tree_dict"]),
        "data": [(f["name"], f["sha256"]) for f in config["data"]["files"]],
        "problem": config.get("problem"),
        "sampler": config.get("sampler"),
    }
    blob = json.dumps(_jsonable(ident), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(blob.encode("utf-8")).hexdigest()


def tree_to_dict_json(d) -> str:
    return json.dumps(_jsonable(d), sort_keys=True, separators=(",", ":"))


# ==== simulators ==================================================================================
# Compiled simulators by (tree, obs_dt, substeps). A Simulator is immutable and is a *static*
# jit argument hashed by identity, so handing the same object to every predict() in a process
# reuses the traced and compiled rollout instead of re-tracing the simulator (seconds; tens of seconds with MJX).
_SIMULATORS: dict[tuple, Any] = {}
_MAX_SIMULATORS = 8


def simulator_for(tree: Tree, obs_dt: float, substeps: int | None = None, backend: str = "auto"):
    """:func:`treeinfer.simulator.make_simulator` with a small per-process cache."""
    from .sim import make_simulator

    tree_key = tree_to_dict_json(tree_to_dict(tree))
    sim = _SIMULATORS.get((tree_key, float(obs_dt), substeps, backend))
    if sim is None:
        sim = make_simulator(tree, obs_dt=float(obs_dt), substeps=substeps, backend=backend)
        while len(_SIMULATORS) >= _MAX_SIMULATORS:
            _SIMULATORS.pop(next(iter(_SIMULATORS)))
        # under the requested and the resolved settings: a run folder records the resolved ones
        for b in {backend, sim.backend}:
            _SIMULATORS[(tree_key, float(obs_dt), substeps, b)] = sim
            _SIMULATORS[(tree_key, float(obs_dt), sim.substeps, b)] = sim
    return sim


# ==== config ======================================================================================
def infer_config(
    tree_path: str | os.PathLike,
    data_dir: str | os.PathLike,
    out: str | os.PathLike,
    *,
    sampler: str,
    particles: int,
    iterations: int,
    kT: float,
    seed: int,
    eta: float,
    grasp_fraction: float | None,
    max_unstable_share: float,
    checkpoint_every: int,
    force: bool = False,
    command: str = "infer",
    backend: str = "auto",
) -> dict:
    """The config of a new run (validated options; data and tree hashed). The problem and
    sampler settings are added by :func:`run_inference` once the problem is built."""
    tree_path, data_dir, out = Path(tree_path), Path(data_dir), Path(out)
    tree = load_tree(tree_path)
    files = data_manifest(data_dir) if data_dir.is_dir() else []
    trajs = read_trajectory_dir(data_dir)  # clear errors for a missing folder / bad file
    options = {
        "tree": str(tree_path.resolve()),
        "data": str(data_dir.resolve()),
        "out": str(out.resolve()),
        "sampler": sampler,
        "particles": int(particles),
        "iterations": int(iterations),
        "backend": str(backend),
        "kT": float(kT),
        "seed": int(seed),
        "eta": float(eta),
        "grasp_fraction": None if grasp_fraction is None else float(grasp_fraction),
        "max_unstable_share": float(max_unstable_share),
        "checkpoint_every": int(checkpoint_every),
        "force": bool(force),
    }
    return {
        "command": command,
        "format": RUN_FORMAT,
        "versions": versions(),
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "options": options,
        "seed": int(seed),
        "tree": {"file": str(tree_path.resolve()), "sha256": file_sha256(tree_path), "name": tree.name,
                 "labels": tree.parameter_labels()},
        "tree_dict": tree_to_dict(tree),
        "data": {
            "dir": str(data_dir.resolve()),
            "files": files,
            "dt": trajs[0].dt,
            "n_steps": [t.n_steps for t in trajs],
            "true_params": TRUE_PARAMS_FILE if (data_dir / TRUE_PARAMS_FILE).is_file() else None,
        },
        "checkpoint": {"every": int(checkpoint_every), "dir": str(partial_dir(out).resolve()), "file": CHECKPOINT_FILE},
    }


def read_true_params(tree: Tree, data_dir: str | os.PathLike) -> np.ndarray | None:
    """True parameters ``[2R]`` (natural units, label order) from ``DIR/true_params.json``, or None."""
    path = Path(data_dir) / TRUE_PARAMS_FILE
    if not path.is_file():
        return None
    from .cli import parse_params  # the one parser of true_params.json

    return parse_params(tree, params_json=path)


def check_data_unchanged(config: dict) -> list[Trajectory]:
    """Re-read the run's training data, refusing if any file changed, vanished or appeared."""
    d = Path(config["data"]["dir"])
    if not d.is_dir():
        raise ConfigError(f"{d}: the run's data folder no longer exists; restore it to resume")
    now = {f["name"]: f["sha256"] for f in data_manifest(d)}
    then = {f["name"]: f["sha256"] for f in config["data"]["files"]}
    changed = sorted(n for n in then if n in now and now[n] != then[n])
    missing = sorted(set(then) - set(now))
    added = sorted(set(now) - set(then))
    if changed or missing or added:
        parts = ([f"changed: {', '.join(changed)}"] if changed else []) + (
            [f"missing: {', '.join(missing)}"] if missing else []) + ([f"new: {', '.join(added)}"] if added else [])
        raise ConfigError(
            f"{d}: the training data differ from the run's (sha256 in config.json; {'; '.join(parts)}); "
            "restore the original files, or start a new run without --resume"
        )
    return read_trajectory_dir(d)


# ==== problem and posterior =======================================================================
def build_problem(config: dict, tree: Tree, trajectories: Sequence[Trajectory] | Observations):
    """The inference problem of a run config (the cached simulator; a jitted log-density)."""
    from .inference import make_problem

    o = config["options"]
    obs = trajectories if isinstance(trajectories, Observations) else stack_trajectories(list(trajectories))
    recorded = config.get("problem") or {}  # a resumed run: the settings it was built with
    sim = simulator_for(tree, float(obs.dt), recorded.get("substeps"), recorded.get("backend", o.get("backend", "auto")))
    problem = make_problem(
        tree, obs, kT=o["kT"], nn_prior=(o["sampler"] == "nnsvgd"), eta=o["eta"],
        grasp_fraction=o["grasp_fraction"], sim=sim,
    )
    # infer() evaluates log_density once at the end: jitted, the simulator is traced and compiled once
    # (op-by-op it costs tens of seconds); MH samples with the same function.
    return dataclasses.replace(problem, log_density=jax.jit(problem.log_density))


def sampler_settings(config: dict) -> dict:
    from .inference import SAMPLER_DEFAULTS

    name = config["options"]["sampler"]
    return {"name": name, "options": dict(SAMPLER_DEFAULTS[name])}


# ==== checkpoints =================================================================================
def partial_dir(run_dir: str | os.PathLike) -> Path:
    """``RUN.partial``: where a run in progress keeps its config and checkpoint."""
    p = Path(run_dir)
    return p.with_name(p.name + PARTIAL_SUFFIX)


class Checkpoint(NamedTuple):
    """A loaded checkpoint: ``state`` (the sampler's pytree) after ``iteration`` completed
    iterations; the coarse trace ``trace_iterations [m]``, ``trace_positions [m, P, D]``,
    ``trace_logdensity [m, P]`` (the state at each checkpoint so far)."""

    iteration: int
    state: Any
    config_hash: str
    trace_iterations: np.ndarray
    trace_positions: np.ndarray
    trace_logdensity: np.ndarray


def _is_key(x) -> bool:
    return jax.dtypes.issubdtype(getattr(x, "dtype", np.float32), jax.dtypes.prng_key)


def flatten_state(state) -> tuple[dict[str, np.ndarray], list[dict]]:
    """Sampler state pytree -> (``{"leaf_<i>": array}``, leaf specs). Key leaves are stored as
    their ``key_data`` with ``{"kind": "key", "impl": ...}``."""
    arrays, specs = {}, []
    for i, leaf in enumerate(jax.tree_util.tree_leaves(state)):
        if _is_key(leaf):
            arrays[f"leaf_{i}"] = np.asarray(jax.random.key_data(leaf))
            specs.append({"kind": "key", "impl": str(jax.random.key_impl(leaf))})
        else:
            a = np.asarray(leaf)
            arrays[f"leaf_{i}"] = a
            specs.append({"kind": "array", "dtype": str(a.dtype), "shape": list(a.shape)})
    return arrays, specs


def unflatten_state(arrays: dict[str, np.ndarray], specs: list[dict], template, where: str = "checkpoint"):
    """Inverse of :func:`flatten_state` onto ``template``'s structure (a state or its
    ``jax.eval_shape``); every leaf's kind, shape and dtype must match."""
    t_leaves, treedef = jax.tree_util.tree_flatten(template)
    if len(t_leaves) != len(specs):
        raise ConfigError(
            f"{where}: holds {len(specs)} state arrays but this sampler's state has {len(t_leaves)}; "
            "it was written by another sampler or treeinfer version"
        )
    leaves = []
    for i, (t, spec) in enumerate(zip(t_leaves, specs)):
        a = arrays[f"leaf_{i}"]
        if _is_key(t):
            if spec.get("kind") != "key":
                raise ConfigError(f"{where}: state array {i} should be a random key")
            leaves.append(jax.random.wrap_key_data(jnp.asarray(a), impl=spec["impl"]))
            continue
        if spec.get("kind") != "array" or tuple(a.shape) != tuple(t.shape) or a.dtype != np.dtype(t.dtype):
            raise ConfigError(
                f"{where}: state array {i} is {a.dtype}{list(a.shape)}, expected "
                f"{np.dtype(t.dtype)}{list(t.shape)} (different particles count or sampler?)"
            )
        leaves.append(jnp.asarray(a))
    return jax.tree_util.tree_unflatten(treedef, leaves)


def _zero_value_and_grad(theta):
    return jnp.zeros(theta.shape[:1], theta.dtype), jnp.zeros_like(theta)


def _zero_log_density(theta):
    return jnp.zeros(theta.shape[:1], theta.dtype)


def state_template(problem, sampler: str, theta0, **sampler_options):
    """Shapes and structure of ``sampler``'s state for particles like ``theta0 [P, D]``, without
    touching the simulator (the target is swapped for a zero function in ``jax.eval_shape``)."""
    from .inference import make_algorithm

    dummy = dataclasses.replace(problem, value_and_grad=_zero_value_and_grad, log_density=_zero_log_density)
    algorithm = make_algorithm(dummy, sampler, **sampler_options)
    return jax.eval_shape(algorithm.init, jax.random.key(0), jnp.asarray(theta0))


def _npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def save_checkpoint(
    path: str | os.PathLike,
    iteration: int,
    state,
    config_hash: str,
    trace_iterations=(),
    trace_positions=None,
    trace_logdensity=None,
) -> Path:
    """Write ``state`` after ``iteration`` completed iterations to ``path`` (.npz) atomically."""
    arrays, specs = flatten_state(jax.device_get(state))
    meta = {
        "format": CHECKPOINT_FORMAT,
        "iteration": int(iteration),
        "config_hash": config_hash,
        "leaves": specs,
        "treeinfer": __version__,
        "written_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    arrays["meta"] = np.asarray(json.dumps(meta))
    arrays["trace_iterations"] = np.asarray(trace_iterations, np.int64)
    if trace_positions is not None and len(trace_iterations):
        arrays["trace_positions"] = np.asarray(trace_positions)
        arrays["trace_logdensity"] = np.asarray(trace_logdensity)
    return atomic_write_bytes(path, _npz_bytes(arrays))


def _open_checkpoint(path: Path) -> tuple[dict, dict[str, np.ndarray]]:
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        meta = json.loads(str(arrays.pop("meta")))
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such checkpoint") from None
    except (OSError, ValueError, KeyError, zipfile.BadZipFile) as e:  # truncated / foreign file
        raise ConfigError(f"{path}: not a readable treeinfer checkpoint ({e})") from None
    if meta.get("format") != CHECKPOINT_FORMAT:
        raise ConfigError(f"{path}: checkpoint format {meta.get('format')!r}, expected {CHECKPOINT_FORMAT}")
    return meta, arrays


def read_checkpoint_info(path: str | os.PathLike) -> dict:
    """The checkpoint's ``meta`` (iteration, config_hash, leaf specs) without rebuilding a state."""
    return _open_checkpoint(Path(path))[0]


def load_checkpoint(path: str | os.PathLike, template, expected_hash: str | None = None) -> Checkpoint:
    """Read a checkpoint onto ``template`` (see :func:`state_template`); refuse one written for
    another config (``expected_hash``)."""
    path = Path(path)
    meta, arrays = _open_checkpoint(path)
    if expected_hash is not None and meta["config_hash"] != expected_hash:
        raise ConfigError(
            f"{path}: written for another configuration (config hash {meta['config_hash'][:12]}, "
            f"config.json gives {expected_hash[:12]}); the folder was modified, start a new run"
        )
    state = unflatten_state(arrays, meta["leaves"], template, str(path))
    it = arrays.get("trace_iterations", np.zeros(0, np.int64))
    n_p, dim = state.position.shape
    pos = arrays.get("trace_positions", np.zeros((0, n_p, dim), np.float32))
    ld = arrays.get("trace_logdensity", np.zeros((0, n_p), np.float32))
    return Checkpoint(int(meta["iteration"]), state, meta["config_hash"], it, pos, ld)


class Checkpointer:
    """The driver's ``callback(iteration, state)``: writes ``checkpoint.npz`` atomically and
    keeps the coarse trace (the state at every checkpoint) that goes with it."""

    def __init__(self, path: str | os.PathLike, config_hash: str, previous: Checkpoint | None = None):
        self.path = Path(path)
        self.config_hash = config_hash
        self.iterations: list[int] = [] if previous is None else [int(i) for i in previous.trace_iterations]
        self.positions: list[np.ndarray] = [] if previous is None else list(previous.trace_positions)
        self.logdensity: list[np.ndarray] = [] if previous is None else list(previous.trace_logdensity)
        self.last_iteration: int | None = None if previous is None else previous.iteration

    def __call__(self, iteration: int, state) -> None:
        iteration = int(iteration)
        if not self.iterations or self.iterations[-1] != iteration:
            self.iterations.append(iteration)
            self.positions.append(np.asarray(state.position))
            self.logdensity.append(np.asarray(state.logdensity))
        save_checkpoint(
            self.path, iteration, state, self.config_hash, self.iterations,
            np.stack(self.positions) if self.positions else None,
            np.stack(self.logdensity) if self.logdensity else None,
        )
        self.last_iteration = iteration


# ==== inference ===================================================================================
class InferOutcome(NamedTuple):
    """What :func:`run_inference` produced: the run folder, its config and summary, the posterior."""

    run_dir: Path
    config: dict
    summary: dict
    posterior: Any


def _prepare_fresh(config: dict, log: Callable[[str], None]):
    run_dir = Path(config["options"]["out"])
    partial = partial_dir(run_dir)
    force = config["options"]["force"]
    check_output_dir(run_dir, force, "run")
    if partial.exists():
        if not force:
            raise OutputExistsError(
                f"{partial}: an interrupted run is waiting there; continue it with "
                f"`treeinfer infer --resume {run_dir}`, or pass --force to discard it and start over"
            )
        shutil.rmtree(partial)
    tree = load_tree(config["options"]["tree"])
    trajs = read_trajectory_dir(config["options"]["data"])
    truth = read_true_params(tree, config["options"]["data"])
    return run_dir, partial, tree, trajs, truth


def _resume_paths(run_arg: str | os.PathLike) -> tuple[Path, Path]:
    p = Path(run_arg)
    if p.name.endswith(PARTIAL_SUFFIX):
        p = p.with_name(p.name[: -len(PARTIAL_SUFFIX)])
    partial = partial_dir(p)
    if not partial.is_dir():
        if (p / "config.json").is_file():
            raise ConfigError(f"{p}: this run is already complete; there is nothing to resume")
        raise ConfigError(
            f"{partial}: no interrupted run to resume (an interrupted `treeinfer infer --out {p}` "
            f"leaves its checkpoint in {partial.name}/)"
        )
    if not (partial / "config.json").is_file():
        raise ConfigError(f"{partial}: has no config.json; it is not an interrupted treeinfer run")
    return p, partial


def run_inference(
    config: dict | None = None,
    *,
    resume: str | os.PathLike | None = None,
    max_unstable_share: float | None = None,
    progress: bool = True,
    log: Callable[[str], None] = lambda msg: None,
    on_checkpointer: Callable[[Checkpointer], None] | None = None,
) -> InferOutcome:
    """Sample a posterior and write the run folder; or continue an interrupted one (``resume``).

    Args:
      config: from :func:`infer_config` (a new run), or None with ``resume=RUN``.
      resume: a run folder whose ``RUN.partial/`` holds an interrupted run.
      max_unstable_share: override the config's limit on unstable final particles (resume).
      progress: tqdm bar. log: one-line status messages (stderr in the CLI).
      on_checkpointer: called with the :class:`Checkpointer` before sampling starts (the CLI
        keeps it to say where a Ctrl-C left the run).

    Raises:
      SimulationError: more than ``max_unstable_share`` of the final particles are unstable
        (``RUN.partial/`` is kept: resume with a larger ``max_unstable_share`` to write it anyway).
    """
    from .inference import infer, initial_particles

    if resume is None:
        if config is None:
            raise ConfigError("run_inference: give a config (new run) or resume=RUN")
        run_dir, partial, tree, trajs, truth = _prepare_fresh(config, log)
        problem = build_problem(config, tree, trajs)
        config = {**config, "problem": problem.settings, "sampler": sampler_settings(config)}
        config["config_hash"] = config_hash(config)
        partial.mkdir(parents=True)
        dump_tree(tree, partial / "tree.yaml")
        write_json(partial / "config.json", config)  # written last: it marks a resumable run
        previous = None
    else:
        run_dir, partial = _resume_paths(resume)
        config = read_json(partial / "config.json", "the interrupted run's config")
        if config.get("format") != RUN_FORMAT or "config_hash" not in config:
            raise ConfigError(f"{partial / 'config.json'}: not a treeinfer run config (format {config.get('format')!r})")
        if config_hash(config) != config["config_hash"]:
            raise ConfigError(f"{partial / 'config.json'}: was edited (its hash no longer matches); start a new run")
        check_output_dir(run_dir, config["options"]["force"], "run")
        for stale in partial.glob(".*.tmp"):  # a temporary file of a write cut short by a kill
            stale.unlink(missing_ok=True)
        tree = load_tree(partial / "tree.yaml")
        if tree_to_dict_json(tree_to_dict(tree)) != tree_to_dict_json(config["tree_dict"]):
            raise ConfigError(f"{partial / 'tree.yaml'}: differs from the tree in config.json (edited?); start a new run")
        trajs = check_data_unchanged(config)
        truth = read_true_params(tree, config["data"]["dir"])
        problem = build_problem(config, tree, trajs)
        if _jsonable(problem.settings) != _jsonable(config["problem"]) or sampler_settings(config) != config["sampler"]:
            raise ConfigError(
                f"{partial}: this treeinfer derives other problem or sampler settings from the run's "
                f"options than the interrupted run did (recorded {config['problem']}, now {problem.settings}); "
                "it cannot continue it exactly: start a new run"
            )
        previous = None
        if (partial / CHECKPOINT_FILE).is_file():
            o = config["options"]
            theta0 = initial_particles(problem, o["particles"], o["seed"])
            template = state_template(problem, o["sampler"], theta0, **config["sampler"]["options"])
            previous = load_checkpoint(partial / CHECKPOINT_FILE, template, config["config_hash"])
            log(f"resuming {run_dir} from iteration {previous.iteration} of {o['iterations']}")
        else:
            log(f"{partial} has no checkpoint yet: starting {run_dir} again from iteration 0")
    if max_unstable_share is not None:
        config["options"]["max_unstable_share"] = float(max_unstable_share)

    o = config["options"]
    every = o["checkpoint_every"] or None
    checkpointer = Checkpointer(partial / CHECKPOINT_FILE, config["config_hash"], previous)
    if on_checkpointer is not None:
        on_checkpointer(checkpointer)
    posterior = infer(
        problem, o["sampler"], n_particles=o["particles"], n_iterations=o["iterations"], seed=o["seed"],
        progress=progress, callback=checkpointer if every else None, callback_every=every,
        initial_state=None if previous is None else previous.state,
        start_iteration=0 if previous is None else previous.iteration,
    )
    if checkpointer.last_iteration != o["iterations"]:
        # the end state too: if anything below fails (or is interrupted), --resume skips sampling
        checkpointer(o["iterations"], posterior.run.final_state)

    trace = _merged_trace(posterior.run, previous)
    fit = _training_fit(problem, posterior, config)
    from .sim import check_stable_share

    try:
        check_stable_share(fit["stable"], o["max_unstable_share"], f"the {o['particles']} final particles")
    except SimulationError as e:
        raise SimulationError(
            f"{e} (the limit is --max-unstable-share). The sampler state is kept in {partial}: "
            f"`treeinfer infer --resume {run_dir} --max-unstable-share X` writes the run anyway"
        ) from None
    summary = _run_summary(problem, posterior, config, trace, fit, truth)
    config = {**config, "posterior_settings": posterior.settings, "finished_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    save_run(run_dir, tree=tree, config=config, posterior=posterior, problem=problem, trace=trace, fit=fit,
             summary=summary, truth=truth, force=o["force"])
    shutil.rmtree(partial, ignore_errors=True)
    return InferOutcome(run_dir, config, summary, posterior)


def infer_posterior(config: dict, tree: Tree, trajectories, progress: bool = True):
    """(problem, posterior) for ``config``'s settings on ``trajectories`` (no run folder): the
    k-fold protocol reuses a run's settings this way."""
    from .inference import infer

    problem = build_problem(config, tree, trajectories)
    o = config["options"]
    posterior = infer(problem, o["sampler"], n_particles=o["particles"], n_iterations=o["iterations"],
                      seed=o["seed"], progress=progress)
    return problem, posterior


def _merged_trace(run, previous: Checkpoint | None) -> dict:
    """Trace of the whole run: the driver's, preceded on a resumed run by the checkpoints' coarse one."""
    pos, ld, it = run.trace_positions, run.trace_logdensity, run.trace_iterations
    if previous is not None and len(previous.trace_iterations):
        keep = previous.trace_iterations <= previous.iteration
        pos = np.concatenate([previous.trace_positions[keep], pos])
        ld = np.concatenate([previous.trace_logdensity[keep], ld])
        it = np.concatenate([previous.trace_iterations[keep], it])
    first = run.settings["start_iteration"]
    diag = {k: np.asarray(v) for k, v in run.diagnostics.items()}
    n_diag = len(next(iter(diag.values()))) if diag else 0
    return {
        "positions": np.asarray(pos),
        "log_density": np.asarray(ld),
        "iterations": np.asarray(it, np.int64),
        "diagnostics": diag,
        "diag_iterations": np.arange(first + 1, first + 1 + n_diag, dtype=np.int64),
        "resumed_from": None if previous is None else int(previous.iteration),
        "elapsed_s": float(run.elapsed_s),
    }


# ==== predictions =================================================================================
class Prediction(NamedTuple):
    """Posterior predictive rollouts: ``tau [P, B, T]`` m; ``valid [P]`` particles used (stable
    here and finite posterior density); ``lower``, ``upper``, ``mean`` ``[B, T]`` m (95% KDE band)."""

    tau: np.ndarray
    tau_dot: np.ndarray
    stable: np.ndarray
    valid: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    mean: np.ndarray


def predict_run(sim, theta, forces, grasp_fraction=None, particle_ok=None, level: float = LEVEL) -> Prediction:
    """Simulate every particle ``theta [P, D]`` under ``forces [B, T]`` and summarise the band;
    unstable particles are excluded (``valid``). Needs two valid particles."""
    from .inference import predict
    from .metrics import predictive_interval

    theta = np.asarray(theta)
    rollout = jax.device_get(predict(sim, theta, np.atleast_2d(np.asarray(forces, np.float32)), grasp_fraction))
    stable = np.asarray(rollout.stable).all(axis=-1)
    valid = stable & (np.ones(len(theta), bool) if particle_ok is None else np.asarray(particle_ok, bool))
    if valid.sum() < 2:
        raise SimulationError(
            f"only {int(valid.sum())} of {len(theta)} particles give a stable simulation of these forces; "
            "a predictive band needs at least 2 (are the forces far larger than in training?)"
        )
    tau = np.asarray(rollout.tau)
    lower, upper, mean = (np.asarray(a) for a in predictive_interval(tau, level, valid))
    return Prediction(tau, np.asarray(rollout.tau_dot), stable, valid, lower, upper, mean)


def _per_trajectory_loglik(pred: Prediction, obs: Observations, kT: float) -> np.ndarray:
    """[P, B] Boltzmann log-likelihood of each particle on each trajectory (-inf if unstable)."""
    from .likelihood import trajectory_loss
    from .sim import Rollout

    r = Rollout(jnp.asarray(pred.tau), jnp.asarray(pred.tau_dot), jnp.asarray(np.broadcast_to(pred.stable[:, None], pred.tau.shape[:2])))
    loss = np.asarray(trajectory_loss(r, obs))
    return np.where(pred.valid[:, None], -loss / kT, -np.inf)


def evaluate_trajectories(sim, theta, labels, trajectories: Sequence[Trajectory], kT: float, grasp_fraction=None,
                          truth=None, particle_ok=None) -> tuple[dict, Prediction, Observations]:
    """Held-out metrics of particles ``theta`` on ``trajectories`` (:func:`treeinfer.metrics.summarize`
    with the posterior NLL of the held-out data, per-trajectory CI width / % outside and, with
    ``truth [2R]`` in natural units, posterior vs truth in log space)."""
    from .metrics import ci_width, fraction_outside, summarize

    obs = stack_trajectories(list(trajectories))
    if not math.isclose(float(obs.dt), sim.obs_dt, rel_tol=1e-6):
        raise ConfigError(f"the trajectories have dt={obs.dt:g} s but the run was inferred at dt={sim.obs_dt:g} s; "
                          "resample them to the run's step")
    pred = predict_run(sim, theta, obs.force, grasp_fraction, particle_ok)
    ll = _per_trajectory_loglik(pred, obs, kT)
    m = summarize(pred.tau, obs.displacement, mask=obs.mask, valid=pred.valid, log_likelihood=ll,
                  particles=None if truth is None else np.exp(np.asarray(theta, float)), truth=truth,
                  labels=labels, log_space=True)
    m["per_trajectory"] = [
        {
            "name": t.source,
            "ci_width": float(ci_width(pred.lower[b], pred.upper[b], obs.mask[b])),
            "pct_outside": 100.0 * float(fraction_outside(pred.lower[b], pred.upper[b], obs.displacement[b], obs.mask[b])),
        }
        for b, t in enumerate(trajectories)
    ]
    m["units"] = {"ci_width": "m", "predictive_nll": "nats", "posterior_nll": "nats (kT-scaled loss)"}
    return m, pred, obs


def _training_fit(problem, posterior, config) -> dict:
    pred_ok = np.isfinite(posterior.log_density)
    sim = problem.sim
    from .metrics import summarize

    rollout_pred = None
    try:
        rollout_pred = predict_run(sim, posterior.theta, problem.obs.force, config["options"]["grasp_fraction"], pred_ok)
    except SimulationError:
        pass  # too few stable particles: the stable-share check reports it
    if rollout_pred is None:
        return {"stable": np.zeros(len(posterior.theta), bool), "prediction": None, "metrics": None}
    ll = _per_trajectory_loglik(rollout_pred, problem.obs, problem.kT)
    metrics = summarize(rollout_pred.tau, problem.obs.displacement, mask=problem.obs.mask, valid=rollout_pred.valid,
                        log_likelihood=ll)
    return {"stable": rollout_pred.valid, "prediction": rollout_pred, "metrics": metrics}


# ==== summaries ===================================================================================
def posterior_table(theta, labels, valid=None, level: float = LEVEL) -> dict:
    """``{label: {mean, lower, upper, unit}}`` in natural units: the particle mean of the gain and
    the central ``level`` interval of the per-parameter KDE in log space, mapped back by ``exp``."""
    from .metrics import predictive_interval

    theta = np.asarray(theta, float)
    ok = np.all(np.isfinite(theta), axis=1) & (True if valid is None else np.asarray(valid, bool))
    out = {}
    if ok.sum() >= 2:
        lo, hi, _ = (np.asarray(a) for a in predictive_interval(theta, level, ok))
    else:
        lo = hi = np.full(theta.shape[1], np.nan)
    for j, lab in enumerate(labels):
        k = np.exp(theta[ok, j])
        out[lab] = {
            "mean": float(k.mean()) if k.size else float("nan"),
            "median": float(np.median(k)) if k.size else float("nan"),
            "lower": float(np.exp(lo[j])),
            "upper": float(np.exp(hi[j])),
            "unit": UNITS[lab.split("[")[0]],
        }
    return out


def _bandwidths(positions: np.ndarray) -> np.ndarray:
    from .samplers import median_length_scale

    if len(positions) == 0:
        return np.zeros(0)
    return np.asarray(jax.jit(jax.vmap(median_length_scale))(jnp.asarray(positions)), float)


def _diagnostics(sampler: str, trace: dict, labels) -> tuple[str, dict, list[str]]:
    from .diagnostics import convergence_warnings, mcmc_diagnostics, svgd_diagnostics

    kind = "svgd" if sampler in ("svgd", "nnsvgd") else "mcmc"
    try:
        if kind == "svgd":
            diag = svgd_diagnostics(trace["log_density"], _bandwidths(trace["positions"]))
        else:
            diag = mcmc_diagnostics(trace["positions"], labels, log_density=trace["log_density"])
        warns = convergence_warnings(diag, kind)
    except ConfigError as e:  # e.g. too short a trace for split R-hat
        diag, warns = {"error": str(e)}, [f"diagnostics unavailable: {e}"]
    if trace["resumed_from"] is not None:
        diag["resumed_from"] = trace["resumed_from"]
    return kind, diag, warns


def _run_summary(problem, posterior, config, trace, fit, truth) -> dict:
    o = config["options"]
    kind, diag, warns = _diagnostics(o["sampler"], trace, list(problem.labels))
    stable = np.asarray(fit["stable"], bool)
    summary = {
        "sampler": o["sampler"],
        "n_particles": o["particles"],
        "n_iterations": o["iterations"],
        "seed": o["seed"],
        "elapsed_s_sampling": trace["elapsed_s"],
        "diagnostics_kind": kind,
        "diagnostics": diag,
        "convergence_warnings": warns,
        "n_unstable": int((~stable).sum()),
        "unstable_particles": np.flatnonzero(~stable).tolist(),
        "posterior": posterior_table(posterior.theta, problem.labels, stable),
        "level": LEVEL,
        "training_metrics": fit["metrics"],
    }
    if truth is not None:
        from .metrics import posterior_vs_truth

        chk = posterior_vs_truth(np.exp(np.asarray(posterior.theta, float)), truth, LEVEL, stable, log=True)
        summary["truth"] = {
            lab: {"truth": float(truth[j]), "log_mean": float(chk.mean[j]), "log_truth": float(np.log(truth[j])),
                  "in_interval": bool(chk.in_marginal[j]), "rel_error_log": float(chk.rel_error[j])}
            for j, lab in enumerate(problem.labels)
        }
        summary["truth_in_joint_region"] = chk.in_joint
    return summary


# ==== the run folder ==============================================================================
def _csv_float(x) -> str:
    return repr(float(x))


def particles_csv(theta, labels, log_density, stable) -> str:
    """One row per particle: ``particle``, the labels in natural units, ``log_density``, ``stable``."""
    theta = np.asarray(theta, float)
    lines = [
        (f"# treeinfer {__version__}: posterior particles; Kp in {UNITS['Kp']}, Kd in {UNITS['Kd']}; "
         "log_density of the whole target (-inf: unstable simulation)"),
        ",".join(["particle", *labels, "log_density", "stable"]),
    ]
    for i, row in enumerate(np.exp(theta)):
        lines.append(",".join([str(i), *(_csv_float(v) for v in row), _csv_float(log_density[i]), str(bool(stable[i])).lower()]))
    return "\n".join(lines) + "\n"


def save_run(
    run_dir: str | os.PathLike,
    *,
    tree: Tree,
    config: dict,
    posterior,
    problem,
    trace: dict,
    fit: dict,
    summary: dict,
    truth=None,
    force: bool = False,
) -> Path:
    """Write the run folder (see the module docstring) atomically: built in a staging folder,
    moved into place at the end."""
    from .diagnostics import save_inference_data, to_inference_data
    from .plots import pair_plot, plot_band_grid, plot_trace, save_figure

    labels = list(problem.labels)
    sampler = config["options"]["sampler"]
    stable = np.asarray(fit["stable"], bool)
    with staged_output_dir(run_dir, force, "run") as stage:
        write_json(stage / "config.json", config)
        dump_tree(tree, stage / "tree.yaml")
        attrs = {"treeinfer_version": __version__, "theta": "natural log of Kp [N m/rad] then Kd [N m s/rad]",
                 "seed": int(config["options"]["seed"]), "n_iterations": int(config["options"]["iterations"])}
        if sampler in ("svgd", "nnsvgd"):
            idata = to_inference_data(posterior.theta, labels, log_density=posterior.log_density, sampler=sampler, attrs=attrs)
        else:
            attrs["trace_iterations"] = ",".join(str(i) for i in trace["iterations"])
            with warnings.catch_warnings():  # short runs: ArviZ suspects chains and draws swapped
                warnings.filterwarnings("ignore", "More chains", UserWarning)
                idata = to_inference_data(trace["positions"], labels, log_density=trace["log_density"],
                                          sampler=sampler, attrs=attrs)
        save_inference_data(idata, stage / "posterior.nc")
        atomic_write_text(stage / "particles.csv", particles_csv(posterior.theta, labels, posterior.log_density, stable))
        arrays = {
            "positions": trace["positions"], "log_density": trace["log_density"], "iterations": trace["iterations"],
            "theta": np.asarray(posterior.theta), "final_log_density": np.asarray(posterior.log_density),
            "labels": np.asarray(labels), "diag_iterations": trace["diag_iterations"],
            **{f"diag_{k}": v for k, v in trace["diagnostics"].items()},
        }
        atomic_write_bytes(stage / "trace.npz", _npz_bytes(arrays))
        write_json(stage / "summary.json", summary)

        plots = stage / "plots"
        bw = _bandwidths(trace["positions"]) if sampler in ("svgd", "nnsvgd") else None
        fig, _ = plot_trace(trace["log_density"], bw, iterations=trace["iterations"], title=f"{sampler}: log density")
        save_figure(fig, plots / "trace.png")
        ok = stable & np.all(np.isfinite(posterior.theta), axis=1)
        t10 = None if truth is None else np.log10(np.asarray(truth, float))
        fig, _ = pair_plot(np.asarray(posterior.theta, float)[ok] / np.log(10.0), [f"log10 {lab}" for lab in labels],
                           truth=t10, title=f"posterior ({int(ok.sum())} stable particles)")
        save_figure(fig, plots / "pairs.png")
        pred = fit["prediction"]
        if pred is not None:
            obs = problem.obs
            gt = np.where(obs.mask, obs.displacement, np.nan)
            t = np.arange(obs.force.shape[1]) * float(obs.dt)
            names = [f["name"] for f in config["data"]["files"]]
            fig, _ = plot_band_grid(t, pred.lower, pred.upper, pred.mean, gt, titles=names,
                                    suptitle="95% predictive band vs training trajectories")
            save_figure(fig, plots / "bands_train.png")
    return Path(run_dir)


class LoadedRun(NamedTuple):
    """A finished run, ready for :func:`predict_run` / :func:`evaluate_trajectories`.

    path: the run folder. tree: its tree. config: config.json. theta: [P, D] final particles
    (log Kp, log Kd; float32 as sampled). labels: theta's columns. log_density: [P].
    stable: [P] stable on the training data. sim: the simulator at the recorded obs_dt/substeps.
    kT: the likelihood temperature. summary: summary.json. grasp_fraction: where the training
    data were recorded (``--grasp-fraction`` of the run; None: the tree's grasp).
    """

    path: Path
    tree: Tree
    config: dict
    theta: np.ndarray
    labels: tuple[str, ...]
    log_density: np.ndarray
    stable: np.ndarray
    sim: Any
    kT: float
    summary: dict
    grasp_fraction: float | None


def load_run(run_dir: str | os.PathLike) -> LoadedRun:
    """Read a run folder written by :func:`save_run` (ConfigError naming what is missing)."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        hint = f"; an interrupted run waits in {partial_dir(run_dir)} (--resume)" if partial_dir(run_dir).is_dir() else ""
        raise ConfigError(f"{run_dir}: no such run folder{hint}")
    if not (run_dir / "config.json").is_file():
        raise ConfigError(f"{run_dir}: not a treeinfer run (no config.json); give the folder `treeinfer infer --out` wrote")
    config = read_json(run_dir / "config.json", "the run's config")
    if config.get("command") not in ("infer", "demo") or config.get("format") != RUN_FORMAT:
        raise ConfigError(f"{run_dir / 'config.json'}: not a treeinfer run config (command {config.get('command')!r})")
    for name in ("tree.yaml", "trace.npz"):
        if not (run_dir / name).is_file():
            raise ConfigError(f"{run_dir}: incomplete run folder, {name} is missing")
    tree = load_tree(run_dir / "tree.yaml")
    try:
        with np.load(run_dir / "trace.npz", allow_pickle=False) as z:
            theta, ld = z["theta"], z["final_log_density"]
            labels = tuple(str(s) for s in z["labels"])
    except (OSError, ValueError, KeyError, zipfile.BadZipFile) as e:
        raise ConfigError(f"{run_dir / 'trace.npz'}: unreadable ({e})") from None
    if list(labels) != tree.parameter_labels():
        raise ConfigError(f"{run_dir}: trace.npz labels {list(labels)} do not match tree.yaml {tree.parameter_labels()}")
    summary = read_json(run_dir / "summary.json", "the run's summary") if (run_dir / "summary.json").is_file() else {}
    stable = np.isfinite(ld)
    if summary.get("unstable_particles"):
        stable[np.asarray(summary["unstable_particles"], int)] = False
    p = config["problem"]
    sim = simulator_for(tree, p["obs_dt"], p["substeps"], p.get("backend", "auto"))  # folders from before backends existed: auto
    return LoadedRun(run_dir, tree, config, theta, labels, ld, stable, sim, float(p["kT"]), summary,
                     config["options"].get("grasp_fraction"))


# ==== force files =================================================================================
class ForceProfile(NamedTuple):
    """A force profile to predict: ``time [T]`` s, ``force [T]`` N (downward); ``displacement
    [T]`` m when the file also recorded the response (drawn as ground truth), else None."""

    time: np.ndarray
    force: np.ndarray
    displacement: np.ndarray | None
    source: str

    @property
    def dt(self) -> float:
        return float((self.time[-1] - self.time[0]) / (len(self.time) - 1))


def read_force_profile(path: str | os.PathLike) -> ForceProfile:
    """A trajectory CSV (``time,force,displacement[,velocity]``) or a ``time,force`` CSV.

    The two-column form is checked like a trajectory (uniform increasing time in s, forces in N)
    and errors name the file and line."""
    from .trajectories import read_trajectory

    path = Path(path)
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except OSError as e:
        raise TrajectoryFileError(f"{path}: cannot read force file ({e.strerror or e})") from None
    except UnicodeDecodeError as e:
        raise TrajectoryFileError(f"{path}: not UTF-8 text (byte {e.start})") from None
    lines = [(n, ln.rstrip("\r")) for n, ln in enumerate(text.split("\n"), start=1)]
    body = [(n, ln) for n, ln in lines if ln.strip() and not ln.strip().startswith("#")]
    if not body:
        raise TrajectoryFileError(f"{path}: file is empty (expected a header 'time,force' or 'time,force,displacement')")
    header = [c.strip().strip('"').strip("'").lower() for c in body[0][1].split(",")]
    if "displacement" in header:
        tr = read_trajectory(path)
        return ForceProfile(tr.time, tr.force, tr.displacement, path.name)
    if sorted(header) != ["force", "time"]:
        raise TrajectoryFileError(
            f"{path}, line {body[0][0]}: header {header}; expected 'time,force' (a force profile) or "
            "'time,force,displacement[,velocity]' (a trajectory)"
        )
    rows, where_line = [], []
    for n, ln in body[1:]:
        cells = ln.split(",")
        if len(cells) != 2:
            raise TrajectoryFileError(f"{path}, line {n}: row has {len(cells)} cell(s) but the header has 2 columns")
        try:
            vals = [float(c) for c in cells]
        except ValueError:
            raise TrajectoryFileError(f"{path}, line {n}: non-numeric value in {ln.strip()!r}") from None
        if not all(math.isfinite(v) for v in vals):
            raise TrajectoryFileError(f"{path}, line {n}: NaN/inf not allowed")
        rows.append(vals)
        where_line.append(n)
    if not rows:
        raise TrajectoryFileError(f"{path}: header only, no data rows")
    a = np.asarray(rows, float)
    col = {name: a[:, j] for j, name in enumerate(header)}
    tr = validate_trajectory(Trajectory(col["time"], col["force"], np.zeros(len(a)), None, str(path)))
    return ForceProfile(tr.time, tr.force, None, path.name)


# ==== k-fold cross-validation =====================================================================
def kfold_splits(n: int, k: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """``k`` (train, test) index splits of ``n`` items: contiguous folds in file order, sizes
    differing by at most one (``numpy.array_split``)."""
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 2:
        raise ConfigError(f"--kfold: K must be an integer >= 2, got {k!r}")
    if k > n:
        raise ConfigError(f"--kfold {k}: needs at least {k} trajectories (one held-out fold each), found {n}")
    idx = np.arange(n)
    folds = np.array_split(idx, k)
    return [(np.setdiff1d(idx, f), f) for f in folds]


class FoldResult(NamedTuple):
    fold: int
    train: list[str]
    test: list[str]
    metrics: dict
    theta: np.ndarray
    prediction: Prediction


def kfold(config: dict, tree: Tree, trajectories: Sequence[Trajectory], k: int, grasp_fraction=None, truth=None,
          progress: bool = True, log: Callable[[str], None] = lambda m: None) -> list[FoldResult]:
    """The paper's real-to-sim protocol: for each of ``k`` folds, infer on the other folds with
    ``config``'s sampler settings and evaluate on the held-out fold."""
    trajectories = list(trajectories)
    splits = kfold_splits(len(trajectories), k)
    cfg = {**config, "options": {**config["options"], "grasp_fraction": grasp_fraction}}
    out = []
    for i, (tr, te) in enumerate(splits, start=1):
        train = [trajectories[j] for j in tr]
        test = [trajectories[j] for j in te]
        log(f"fold {i}/{k}: inferring on {len(train)} trajectories, holding out {', '.join(t.source for t in test)}")
        problem, post = infer_posterior(cfg, tree, train, progress)
        m, pred, _ = evaluate_trajectories(problem.sim, post.theta, list(problem.labels), test, problem.kT,
                                           grasp_fraction, truth, np.isfinite(post.log_density))
        out.append(FoldResult(i, [t.source for t in train], [t.source for t in test], m, np.asarray(post.theta), pred))
    return out


def mean_metrics(results: Sequence[dict]) -> tuple[dict, dict]:
    """Mean and standard deviation (ddof=0) over folds of every numeric top-level metric."""
    keys = [k for k, v in results[0].items() if isinstance(v, (int, float)) and not isinstance(v, bool)]
    mean, std = {}, {}
    for k in keys:
        vals = np.array([r[k] for r in results if isinstance(r.get(k), (int, float)) and r.get(k) is not None], float)
        mean[k] = float(np.mean(vals)) if vals.size else None
        std[k] = float(np.std(vals)) if vals.size else None
    return mean, std
