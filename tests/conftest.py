"""Shared test configuration.

MJX programs take tens of seconds to compile on a small CPU, and several tests build the same
program (same shapes, new closures). The persistent compilation cache turns those repeats into
fast loads.
"""

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import treeinfer  # noqa: E402

treeinfer.enable_compilation_cache()


def pytest_collection_modifyitems(config, items):
    """Skip ``@pytest.mark.gpu`` tests, with the reason, when JAX sees no GPU (they are left out
    of the default run anyway; ``-m gpu`` selects them on a GPU machine)."""
    if not any(item.get_closest_marker("gpu") for item in items):
        return
    import jax

    if any(d.platform == "gpu" for d in jax.devices()):
        return
    import pytest

    skip = pytest.mark.skip(reason="needs a GPU (JAX sees none; JAX_PLATFORMS=cpu by default here)")
    for item in items:
        if item.get_closest_marker("gpu"):
            item.add_marker(skip)
