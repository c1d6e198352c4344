"""How the Pallas backend (:mod:`treeinfer.sim.pallas`) lays rollouts out for its kernel and
back: :func:`_prepare` settles the P parameter sets (the fused backend's Newton solve) and packs
every (parameter set, force profile) pair into one column of ``[K, P * B]`` row arrays
(:func:`_rows`; :func:`_pad` pads the columns to whole kernel blocks), and :func:`_finish` turns
the kernel's rows back into a :class:`~treeinfer.sim.Rollout`.

Separate from the kernel (:mod:`treeinfer.sim.pallas_kernel`) and the dispatch
(:mod:`treeinfer.sim.pallas`) because it is plain JAX on whole arrays, outside the kernel, shared
by the value and the tangent paths (issue 26). :mod:`treeinfer.sim.pallas` re-exports every
name (they lived there before the split).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def _rows(x, n_profiles: int):
    """[P, K] per particle -> [K, P * B] per rollout row (row = particle * B + profile)."""
    return jnp.repeat(x, n_profiles, axis=0).T


def _pad(x, n: int):
    """Pad the last axis to ``n`` by repeating its first column (finite, discarded later)."""
    extra = n - x.shape[-1]
    if extra == 0:
        return x
    return jnp.concatenate([x, jnp.broadcast_to(x[..., :1], x.shape[:-1] + (extra,))], axis=-1)


def _prepare(sim, kp, kd, forces, grasp_fraction, direction):
    """Settle P parameter sets (fused backend's Newton solve) and lay out rollout rows."""
    from .fused_backend import _prepare as _fused_prepare

    dtype = sim.dtype
    kp, kd = jnp.atleast_2d(kp).astype(dtype), jnp.atleast_2d(kd).astype(dtype)
    forces = jnp.atleast_2d(forces).astype(dtype)
    n_profiles = forces.shape[0]

    def settle(a, b):
        _, q, ok = _fused_prepare(sim, a, b, dtype)
        return q, ok

    q_rest, settled = jax.vmap(settle)(kp, kd)
    if grasp_fraction is None:
        site = jnp.broadcast_to(
            jnp.asarray(sim.mj_model.site_pos[sim.grasp_site], dtype), (n_profiles, 3)
        )
    else:
        frac = jnp.broadcast_to(jnp.asarray(grasp_fraction, dtype), (n_profiles,))
        length = float(np.linalg.norm(sim.grasp_end - sim.grasp_start))
        site = sim.branch_point(None, length, frac)
    dirs = None
    if direction is not None:
        dirs = jnp.broadcast_to(jnp.asarray(direction, dtype), (n_profiles, 3))
        dirs = dirs / jnp.linalg.norm(dirs, axis=-1, keepdims=True)
    n_particles = kp.shape[0]
    tile = lambda x: jnp.tile(x, (n_particles, 1)).T  # [B, K] -> [K, P * B]
    from .forcing import next_samples

    rows = {
        "kp": _rows(kp, n_profiles),
        "kd": _rows(kd, n_profiles),
        "q_rest": _rows(q_rest, n_profiles),
        "site": tile(site),
        "dirs": None if dirs is None else tile(dirs),
        "f": tile(forces),
        "fn": tile(jax.vmap(next_samples)(forces)),
    }
    return rows, q_rest, settled, (n_particles, n_profiles, forces.shape[1])


def _finish(sim, tau_rows, ok_rows, settled, shape):
    from . import Rollout, velocity

    n_particles, n_profiles, n_steps = shape
    tau = tau_rows.T.reshape(n_particles, n_profiles, n_steps)
    ok = (ok_rows.reshape(n_particles, n_profiles) > 0.5) & settled[:, None]
    tau = jnp.where(ok[..., None], tau, 0.0)
    tau_dot = jnp.where(ok[..., None], velocity(tau, sim.obs_dt), 0.0)
    return Rollout(tau=tau, tau_dot=tau_dot, stable=ok)
