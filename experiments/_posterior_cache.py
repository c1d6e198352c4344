"""Posteriors of the studies and their on-disk cache (split from :mod:`experiments.common`)."""

from __future__ import annotations

import functools
import hashlib
import importlib.metadata
import importlib.util
import json
import sys
from pathlib import Path
from typing import NamedTuple

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:  # run as `python experiments/<study>.py` from anywhere
    sys.path.insert(0, str(ROOT))

from experiments._config import _POSTERIOR_MODULES, StudyConfig  # noqa: E402
from experiments._data import SyntheticData  # noqa: E402
from treeinfer import __version__
from treeinfer.inference import sampler_options
from treeinfer.io.atomic import atomic_save


# ==== inference ===================================================================================
def make_problem(cfg: StudyConfig, data: SyntheticData, nn_prior: bool):
    from treeinfer.inference import make_problem as _make_problem

    kw = {}
    if cfg.kT is not None:
        kw["kT"] = cfg.kT
    if cfg.eta is not None:
        kw["eta"] = cfg.eta
    # explicit: the paper's loss is no longer make_problem's default (issue 27)
    kw["likelihood"] = cfg.likelihood
    if cfg.likelihood != "boltzmann":
        kw["noise_displacement"] = cfg.noise_displacement
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
    for name in _POSTERIOR_MODULES:  # module names, so a module that moves is still found
        spec = importlib.util.find_spec(name)
        p = Path(spec.origin)
        files = sorted(p.parent.rglob("*.py")) if p.name == "__init__.py" else [p]
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
    from treeinfer.tree.description import tree_to_dict

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
