"""Variants of ``treeinfer.simulator.simulate`` used to measure speed levers.

:func:`simulate_variant` is ``simulate`` with knobs that the library does not expose (yet):

* ``unroll_outer``: ``lax.scan(..., unroll=k)`` over the observation steps;
* ``unroll_inner``: unroll the ``substeps`` loop (``True``: fully; MJX's step is then traced
  ``substeps`` times, which multiplies compile time);
* ``integrator``: ``"implicitfast"`` (the library's) or ``"euler"`` (MuJoCo's Euler with implicit
  joint damping);

With every knob at its default it computes exactly what ``simulate`` computes (the benchmark
checks this), so a measured difference is the knob's. The settle, gains and observation code are
the library's own functions; only the pull loop is restated here.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from treeinfer.simulator import Rollout, Simulator, settle_one, velocity, with_gains


def with_integrator(sim: Simulator, integrator: str) -> Simulator:
    """A copy of ``sim`` whose models use ``integrator`` (``implicitfast`` or ``euler``)."""
    import copy

    import mujoco
    from mujoco import mjx

    m = copy.copy(sim.mj_model)
    m.opt.integrator = {"implicitfast": mujoco.mjtIntegrator.mjINT_IMPLICITFAST,
                        "euler": mujoco.mjtIntegrator.mjINT_EULER}[integrator]
    return dataclasses.replace(sim, mj_model=m, model=mjx.put_model(m))


def _pull_one(sim, model, qpos_rest, forces, site_local, unroll_outer, unroll_inner):
    from mujoco import mjx

    sid, bid = sim.grasp_site, sim.grasp_body
    model = model.replace(site_pos=model.site_pos.at[sid].set(site_local))
    gdir = jnp.asarray(sim.gravity_dir, dtype=model.site_pos.dtype)
    data = mjx.make_data(model).replace(qpos=qpos_rest)
    data = mjx.kinematics(model, data)
    data = mjx.com_pos(model, data)
    c_rest = data.site_xpos[sid]
    nbody = sim.mj_model.nbody

    def push(d, f):
        force = f * gdir
        lever = d.site_xpos[sid] - d.xipos[bid]
        wrench = jnp.concatenate([force, jnp.cross(lever, force)])
        return d.replace(xfrc_applied=jnp.zeros((nbody, 6), force.dtype).at[bid].set(wrench))

    def observe(carry, f):
        d, ok = carry

        def sub(k, dc):
            dd, c = dc
            dd = mjx.step(model, push(dd, f))
            return dd, jnp.where(k == 0, dd.site_xpos[sid], c)

        d, c = jax.lax.fori_loop(0, sim.substeps, sub, (d, c_rest), unroll=unroll_inner)
        ok = ok & jnp.all(jnp.isfinite(d.qpos)) & jnp.all(jnp.abs(d.qvel) < sim.max_joint_speed)
        return (d, ok), c

    (_, ok), cs = jax.lax.scan(observe, (data, jnp.bool_(True)), forces.astype(gdir.dtype), unroll=unroll_outer)
    tau = (cs - c_rest) @ gdir
    ok = ok & jnp.all(jnp.isfinite(tau)) & jnp.all(jnp.abs(tau) < sim.max_displacement)
    return tau, ok


def simulate_variant(sim: Simulator, kp, kd, forces, *, unroll_outer: int = 1, unroll_inner=1) -> Rollout:
    """``simulate(sim, kp [P, R], kd [P, R], forces [B, T])`` with the loop knobs above."""
    kp, kd, forces = jnp.atleast_2d(kp), jnp.atleast_2d(kd), jnp.atleast_2d(forces)
    site_local = jnp.broadcast_to(jnp.asarray(sim.model.site_pos[sim.grasp_site]), (forces.shape[0], 3))

    def per_params(kp_i, kd_i):
        model = with_gains(sim, kp_i, kd_i)
        qpos_rest, settled = settle_one(sim, model)
        tau, ok = jax.vmap(
            lambda f, s: _pull_one(sim, model, qpos_rest, f, s, unroll_outer, unroll_inner)
        )(forces, site_local)
        return tau, ok & settled

    tau, ok = jax.vmap(per_params)(kp, kd)
    tau = jnp.where(ok[..., None], tau, 0.0)
    tau_dot = jnp.where(ok[..., None], velocity(tau, sim.obs_dt), 0.0)
    return Rollout(tau=tau, tau_dot=tau_dot, stable=ok)
