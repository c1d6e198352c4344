"""A softening root plate: the root-soil hinge's moment-rotation curve bends over as the load
grows, the standard behaviour of root plates in tree-pulling tests (the rotational stiffness
falls with the tilt long before the tree fails; practice treats the first quarter degree or so
as linear and extrapolates from there).

The law, in series with the joint's linear spring ``Kp``: the rotation under a moment ``M`` is

    q(M) = (M / Kp) (1 + |M| / M_s),      M_s = Kp theta_s,

a compliance that grows linearly with the moment (a Ramberg-Osgood law of exponent 2, the
simplest smooth softening without a singularity: a load-controlled model never predicts an
infinite tilt inside the band). ``theta_s`` (rad) is the elastic rotation ``M / Kp`` at which
the compliance has doubled; its prior (:data:`SOFT_TILT_PRIOR`, LogUniform) runs from 0.25
deg (strong softening inside the range practice calls linear) to 25 deg (linear over any
tilt these tests record), so that the data choose between a linear and a softening plate.

Quasi-static and first order, like the creep element (:mod:`.creep`): the elastic equilibrium
(:func:`.model.model_response`, gravity's P-Delta included) gives the joint's elastic rotation
``dq = M / Kp``; the extra rotation ``dq |dq| / theta_s`` is added through the tilts'
Jacobian at the rest (it changes the moment arms by a fraction of a degree's worth, which is
dropped). The creep elements stay driven by the moment (``dq``): the softening is a separate
element in series. Tests check the single-hinge case against the closed form of the law.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from .creep import creep_states
from .model import NEWTON_ITERATIONS, PullModel, model_response

__all__ = ["SOFT_TILT_PRIOR", "chain_tilts", "softening_angle"]

SOFT_TILT_PRIOR = (math.radians(0.25), math.radians(25.0))  # rad: theta_s, LogUniform


def softening_angle(dq, theta_s):
    """The softening element's rotation ``dq |dq| / theta_s`` (rad) for elastic rotations
    ``dq`` [..., T] (``M / Kp``) and ``theta_s`` [...] rad (module docstring)."""
    dq = jnp.asarray(dq)
    return dq * jnp.abs(dq) / jnp.asarray(theta_s)[..., None]


def chain_tilts(
    model: PullModel,
    kp,
    forces,
    time,
    *,
    creep=None,
    lag=None,
    soft=None,
    soft_joint: str = "root",
    iterations: int = NEWTON_ITERATIONS,
) -> tuple[jax.Array, jax.Array]:
    """The chain's tilts ``[P, C, T]`` rad and ``stable`` [P] with any of its series elements:
    ``creep`` ``(ratio, tau)`` [P, R] (:func:`.creep.creep_tilts`), ``lag`` ``(ratio, tau,
    joint)`` the fast lag (``joint`` a name and ratio/tau [P], or ``None`` and [P, R]:
    :func:`.creep.lagged_creep_tilts`), ``soft`` ``theta_s`` [P] rad the softening element on
    ``soft_joint``. All elements are driven by each joint's elastic rotation and enter the
    tilts through the Jacobian at the rest."""
    tilts, dq, jac, stable = model_response(model, kp, forces, iterations)
    extra = jnp.zeros_like(dq)  # [P, R, T]
    if creep is not None:
        extra = extra + creep_states(dq, time, *creep)
    if lag is not None:
        ratio, tau, joint = lag
        if joint is None:
            extra = extra + creep_states(dq, time, ratio, tau)
        else:
            j = list(model.joints).index(joint)
            extra = extra.at[:, j].add(creep_states(dq[:, j], time, ratio, tau))
    if soft is not None:
        j = list(model.joints).index(soft_joint)
        extra = extra.at[:, j].add(softening_angle(dq[:, j], soft))
    if creep is None and lag is None and soft is None:
        return tilts, stable
    return tilts + jnp.einsum("pcr,prt->pct", jac, extra), stable
