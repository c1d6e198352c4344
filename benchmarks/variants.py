"""Variants of ``treeinfer.simulator.simulate`` used to measure speed levers.

:func:`simulate_variant` is ``simulate`` with knobs that the library does not expose (yet):

* ``unroll_outer``: ``lax.scan(..., unroll=k)`` over the observation steps;
* ``unroll_inner``: unroll the ``substeps`` loop (``True``: fully; MJX's step is then traced
  ``substeps`` times, which multiplies compile time);
* ``integrator``: ``"implicitfast"`` (the library's) or ``"euler"`` (MuJoCo's Euler with implicit
  joint damping);

The loop knobs are ``simulate``'s own ``unroll_outer``/``unroll_inner`` arguments, so with every
knob at its default this is exactly ``simulate`` and a measured difference is the knob's.
"""

from __future__ import annotations

import dataclasses

from treeinfer.sim import Rollout, Simulator, simulate


def with_integrator(sim: Simulator, integrator: str) -> Simulator:
    """A copy of ``sim`` whose models use ``integrator`` (``implicitfast`` or ``euler``), on the
    MJX backend (the fused step is implicitfast only)."""
    import copy

    import mujoco

    m = copy.copy(sim.mj_model)
    m.opt.integrator = {
        "implicitfast": mujoco.mjtIntegrator.mjINT_IMPLICITFAST,
        "euler": mujoco.mjtIntegrator.mjINT_EULER,
    }[integrator]
    return dataclasses.replace(sim, mj_model=m, backend="mjx", hinge_tree=None)


def simulate_variant(
    sim: Simulator, kp, kd, forces, *, unroll_outer: int = 1, unroll_inner=1
) -> Rollout:
    """``simulate(sim, kp [P, R], kd [P, R], forces [B, T])`` with the loop knobs above."""
    return simulate(sim, kp, kd, forces, unroll_outer=unroll_outer, unroll_inner=unroll_inner)
