"""Creep: a quasi-static viscoelastic joint (standard linear solid) for slow pulling tests.

Each inferred joint is its elastic spring ``Kp`` in series with a Kelvin-Voigt creep element
(a spring ``K2`` parallel to a dashpot ``eta``): the moment ``M`` through both is the same, so
the joint's deflection is ``q = q_e + q_c`` with ``Kp q_e = M`` and ``K2 q_c + eta dq_c/dt = M``.
With the creep ratio ``c = Kp / K2`` (the long-term extra compliance as a fraction of the
elastic one) and the relaxation time ``tau = eta / K2``,

    dq_c/dt = (c q_e(t) - q_c) / tau

driven by the elastic deflection ``q_e`` (= ``M / Kp``). Its creep compliance is the standard
linear solid's, ``J(t) = [1 + c (1 - exp(-t / tau))] / Kp``: a step of moment gives the elastic
tilt at once and creeps to ``(1 + c)`` times it; on release the tilt drops by the elastic part
and the rest recovers with ``tau`` (the lag and the residual tilt of the recordings).

Quasi-static: no inertia (a pull lasts minutes, the tree's periods are seconds). The moment
comes from the elastic equilibrium under the recorded force (:func:`.model.model_response`,
gravity's P-Delta included); the extra tilt from creep is the creep angles times the tilts'
derivative at the rest (it changes the moment arms by a fraction of a degree's worth, which is
dropped). The tree is at rest (creep relaxed) when the record starts.

A fast lag on the root plate (:func:`lagged_creep_tilts`): a second Kelvin-Voigt element in
series on one joint (the root hinge), with its own ratio and a time constant of a fraction of a
second to seconds (:data:`LAG_TAU_PRIOR`), the slow creep element then restricted to
relaxation times beyond it (:data:`SLOW_TAU_PRIOR`) so that the two cannot swap. With one
element per joint the root's creep sat at its prior's edge (ratio 3, 1-2 s) modelling the
lag of the reading behind the winch's steps (the root plate's quick viscous response and the
inclinometer's own filtering) and left the slow creep of the hold unmodelled
(``docs/pulling_tests.md``); the root joint's compliance is then the generalised Kelvin
solid's, ``J(t) = [1 + c_f (1 - exp(-t/tau_f)) + c (1 - exp(-t/tau))] / Kp``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .model import NEWTON_ITERATIONS, PullModel, model_response

__all__ = [
    "CREEP_RATIO_PRIOR",
    "CREEP_TAU_PRIOR",
    "LAG_RATIO_PRIOR",
    "LAG_TAU_PRIOR",
    "SLOW_TAU_PRIOR",
    "creep_states",
    "creep_tilts",
    "lagged_creep_tilts",
]

CREEP_RATIO_PRIOR = (1.0e-3, 3.0)  # c = Kp / K2: LogUniform (from no creep to 3x the elastic)
CREEP_TAU_PRIOR = (
    1.0,
    1000.0,
)  # s: LogUniform; below 1 s creep is a softer spring (ramps: minutes)
# the fast lag element (LogUniform, s): the readings are 0.08-0.27 s apart, the winch's steps a
# few seconds; below 0.05 s a lag is a softer spring at these rates
LAG_TAU_PRIOR = (0.05, 5.0)
LAG_RATIO_PRIOR = CREEP_RATIO_PRIOR  # its ratio (LogUniform): as the slow element's
SLOW_TAU_PRIOR = (5.0, 1000.0)  # s: the slow creep's relaxation time beside a fast lag


def creep_states(drive, time, ratio, tau):
    """The creep angles ``q_c`` [..., R, T] of ``dq_c/dt = (ratio * drive - q_c) / tau`` from
    ``q_c = 0`` at ``time[0]``: ``drive`` [..., R, T] (the elastic deflection), ``time`` [T] s
    (irregular steps are fine), ``ratio`` and ``tau`` [..., R].

    Written out rather than by an ODE library because the update is exact: with the drive
    linear between samples (first-order hold), over a step ``h = dt / tau``, ``e = exp(-h)``,
    ``g = (1 - e) / h``,

        q_c[n+1] = e q_c[n] + u[n] (g - e) + u[n+1] (1 - g),   u = ratio * drive,

    one ``lax.scan`` over T, differentiable, with no step-size error to tune."""
    time = jnp.asarray(time)
    u = jnp.moveaxis(jnp.asarray(ratio)[..., None] * jnp.asarray(drive), -1, 0)  # [T, ..., R]
    tau = jnp.asarray(tau)
    dt = jnp.diff(time)

    def step(x, inp):
        d, u0, u1 = inp
        h = d / tau
        e = jnp.exp(-h)
        g = -jnp.expm1(-h) / h
        x = e * x + u0 * (g - e) + u1 * (1.0 - g)
        return x, x

    x0 = jnp.zeros_like(u[0])
    _, xs = jax.lax.scan(step, x0, (dt, u[:-1], u[1:]))
    return jnp.moveaxis(jnp.concatenate([x0[None], xs]), 0, -1)


def creep_tilts(
    model: PullModel, kp, ratio, tau, forces, time, iterations: int = NEWTON_ITERATIONS
) -> tuple[jax.Array, jax.Array]:
    """The viscoelastic chain's tilts ``[P, C, T]`` rad and ``stable`` [P] under ``forces`` [T]
    N recorded at ``time`` [T] s: ``kp``, ``ratio`` and ``tau`` [P, R] in the order of
    ``model.joints``. The elastic tilts plus the creep angles through the tilts' Jacobian."""
    tilts, dq, jac, stable = model_response(model, kp, forces, iterations)
    qc = creep_states(dq, time, ratio, tau)  # [P, R, T]
    return tilts + jnp.einsum("pcr,prt->pct", jac, qc), stable


def lagged_creep_tilts(
    model: PullModel,
    kp,
    ratio,
    tau,
    lag_ratio,
    lag_tau,
    forces,
    time,
    joint: str = "root",
    iterations: int = NEWTON_ITERATIONS,
) -> tuple[jax.Array, jax.Array]:
    """:func:`creep_tilts` with a fast lag element on ``joint`` (module docstring):
    ``lag_ratio`` and ``lag_tau`` [P] its ratio and time constant (s), driven, as the slow
    element, by the joint's elastic deflection; ``joint=None``: one on every joint
    (``lag_ratio`` and ``lag_tau`` [P, R])."""
    tilts, dq, jac, stable = model_response(model, kp, forces, iterations)
    qc = creep_states(dq, time, ratio, tau)  # [P, R, T]
    if joint is None:
        qf = creep_states(dq, time, lag_ratio, lag_tau)  # [P, R, T]
        return tilts + jnp.einsum("pcr,prt->pct", jac, qc + qf), stable
    j = list(model.joints).index(joint)
    qf = creep_states(dq[:, j], time, lag_ratio, lag_tau)  # [P, T]
    out = tilts + jnp.einsum("pcr,prt->pct", jac, qc) + jac[:, :, j, None] * qf[:, None, :]
    return out, stable
