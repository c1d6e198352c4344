"""When are data quasi-static: natural periods of the settled tree against the sample interval."""

from __future__ import annotations

import math

import numpy as np

from ...sim import Simulator

QUASI_STATIC_RATIO = 5.0  # sample interval / slowest natural period above which data are static


def natural_periods(sim: Simulator, kp) -> np.ndarray:
    """Natural periods (s, longest first) of small oscillations about the gravity-settled rest.

    Linearised in MuJoCo C (float64): stiffness ``K = -d(qfrc_passive - qfrc_bias)/dq`` (so
    gravity's stiffening or softening counts) and mass matrix ``M`` at the rest pose; periods
    ``2 pi / omega`` from ``K v = omega^2 M v``. Modes with ``omega^2 <= 0`` (unstable) are
    reported as ``inf``.

    Args:
        kp: [R] N m/rad for the inferred joints.
    """
    import copy

    import mujoco

    from ...sim.reference import settle_reference

    m = copy.deepcopy(sim.mj_model)
    for j, k in zip(sim.joint_ids, np.asarray(kp, float).reshape(-1)):
        m.jnt_stiffness[j] = k
    q = settle_reference(m)
    d = mujoco.MjData(m)

    def torque(qq):
        d.qpos[:] = qq
        d.qvel[:] = 0
        mujoco.mj_forward(m, d)
        return d.qfrc_passive - d.qfrc_bias

    k = np.zeros((m.nv, m.nv))
    for i in range(m.nv):
        e = np.zeros(m.nq)
        e[i] = 1e-6
        k[:, i] = -(torque(q + e) - torque(q - e)) / 2e-6
    torque(q)
    mass = np.zeros((m.nv, m.nv))
    mujoco.mj_fullM(m, d, mass)
    k = 0.5 * (k + k.T)
    li = np.linalg.inv(np.linalg.cholesky(mass))
    w2 = np.linalg.eigvalsh(li @ k @ li.T)
    with np.errstate(divide="ignore", invalid="ignore"):
        periods = np.where(w2 > 0, 2 * np.pi / np.sqrt(np.maximum(w2, 1e-300)), np.inf)
    return np.sort(periods)[::-1]


def suggest_static(dt: float, sim: Simulator, kp, ratio: float = QUASI_STATIC_RATIO) -> str | None:
    """A message suggesting the static model if ``dt`` is far longer than the slowest period.

    Args:
        dt: s, the data's sample interval.
        kp: [R] stiffness at which to judge (e.g. the prior box's geometric centre, see
            :func:`quasi_static_notice`; softer branches have longer periods).

    Returns:
        ``None`` when the data resolve the branch's motion, else the message.
    """
    periods = natural_periods(sim, kp)
    slowest = float(periods[0])
    if not math.isfinite(slowest) or dt <= ratio * slowest:
        return None
    return (
        f"samples are {dt:g} s apart, {dt / slowest:.0f}x the branch's slowest natural period "
        f"({slowest:.3g} s at the stiffness judged): the data are quasi-static and "
        "carry no information on damping or inertia; use the static model "
        "(--model-kind static), which infers stiffness only"
    )


def quasi_static_notice(tree, sim: Simulator, dt: float) -> str | None:
    """:func:`suggest_static` at the geometric centre of ``tree``'s stiffness prior box: the
    message ``infer`` prints for quasi-static data, or ``None``. (The box's softest corner is
    often near buckling for upright stems, where the period diverges; its centre is the prior's
    typical branch.)"""
    lo, hi = tree.bounds_array()
    r = tree.n_inferred
    return suggest_static(dt, sim, np.sqrt(lo[:r] * hi[:r]))
