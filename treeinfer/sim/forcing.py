"""The force between samples, shared by every backend (and mirrored by the C reference).

Sample ``k`` of a profile is the force at ``t_k = k * obs_dt``. Simulation substep ``j`` of
observation interval ``k`` starts at ``t_k + j * obs_dt / substeps`` and applies the force at
that time: under the first-order hold (``force_interp="linear"``)
``f_k + (j / substeps) (f_{k+1} - f_k)``, under the zero-order hold (``"hold"``) ``f_k``.
After the last sample the force stays at its value (``f_{T} := f_{T-1}``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def force_fraction(force_interp: str, k, n_sub, dtype):
    """Weight of the next sample in substep ``k`` of ``n_sub``: ``k / n_sub`` under the
    first-order hold, 0 under the zero-order hold (a Python 0.0 that folds away)."""
    if force_interp == "hold":
        return 0.0
    return jnp.asarray(k, dtype) / jnp.asarray(n_sub, dtype)


def next_samples(forces: jax.Array) -> jax.Array:
    """[T] sample k + 1 for every k of ``forces`` [T]; the last one repeats."""
    return jnp.concatenate([forces[1:], forces[-1:]])
