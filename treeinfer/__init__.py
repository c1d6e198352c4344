"""treeinfer: learn how tree branches bend when a robot pulls on them.

Importing treeinfer changes nothing outside it (no environment variables, no JAX settings). The
command line sets up JAX's runtime for its run (:func:`configure_runtime`: persistent compile
cache, GPU memory grown on demand); a program that uses the library calls
``treeinfer.configure_runtime()`` itself, before its first JAX computation, to get the same.
"""

import sys as _sys

if _sys.version_info < (3, 11):  # before any syntax or library that needs 3.11 fails obscurely
    raise ImportError(
        f"treeinfer needs Python >= 3.11; this is Python {_sys.version.split()[0]} "
        f"({_sys.executable})"
    )

__version__ = "0.1.0"

# The public API, imported lazily so `treeinfer --help` does not pay for JAX and MuJoCo.
_EXPORTS = {
    "load_tree": "tree.description",
    "dump_tree": "tree.description",
    "make_tree": "tree.description",
    "Tree": "tree.description",
    "Branch": "tree.description",
    "Bounds": "tree.description",
    "Trajectory": "data.trajectories",
    "read_trajectory": "data.trajectories",
    "read_trajectory_dir": "data.trajectories",
    "write_trajectory": "data.trajectories",
    "stack_trajectories": "data.trajectories",
    "make_simulator": "sim",
    "simulate": "sim",
    "Rollout": "sim",
    "make_problem": "inference.problem",
    "infer": "inference.problem",
    "predict": "inference.problem",
    "Problem": "inference.problem",
    "ProblemSpec": "inference.spec",
    "Posterior": "inference.problem",
    "load_posterior": "runs.posterior_load",
    "example_path": "examples",
    "check_environment": "cli.environment",
}
_MODULES = {
    "tree",
    "sim",
    "model",
    "inference",
    "evaluation",
    "data",
    "errors",
    "examples",
    "runs",
    "cli",
}


# Old module paths (the flat layout before issue 26) keep working for one release, with a
# DeprecationWarning naming the new path: user scripts, notebooks and pickles written against
# 0.1 still import. A finder first on sys.meta_path answers only for these names (none of
# which exists any more), so it changes nothing else; being first, it also catches submodules
# of a moved folder (treeinfer.samplers.svgd), which the path finder would load twice.
# Old names that are now packages themselves (tree, inference, evaluation, design) are not here:
# the package re-exports the old module's public names.
_MOVED = {  # old module (before the layout by job, issue 26) -> where it lives now
    "_generate": "tree._generate",
    "_io": "io.atomic",
    "_plot_common": "evaluation._plot_common",
    "arviz_compat": "inference.diagnostics.arviz_compat",
    "atomic_write": "io.atomic_write",
    "bag_kortex": "data.kortex",
    "bag_streams": "data.bags",
    "bag_types": "data.bag_messages",
    "bags": "data.import_bag",
    "bands": "evaluation.bands",
    "batch_posteriors": "inference.batch",
    "checks": "evaluation.checks",
    "checks_data": "data.checks",
    "checks_fit": "evaluation.ppc",
    "checks_tree": "tree.plausibility",
    "compile_stats": "sim.compile_stats",
    "csv_import": "data.import_csv",
    "csv_read": "data.csv_format",
    "design_candidates": "design.candidates",
    "design_estimators": "design.estimators",
    "design_run": "runs.suggest",
    "design_scoring": "design.scoring",
    "diagnostics": "inference.diagnostics",
    "environment": "cli.environment",
    "export": "tree.export",
    "fast_posterior": "inference.fast",
    "force_noise": "model.force_noise",
    "forces": "data.forces",
    "gains": "model.gains",
    "generators": "tree.generators",
    "gradients": "model.gradients",
    "importance": "inference.importance",
    "inequality_net": "model.inequality_net",
    "integrity": "runs.integrity",
    "interrupt": "io.interrupt",
    "jsonio": "io.jsonio",
    "laplace": "inference.laplace",
    "likelihood": "model.likelihood",
    "limits": "io.limits",
    "lm": "inference.lm",
    "lsystem": "tree.lsystem",
    "manifest": "io.manifest",
    "mapfit": "inference.mapfit",
    "metrics": "evaluation.metrics",
    "model_geometry": "tree.geometry",
    "model_paths": "tree.model_paths",
    "modelsection": "tree.model_section",
    "noise": "model.noise",
    "noise_estimate": "data.noise_estimate",
    "ownership": "io.ownership",
    "plot_posterior": "evaluation.posterior_plots",
    "plot_trace": "evaluation.trace_plot",
    "plots": "evaluation.plots",
    "posterior": "inference.posterior",
    "posterior_io": "inference.posterior_io",
    "predictive": "evaluation.posterior_bands",
    "priors": "model.priors",
    "problem_priors": "model.prior_terms",
    "program_cache": "sim.program_cache",
    "pull_checks": "data.pull_checks",
    "pulls": "data.pulls",
    "rollout": "inference.rollout",
    "run_figures": "runs.figures",
    "runs.provenance": "io.provenance",
    "safe_load": "io.safe_load",
    "safe_parse": "io.safe_parse",
    "samplers": "inference.samplers",
    "sequential": "inference.sequential",
    "sharding": "inference.sharding",
    "side_files": "data.side_files",
    "sim.direction": "data.direction",
    "small_solve": "sim.small_solve",
    "start_pipeline": "inference.start_pipeline",
    "start_steps": "inference.start_steps",
    "startup": "sim.startup",
    "static": "inference.static",
    "synthetic": "sim.synthetic",
    "synthetic_stem": "tree.stem",
    "temperature": "model.temperature",
    "trajectories": "data.trajectories",
    "trajectory_types": "data.types",
    "tree_checks": "tree.checks",
    "tree_options": "tree.options",
    "tree_types": "tree.types",
    "true_params": "data.true_params",
    "urdf": "tree.urdf",
    "usermodel": "tree.usermodel",
}


def _moved_target(fullname: str) -> str | None:
    """``treeinfer.metrics`` -> ``treeinfer.evaluation.metrics``; also below a moved folder."""
    if not fullname.startswith(__name__ + "."):
        return None
    rest = fullname[len(__name__) + 1 :]
    parts = rest.split(".")
    for k in range(len(parts), 0, -1):
        head = ".".join(parts[:k])
        if head in _MOVED:
            return ".".join([__name__, _MOVED[head], *parts[k:]])
    return None


class _MovedFinder:
    """Loads an old module path as the module that now holds it (same object, one copy)."""

    @staticmethod
    def find_spec(fullname, path=None, target=None):
        # every import in the process passes here first: decide by the name alone, and import
        # nothing before that (importing importlib.util here would look itself up: recursion)
        new = _moved_target(fullname)
        if new is None:
            return None
        import importlib.util

        return importlib.util.spec_from_loader(fullname, _MovedLoader(new))


class _MovedLoader:
    def __init__(self, new: str):
        self.new = new

    def create_module(self, spec):
        import importlib
        import warnings

        warnings.warn(
            f"{spec.name} moved to {self.new} (issue 26); the old path goes in the next release",
            DeprecationWarning,
            stacklevel=3,
        )
        return importlib.import_module(self.new)

    def exec_module(self, module):
        pass  # the module was executed under its new name


if not any(isinstance(f, _MovedFinder) for f in _sys.meta_path):
    _sys.meta_path.insert(0, _MovedFinder())


def __getattr__(name):
    import importlib

    if name in _EXPORTS:
        return getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
    if name in _MODULES:
        return importlib.import_module(f".{name}", __name__)
    if name in _MOVED:  # ti.metrics and the like: the old flat module, through the finder
        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module 'treeinfer' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS) | _MODULES)


def configure_runtime(
    cache_dir: str | None = None,
    *,
    compilation_cache: bool = True,
    gpu_preallocate: bool | None = None,
) -> dict:
    """Set up JAX's runtime as the ``treeinfer`` command does; call it once, before the first
    JAX computation (XLA reads the GPU memory settings when its GPU client starts).

    Args:
      cache_dir: the persistent compilation cache's folder (:func:`enable_compilation_cache`;
        default ``$TREEINFER_JAX_CACHE`` or ``~/.cache/treeinfer/jax``; a user's own
        ``JAX_COMPILATION_CACHE_DIR`` is kept).
      compilation_cache: False leaves JAX's cache settings alone.
      gpu_preallocate: None (default): grow GPU memory on demand
        (``XLA_PYTHON_CLIENT_PREALLOCATE=false``) unless the environment already has one of
        XLA's memory settings; False: grow on demand whatever the environment says; True:
        JAX's own default (reserve 75% of the card at the first transfer).

    Sets environment variables of this process (``JAX_COMPILATION_CACHE_DIR`` and the other
    ``JAX_*`` cache defaults, ``XLA_PYTHON_CLIENT_PREALLOCATE``) and, when JAX is already
    imported, JAX's config. Returns ``{"cache_dir": folder or None, "gpu_preallocate": bool}``
    (what the GPU client will do)."""
    import os

    cache = enable_compilation_cache(cache_dir) if compilation_cache else None
    if gpu_preallocate is None:
        _grow_gpu_memory_on_demand()
    else:
        os.environ["XLA_PYTHON_CLIENT_PREALLOCATE"] = "true" if gpu_preallocate else "false"
    prealloc = os.environ.get("XLA_PYTHON_CLIENT_PREALLOCATE", "true").strip().lower()
    return {"cache_dir": cache, "gpu_preallocate": prealloc not in ("false", "0")}


def _cache_tag() -> str:
    """``treeinfer-<v>_jax-<v>_jaxlib-<v>``: the compiled-program cache folder of this install.

    A reinstall of the same versions, in any folder, maps to the same tag; JAX's own key hashes
    each program with its debug info (source paths) stripped, so the entries stay valid there."""
    return (
        f"treeinfer-{__version__}_jax-{_installed_version('jax')}"
        f"_jaxlib-{_installed_version('jaxlib')}"
    )


def _installed_version(package: str) -> str:
    """``package``'s version without importing it (JAX takes a second to import): the
    ``_version = "..."`` line of its ``version.py``, else the distribution metadata."""
    import importlib.util
    import re
    from pathlib import Path

    try:
        spec = importlib.util.find_spec(package)
        folder = Path(next(iter(spec.submodule_search_locations)))
        found = re.search(
            r'^_version\s*(?::\s*str)?\s*=\s*"([^"]+)"',
            (folder / "version.py").read_text(),
            re.MULTILINE,
        )
        if found:
            return found.group(1)
    except (AttributeError, ImportError, OSError, StopIteration, TypeError, ValueError):
        pass
    from importlib import metadata

    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return "unknown"


_CACHE_OFF = ("", "0", "off", "none", "false", "no")


def enable_compilation_cache(path: str | None = None) -> str | None:
    """Keep compiled XLA programs on disk so the next process with the same shapes skips
    compiling (seconds per program on a small CPU).

    ``path`` defaults to ``$TREEINFER_JAX_CACHE`` or ``~/.cache/treeinfer/jax``; programs go to
    a sub-folder named by :func:`_cache_tag` (treeinfer, jax and jaxlib versions), so an upgrade
    starts a fresh folder and a reinstall of the same versions reuses it.
    ``TREEINFER_JAX_CACHE=off`` turns the cache off (returns None). Every program is cached,
    however short its compile: on a 2-core CPU the many sub-second ones add up.

    Called by the command line and :func:`configure_runtime` (not on ``import treeinfer``).
    When JAX is not imported yet
    this only sets the ``JAX_*`` environment defaults JAX reads at import (no JAX import, so
    ``treeinfer --help`` stays fast); a user's own ``JAX_COMPILATION_CACHE_DIR`` wins."""
    import os
    import sys

    env = os.environ.get("TREEINFER_JAX_CACHE")
    path_given = path is not None
    if path is None and env is not None and env.strip().lower() in _CACHE_OFF:
        return None
    if path is None and env is None and os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        return os.environ["JAX_COMPILATION_CACHE_DIR"]  # the user's own JAX cache
    root = path or env or os.path.join(os.path.expanduser("~"), ".cache", "treeinfer", "jax")
    path = os.path.join(root, _cache_tag())
    try:
        os.makedirs(path, exist_ok=True)
    except OSError:  # a read-only home: run without the cache rather than fail
        return None
    settings = {
        "jax_compilation_cache_dir": path,
        "jax_persistent_cache_min_compile_time_secs": 0.0,
        "jax_persistent_cache_min_entry_size_bytes": 0,
    }
    explicit = path_given or env is not None
    for name, value in settings.items():
        if explicit:
            os.environ[name.upper()] = str(value)
        else:
            os.environ.setdefault(name.upper(), str(value))
    if "jax" in sys.modules:
        import jax

        if explicit or jax.config.jax_compilation_cache_dir is None:
            for name, value in settings.items():
                jax.config.update(name, value)
    return path


# What XLA's GPU client reads, at its start, to size its memory pool; any of them set by the user
# is theirs to keep.
_GPU_MEMORY_SETTINGS = (
    "XLA_PYTHON_CLIENT_PREALLOCATE",
    "XLA_PYTHON_CLIENT_MEM_FRACTION",
    "XLA_CLIENT_MEM_FRACTION",
    "XLA_PYTHON_CLIENT_ALLOCATOR",
)


def _grow_gpu_memory_on_demand() -> bool:
    """Set ``XLA_PYTHON_CLIENT_PREALLOCATE=false`` unless the user set any of the GPU memory
    settings (:data:`_GPU_MEMORY_SETTINGS`); returns whether it set it.

    Why: by default JAX's GPU client reserves 75% of the card's memory in its first transfer,
    and that reservation is most of a cold process's GPU start: 1.4-1.9 s of the first
    ``device_put`` on an H200 (105 GiB), 0.00 s without it (BENCHMARKS.md, issue 15). treeinfer's
    programs need little memory (the standard problem's NNSVGD iteration a few MB; 131k
    parameter sets a few GB) and run the same once the pool has grown. Read by XLA when its GPU
    client starts, so it works as long as no JAX computation has run yet; set
    ``XLA_PYTHON_CLIENT_PREALLOCATE=true`` to keep JAX's reservation. Called by the command
    line and :func:`configure_runtime`."""
    import os

    if any(name in os.environ for name in _GPU_MEMORY_SETTINGS):
        return False
    os.environ["XLA_PYTHON_CLIENT_PREALLOCATE"] = "false"
    return True
