"""treeinfer: learn how tree branches bend when a robot pulls on them."""

__version__ = "0.1.0"


def enable_compilation_cache(path: str | None = None) -> str:
    """Keep compiled XLA programs on disk so a second run (or test session) skips MJX's
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
