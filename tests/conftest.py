"""Shared test configuration.

MJX programs take tens of seconds to compile on a small CPU, and several tests build the same
program (same shapes, new closures). The persistent compilation cache turns those repeats into
fast loads.
"""

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import treeinfer  # noqa: E402

treeinfer.enable_compilation_cache()
