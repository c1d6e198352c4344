"""Observation channels (markers, inclinometers: :mod:`treeinfer.model.channels`) for any
:class:`~treeinfer.inference.static.Model`: the paper's dynamic rollout, the dynamic rollout
along each pull's direction on each pull's branch, and the static model's equilibria."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ...model.gains import gains_from_theta
from ...sim.observe import simulate_features


def model_features(sim, model, theta, forces, features, grasp_fraction=None):
    """``(features [P, B, T, F, 3], stable [P, B])`` of particles ``theta [P, >= D]`` (the
    model's gain columns first) under ``forces [B, T]`` for any
    :class:`treeinfer.inference.static.Model`: None (the paper's dynamic model), the dynamic
    model with its pulls' directions and branches (one compiled group per pulled branch, as the
    static solver groups them), or the static model, whose channels are the kinematics of each
    force sample's equilibrium (:func:`treeinfer.inference.static.static_equilibria`) measured
    from the gravity-settled rest, as a rollout's are from its first row."""
    theta = jnp.atleast_2d(jnp.asarray(theta))
    if model is None:
        kp, kd = gains_from_theta(theta, sim.n_joints)
        ro = simulate_features(sim, kp, kd, forces, features, grasp_fraction)
        return ro.features, ro.stable
    kp, kd = model.layout.gains(theta[:, : model.layout.dim])
    branch = model.grasp_branch
    branch = tuple(branch) if branch is not None and not isinstance(branch, str) else branch
    if model.kind == "static":
        from ...sim.observe import features_from_q
        from .equilibrium import static_equilibria

        eq = static_equilibria(sim, kp, forces, grasp_fraction, model.direction, branch, model.tree)
        q = jnp.asarray(eq.q)
        rest = jnp.broadcast_to(eq.q_rest[:, None, None, :], q.shape[:2] + (1, q.shape[-1]))
        feats = features_from_q(sim, jnp.concatenate([rest, q], axis=2), tuple(features))
        feats = feats[:, :, 1:]
        ok = eq.stable & jnp.all(jnp.isfinite(feats), axis=(-3, -2, -1))
        return jnp.where(ok[..., None, None, None], feats, 0.0), ok
    from ...sim.observe import simulate_features_at
    from .equilibrium import _profile_geometry

    kp, forces, bodies, sites, dirs = _profile_geometry(
        sim, kp, forces, grasp_fraction, model.direction, branch, model.tree
    )
    p, (b, n) = kp.shape[0], forces.shape
    feats = jnp.zeros((p, b, n, len(features), 3), kp.dtype)
    ok = jnp.zeros((p, b), bool)
    for body in sorted(set(bodies)):  # one compiled program per pulled branch
        idx = np.asarray([i for i, x in enumerate(bodies) if x == body])
        ro = simulate_features_at(
            sim, kp, kd.astype(kp.dtype), forces[idx], features, sites[idx], dirs[idx], body
        )
        feats = feats.at[:, idx].set(ro.features)
        ok = ok.at[:, idx].set(ro.stable)
    return feats, ok


def channel_rollout(sim, model, forces, features, grasp_fraction=None):
    """``gains [N, D] -> (features, stable)``: :func:`model_features` on fixed pulls, the
    ``features`` argument of :func:`treeinfer.model.channels.with_channels`."""
    forces = jnp.asarray(forces, sim.dtype)

    def rollout(gains):
        return model_features(sim, model, gains, forces, features, grasp_fraction)

    return rollout
