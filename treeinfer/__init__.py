"""treeinfer: learn how tree branches bend when a robot pulls on them."""

__version__ = "0.1.0"

# The public API, imported lazily so `treeinfer --help` does not pay for JAX and MuJoCo.
_EXPORTS = {
    "load_tree": "tree", "dump_tree": "tree", "make_tree": "tree", "Tree": "tree", "Branch": "tree",
    "Bounds": "tree",
    "Trajectory": "trajectories", "read_trajectory": "trajectories",
    "read_trajectory_dir": "trajectories", "write_trajectory": "trajectories",
    "stack_trajectories": "trajectories",
    "make_simulator": "sim", "simulate": "sim", "Rollout": "sim",
    "make_problem": "inference", "infer": "inference", "predict": "inference",
    "Problem": "inference", "Posterior": "inference",
    "example_path": "examples",
}
_MODULES = {
    "tree", "generators", "export", "urdf", "sim", "likelihood", "priors", "gradients",
    "samplers", "inference", "metrics", "plots", "diagnostics", "trajectories", "bags", "forces",
    "errors", "examples", "sharding", "runs",
}


def __getattr__(name):
    import importlib

    if name in _EXPORTS:
        return getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
    if name in _MODULES:
        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module 'treeinfer' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS) | _MODULES)


def enable_compilation_cache(path: str | None = None) -> str:
    """Keep compiled XLA programs on disk so a second run (or test session) skips the simulator's
    long compile. ``path`` defaults to ``$TREEINFER_JAX_CACHE`` or ``~/.cache/treeinfer/jax``."""
    import os

    import jax

    path = path or os.environ.get("TREEINFER_JAX_CACHE") or os.path.join(
        os.path.expanduser("~"), ".cache", "treeinfer", "jax"
    )
    os.makedirs(path, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path
