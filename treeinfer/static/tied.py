"""A one-parameter stiffness layout: every inferred joint's Kp a fixed multiple of one scale.

For a tapered stem modelled as a chain of hinges, a beam segment of length ``l`` at height
``z`` bends like a hinge of stiffness ``E I(z) / l``; with E unknown but the taper known, the
hinges' stiffnesses are tied, ``Kp_j = s * shape_j``, and only the scale ``s`` is inferred
(``theta = [log s]``, plus noise columns). Two push heights identify one scale where they cannot
identify three free stiffnesses.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from ..errors import ConfigError


class TiedLayout(NamedTuple):
    """``Kp_j = exp(theta[0]) * shape[j]`` N m/rad; damping held at ``fixed_kd`` [R].

    Duck-types :class:`~treeinfer.static.ParameterLayout` (``dim``, ``labels``, ``gains``,
    ``full_theta``, ``lower``/``upper`` in log units of the scale)."""

    joints: tuple[str, ...]
    shape: np.ndarray  # [R] dimensionless, Kp_j / s
    fixed_kd: np.ndarray  # [R] N m s/rad
    lower: np.ndarray  # [1] log of the scale's prior box
    upper: np.ndarray  # [1]
    parameters: tuple[str, ...] = ("kp",)
    label: str = "Kp_scale"

    @property
    def n_joints(self) -> int:
        return len(self.joints)

    @property
    def dim(self) -> int:
        return 1

    @property
    def infers_damping(self) -> bool:
        return False

    @property
    def labels(self) -> list[str]:
        return [self.label]

    def gains(self, theta):
        """``theta [..., 1+]`` -> (Kp [..., R], Kd [..., R]) in natural units (jax)."""
        kp = jnp.exp(theta[..., :1]) * jnp.asarray(self.shape, theta.dtype)
        kd = jnp.broadcast_to(jnp.asarray(self.fixed_kd, kp.dtype), kp.shape)
        return kp, kd

    def full_theta(self, theta):
        """``[..., 1]`` -> ``[..., 2R]`` (log Kp, log Kd)."""
        kp, kd = self.gains(theta)
        return jnp.concatenate([jnp.log(kp), jnp.log(kd)], axis=-1)


def tied_layout(tree, shape, scale_bounds, fixed_kd=None) -> TiedLayout:
    """:class:`TiedLayout` for ``tree``'s inferred joints.

    Args:
        shape: [R] positive relative stiffnesses (``Kp_j = s * shape_j``), order
            ``tree.inferred``.
        scale_bounds: (low, high) prior box of the scale s (log-uniform inside).
        fixed_kd: [R] or scalar N m s/rad (default the geometric mean of each Kd box).
    """
    joints = tuple(tree.inferred)
    shape = np.asarray(shape, float).reshape(-1)
    if shape.shape != (len(joints),) or not np.all(np.isfinite(shape)) or np.any(shape <= 0):
        raise ConfigError(f"shape: expected {len(joints)} positive numbers, got {shape.tolist()}")
    lo, hi = (float(v) for v in scale_bounds)
    if not (0 < lo < hi < np.inf):
        raise ConfigError(f"scale_bounds: expected 0 < low < high, got {scale_bounds!r}")
    if fixed_kd is None:
        kd = np.asarray([tree.bounds[n].kd for n in joints], float)
        fixed = np.sqrt(kd[:, 0] * kd[:, 1])
    else:
        fixed = np.broadcast_to(np.asarray(fixed_kd, float), (len(joints),)).copy()
    return TiedLayout(joints, shape, fixed, np.log([lo]), np.log([hi]))
