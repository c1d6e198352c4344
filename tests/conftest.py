"""Shared test configuration.

MJX programs take tens of seconds to compile on a small CPU, and several tests build the same
program (same shapes, new closures). The persistent compilation cache turns those repeats into
fast loads.
"""

import contextlib
import io
import os

import pytest

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


@pytest.fixture(scope="session")
def demo_quick(tmp_path_factory):
    """``treeinfer demo --quick`` with the paper's loss and the Laplace start (test_cli_infer's
    ``SAMPLER_RUN``: the sampler runs its iterations, which its run-folder tests read):
    (folder, its stdout). One run for the session: test_cli_infer reads its run and output, and
    test_cli_noise and test_force_noise_cli take its noise-free pulls (the data depend on the
    seed and the sizes only), which each made with a demo of their own before."""
    from treeinfer.cli import main

    out = tmp_path_factory.mktemp("demo") / "demo"
    buf, err = io.StringIO(), io.StringIO()
    argv = ["demo", "--quick", "--out", str(out), "--no-progress"]
    argv += ["--likelihood", "boltzmann", "--init", "laplace"]
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(err):
        rc = main(argv)
    assert rc == 0, err.getvalue()
    return out, buf.getvalue()
