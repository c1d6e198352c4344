"""What sensors other than the grasp point see: positions and orientations of named points on
the tree along a rollout (issue 30, "observations anywhere").

The rollout is the simulator's own (:func:`treeinfer.sim.fused_backend._pull_one` with
``with_q=True``: the same settle, force and observation timing as :func:`treeinfer.sim.simulate`)
and records the joint angles at every observation; the channels are forward kinematics of those
angles with the fused step's :func:`treeinfer.sim.fused.kinematics` (MuJoCo's own kinematics
written as JAX, so that it runs batched over particles, pulls and samples in one XLA program; it
is checked against MuJoCo C's ``mj_kinematics`` in ``tests/test_observe.py``).

A *feature* is a static description ``(kind, body, local)`` of one sensed point: ``"position"``
gives the world displacement [3] m of the point ``local`` (body frame) from its rest position;
``"angle"`` the rotation vector [3] rad (world axes) of the body's frame from its rest orientation
(``log(R(t) R(0)^T)``); ``"image"`` the point's pixel displacement ``(u, v, 0)`` from its rest
position in a pinhole camera (``u = fx x_c / z_c + cx``, ``v = fy y_c / z_c + cy``). Row 0 of
every rollout is the rest pose, so all are 0 there.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ConfigError
from . import fused as hd
from .simulator import Simulator


class Feature(NamedTuple):
    """A sensed point: ``kind`` ``"position"`` | ``"angle"`` | ``"image"``, MuJoCo ``body``
    index, ``local`` [3] m in the body's frame, ``camera`` (image: the 16 floats of
    :func:`treeinfer.data.channels.parse_camera`); floats, hashable, static under jit."""

    kind: str
    body: int
    local: tuple[float, float, float]
    camera: tuple = ()


def feature_for(
    sim: Simulator, kind: str, link: str, fraction: float, camera: tuple = ()
) -> Feature:
    """The :class:`Feature` of a point at ``fraction`` of ``link``'s axis."""
    if sim.hinge_tree is None:
        raise ConfigError(
            "observation channels: need the fused (or pallas) backend's hinge-tree model; this "
            f"simulator uses {sim.backend!r}: pass --backend fused (backend='fused') with a tree "
            "file treeinfer builds (a user MJCF/URDF model, --model-file, is not covered: leave "
            "channels.yaml out of its data folder)"
        )
    if link not in sim.branches:
        raise ConfigError(
            f"observation channel: unknown link '{link}'; the model has: {', '.join(sim.branches)}"
        )
    body, length = sim.branches[link]
    local = np.asarray(sim.branch_point(int(body), float(length), float(fraction)), float)
    return Feature(kind, int(body), tuple(float(x) for x in local), tuple(camera))


def _array(elems, shape, dtype) -> jax.Array:
    """A vector (tuple of elements: floats or arrays of ``shape``) as ``shape + [3]``, a matrix
    (tuple of rows) as ``shape + [3, 3]``."""
    if isinstance(elems[0], tuple):
        return jnp.stack([_array(row, shape, dtype) for row in elems], axis=-2)
    return jnp.stack([jnp.broadcast_to(jnp.asarray(e, dtype), shape) for e in elems], axis=-1)


def rotation_vector(r: jax.Array) -> jax.Array:
    """``[..., 3]`` rotation vectors (axis * angle, rad) of rotation matrices ``r [..., 3, 3]``:
    the matrix logarithm, stable at small angles (where it is the skew part). Written here
    because jax has no batched rotation log; checked against scipy's ``Rotation.as_rotvec``."""
    v = 0.5 * jnp.stack(
        [r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]],
        axis=-1,
    )  # sin(angle) * axis
    s = jnp.linalg.norm(v, axis=-1)
    c = 0.5 * (r[..., 0, 0] + r[..., 1, 1] + r[..., 2, 2] - 1.0)
    angle = jnp.arctan2(s, c)
    safe = jnp.where(s > 1e-12, s, 1.0)
    scale = jnp.where(s > 1e-12, angle / safe, 1.0)  # angle / sin(angle) -> 1
    return v * scale[..., None]


def features_from_q(sim: Simulator, q: jax.Array, features: tuple[Feature, ...]) -> jax.Array:
    """``[..., T, F, 3]`` channel values for joint angles ``q [..., T, nq]`` (row 0: rest)."""
    t = sim.hinge_tree
    q = jnp.asarray(q)  # a NumPy float64 q: JAX's own float type (float32 without x64), no warning
    shape = q.shape[:-1]
    dtype = q.dtype
    kin = hd.kinematics(t, [q[..., i] for i in range(t.nv)])
    out = []
    for f in features:
        if f.kind == "position":
            p = _array(hd.point(kin, f.body, f.local), shape, dtype)  # [..., T, 3]
            out.append(p - p[..., :1, :])
        elif f.kind == "image":  # pinhole projection, pixels from the rest pose's
            p = _array(hd.point(kin, f.body, f.local), shape, dtype)
            c = np.asarray(f.camera, float)
            rot, centre = jnp.asarray(c[4:13].reshape(3, 3), dtype), jnp.asarray(c[13:16], dtype)
            pc = jnp.einsum("ij,...j->...i", rot, p - centre)
            uv = jnp.stack(
                [c[0] * pc[..., 0] / pc[..., 2] + c[2], c[1] * pc[..., 1] / pc[..., 2] + c[3]], -1
            )
            uv = uv - uv[..., :1, :]
            out.append(jnp.concatenate([uv, jnp.zeros_like(uv[..., :1])], axis=-1))
        elif f.kind == "angle":
            r = _array(kin.rot[f.body], shape, dtype)  # [..., T, 3, 3]
            rel = jnp.einsum("...ij,...kj->...ik", r, r[..., :1, :, :])
            out.append(rotation_vector(rel))
        else:
            raise ConfigError(f"observation channel: unknown kind {f.kind!r}")
    return jnp.stack(out, axis=-2)


class ChannelRollout(NamedTuple):
    """``tau`` [P, B, T] m (the grasp point, as :class:`treeinfer.sim.Rollout`), ``features``
    [P, B, T, F, 3] (:func:`features_from_q`), ``stable`` [P, B]; zero where unstable."""

    tau: jax.Array
    features: jax.Array
    stable: jax.Array


def simulate_features(
    sim: Simulator,
    kp,
    kd,
    forces,
    features: tuple[Feature, ...],
    grasp_fraction=None,
    direction=None,
) -> ChannelRollout:
    """Roll out P parameter sets ``kp, kd [P, R]`` under ``forces [B, T]`` (as
    :func:`treeinfer.sim.simulate`, on the tree's grasped branch; ``grasp_fraction`` None, a
    scalar or [B]; ``direction`` None, [3] or [B, 3]) and return the grasp point's displacement
    and the ``features`` at every observation."""
    if sim.hinge_tree is None:
        raise ConfigError(
            "observation channels: need the fused (or pallas) backend: pass --backend fused "
            "(backend='fused') with a tree file treeinfer builds"
        )
    return _simulate_features(sim, tuple(features), kp, kd, forces, grasp_fraction, direction)


@functools.partial(jax.jit, static_argnums=(0, 1))
def _simulate_features(sim, features, kp, kd, forces, grasp_fraction, direction):
    from . import fused_backend as fb

    kp, kd, forces = jnp.atleast_2d(kp), jnp.atleast_2d(kd), jnp.atleast_2d(forces)
    dtype = sim.dtype
    n = forces.shape[0]
    frac = sim.grasp_fraction if grasp_fraction is None else grasp_fraction
    frac = jnp.broadcast_to(jnp.asarray(frac, dtype), (n,))
    site = sim.grasp_point(frac)  # [B, 3] in the grasped body's frame
    if grasp_fraction is None:  # the model's own grasp site (a user model may place it off-axis)
        site = jnp.broadcast_to(jnp.asarray(sim.mj_model.site_pos[sim.grasp_site], dtype), (n, 3))
    dirs = None
    if direction is not None:
        dirs = jnp.broadcast_to(jnp.asarray(direction, dtype), (n, 3))
        dirs = dirs / jnp.linalg.norm(dirs, axis=-1, keepdims=True)

    def per_params(kp_i, kd_i):
        (kp_c, kd_c), q_rest, settled = fb._prepare(sim, kp_i, kd_i, dtype)

        def pull(f, s, d):
            return fb._pull_one(sim, kp_c, kd_c, q_rest, f, s, direction=d, with_q=True)

        if dirs is None:
            tau, ok, q = jax.vmap(lambda f, s: pull(f, s, None))(forces.astype(dtype), site)
        else:
            tau, ok, q = jax.vmap(pull)(forces.astype(dtype), site, dirs)
        return tau, q, ok & settled

    tau, q, ok = jax.vmap(per_params)(kp, kd)  # [P, B, T], [P, B, T, nq], [P, B]
    feats = features_from_q(sim, q, features)
    ok = ok & jnp.all(jnp.isfinite(feats), axis=(-3, -2, -1))
    tau = jnp.where(ok[..., None], tau, 0.0)
    feats = jnp.where(ok[..., None, None, None], feats, 0.0)
    return ChannelRollout(tau, feats, ok)


def simulate_features_at(
    sim: Simulator, kp, kd, forces, features: tuple[Feature, ...], sites, dirs, body: int
) -> ChannelRollout:
    """:func:`simulate_features` for pulls on any ``body`` (MuJoCo index; the grasped branch's
    or another), at ``sites [B, 3]`` in that body's frame along unit ``dirs [B, 3]`` (world):
    the per-pull branches of :class:`treeinfer.inference.static.Model` (grouped by body by
    :func:`treeinfer.inference.static.channels.model_features`)."""
    if sim.hinge_tree is None:
        raise ConfigError(
            "observation channels: need the fused (or pallas) backend: pass --backend fused "
            "(backend='fused') with a tree file treeinfer builds"
        )
    return _simulate_features_at(sim, tuple(features), int(body), kp, kd, forces, sites, dirs)


@functools.partial(jax.jit, static_argnums=(0, 1, 2))
def _simulate_features_at(sim, features, body, kp, kd, forces, sites, dirs):
    from . import fused_backend as fb

    dtype = sim.dtype
    kp, kd, forces = jnp.atleast_2d(kp), jnp.atleast_2d(kd), jnp.atleast_2d(forces)
    sites, dirs = jnp.asarray(sites, dtype), jnp.asarray(dirs, dtype)

    def per_params(kp_i, kd_i):
        (kp_c, kd_c), q_rest, settled = fb._prepare(sim, kp_i, kd_i, dtype)

        def pull(f, s, d):
            return fb._pull_one(sim, kp_c, kd_c, q_rest, f, s, direction=d, body=body, with_q=True)

        tau, ok, q = jax.vmap(pull)(forces.astype(dtype), sites, dirs)
        return tau, q, ok & settled

    tau, q, ok = jax.vmap(per_params)(kp, kd)
    feats = features_from_q(sim, q, features)
    ok = ok & jnp.all(jnp.isfinite(feats), axis=(-3, -2, -1))
    tau = jnp.where(ok[..., None], tau, 0.0)
    feats = jnp.where(ok[..., None, None, None], feats, 0.0)
    return ChannelRollout(tau, feats, ok)


class ChannelSpec(NamedTuple):
    """A synthetic sensor for :func:`synthetic_channels`: ``kind`` (``"position"`` |
    ``"angle"``) at ``fraction`` of ``link``, measuring world ``components`` (``"xz"``), with
    white Gaussian noise ``noise`` (m or rad; 0: none)."""

    kind: str
    link: str
    fraction: float
    components: str = "xyz"
    noise: float = 0.0

    @classmethod
    def parse(cls, text: str) -> ChannelSpec:
        """``KIND:LINK:FRACTION[:AXES[:NOISE]]``, e.g. ``position:child:0.5:xz:0.001``."""
        parts = text.split(":")
        if not 3 <= len(parts) <= 5:
            raise ConfigError(
                f"--channel {text!r}: expected KIND:LINK:FRACTION[:AXES[:NOISE]], e.g. "
                "position:child:0.5:xz:0.001 (noise in m, or rad for an angle)"
            )
        kind, link = parts[0], parts[1]
        if kind not in ("position", "angle"):
            raise ConfigError(f"--channel {text!r}: KIND must be position or angle, got {kind!r}")
        try:
            frac = float(parts[2])
            noise = float(parts[4]) if len(parts) > 4 else 0.0
        except ValueError:
            raise ConfigError(f"--channel {text!r}: FRACTION and NOISE must be numbers") from None
        axes = parts[3] if len(parts) > 3 else ("xyz" if kind == "position" else "y")
        if not (0.0 <= frac <= 1.0) or noise < 0 or not axes or set(axes) - set("xyz"):
            raise ConfigError(
                f"--channel {text!r}: FRACTION in [0, 1], AXES among x, y, z, NOISE >= 0"
            )
        return cls(kind, link, frac, axes, noise)


def synthetic_channels(sim, kp, kd, forces, recordings, specs, rng, t0: float = 0.0) -> tuple:
    """Simulated channels (:class:`treeinfer.data.channels.Channel`, noise ``"auto"``) of every
    ``specs`` sensor on every pull ``forces [B, T]`` (file names ``recordings``) at the true
    gains ``kp, kd [R]``, sampled on the pulls' grid, with each spec's noise from ``rng``."""
    from ..data.channels import Channel, NamedPoint

    feats = tuple(
        feature_for(sim, s.kind, s.link, s.fraction) for s in specs
    )  # one per spec (repeats are harmless)
    ro = simulate_features(sim, np.atleast_2d(kp), np.atleast_2d(kd), forces, feats)
    values = np.asarray(ro.features[0], float)  # [B, T, F, 3]
    t = t0 + np.arange(values.shape[1]) * sim.obs_dt
    out = []
    for j, s in enumerate(specs):
        axes = ["xyz".index(c) for c in s.components]
        for b, rec in enumerate(recordings):
            v = values[b, :, j][:, axes]
            v = v + rng.normal(0.0, s.noise, v.shape) if s.noise > 0 else v
            name = f"{s.kind}_{s.link}_{s.fraction:g}_{b:03d}"
            point = NamedPoint(s.link, fraction=float(s.fraction))
            sensor = f"{s.kind}_{s.link}_{s.fraction:g}"  # one noise scale over the pulls
            out.append(Channel(name, s.kind, rec, point, tuple(s.components), t, v, sensor=sensor))
    return tuple(out)
