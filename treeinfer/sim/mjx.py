"""The MJX backend of :mod:`treeinfer.sim`: ``mujoco.mjx.step`` on an MJX model with the
inferred joints' gains, a Newton settle through MJX's kinematics, and the batched pull.

Selected by ``Simulator.backend == "mjx"`` (models the fused step does not reproduce, or on
request); :data:`BACKEND` is what :mod:`treeinfer.sim` dispatches to.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import jax
import jax.numpy as jnp

from .small_solve import solve as small_solve  # not jnp.linalg.solve: treeinfer.sim.small_solve

if TYPE_CHECKING:
    from . import Simulator


def import_mjx():
    """``mujoco.mjx``, imported on first use: the fused backend never needs it, and importing it
    costs ~1 s. MJX prints 'Failed to import warp' when the optional Warp backend is absent; we
    use its JAX implementation only, so that line is noise for users."""
    import contextlib
    import io

    with contextlib.redirect_stdout(io.StringIO()):
        from mujoco import mjx
    return mjx


def with_gains(sim: Simulator, kp: jax.Array, kd: jax.Array):
    """MJX model with the inferred joints' stiffness ``kp`` [R] and damping ``kd`` [R]."""
    m = sim.model
    return m.replace(
        jnt_stiffness=m.jnt_stiffness.at[sim.joint_ids].set(kp.astype(m.jnt_stiffness.dtype)),
        dof_damping=m.dof_damping.at[sim.dof_ids].set(kd.astype(m.dof_damping.dtype)),
    )


def _static_torque(model, data, qpos):
    """Net joint torque at rest [nv]: spring ``-Kp (q - q_spring)`` minus gravity.

    Gravity's joint torque is the recursive Newton-Euler bias at zero velocity (kinematics,
    com_pos, rne): a third of what a full forward pass traces, which keeps MJX's compile short.
    Hinge joints only (checked in :func:`make_simulator`), so ``nq == nv``."""
    mjx = import_mjx()

    d = data.replace(qpos=qpos, qvel=jnp.zeros_like(data.qvel))
    d = mjx.rne(model, mjx.com_pos(model, mjx.kinematics(model, d)))
    spring = -model.jnt_stiffness[model.dof_jntid] * (qpos - model.qpos_spring)
    return spring - d.qfrc_bias


def settle_one(sim: Simulator, model) -> tuple[jax.Array, jax.Array]:
    """Gravity-settled joint angles [nq] of one model and whether the solve converged.

    Newton's method with a central-difference Jacobian of the static torque: the nv + 1
    residuals per iteration run as one vmapped evaluation, which compiles several times faster
    than ``jax.jacfwd`` through MJX and converges to the same point (the residual, not the
    Jacobian, decides where Newton stops)."""
    mjx = import_mjx()

    data = mjx.make_data(model)
    nq = sim.mj_model.nq
    q0 = jnp.zeros(nq, dtype=data.qpos.dtype)
    f = jax.vmap(lambda q: _static_torque(model, data, q))
    eps = jnp.asarray(1e-3, q0.dtype)
    probes = jnp.concatenate(
        [
            jnp.zeros((1, nq), q0.dtype),
            eps * jnp.eye(nq, dtype=q0.dtype),
            -eps * jnp.eye(nq, dtype=q0.dtype),
        ]
    )

    def newton(carry, i):
        q, r_first, _ = carry
        r = f(q[None] + probes)
        jac = ((r[1 : nq + 1] - r[nq + 1 :]) / (2 * eps)).T
        dq = jnp.clip(-small_solve(jac, r[0]), -0.2, 0.2)  # clipped: robust far from the root
        r_first = jnp.where(i == 0, r[0], r_first)
        return (q + dq, r_first, r[0]), None

    zero = jnp.zeros(sim.mj_model.nv, q0.dtype)
    # One traced residual (inside the scan): MJX compiles slowly, so nothing is traced twice.
    (q, r_first, r_last), _ = jax.lax.scan(
        newton, (q0, zero, zero), jnp.arange(sim.settle_iterations)
    )
    scale = 1.0 + jnp.max(jnp.abs(r_first))
    ok = jnp.all(jnp.isfinite(q)) & (jnp.max(jnp.abs(r_last)) <= sim.settle_tolerance * scale)
    return q, ok


def pull_one(
    sim: Simulator,
    model,
    qpos_rest,
    forces,
    site_local,
    unroll_outer: int = 1,
    unroll_inner=1,
    direction=None,
    body: int | None = None,
    substeps=None,
):
    """One rollout: displacement [T] of C under ``forces`` [T] (N, along ``direction``), and a
    stable flag.

    ``direction``: [3] unit pull direction (None: gravity's). ``body``: MuJoCo index of the
    grasped body (None: ``sim.grasp_body``); ``site_local`` [3] is C in that body's frame.
    ``substeps``: a traced step count overriding ``sim.substeps`` (the accuracy check's step
    doubling runs every candidate through one compiled program). ``unroll_outer``/
    ``unroll_inner`` unroll the observation scan and the substep loop (speed levers measured in
    ``benchmarks/levers.py``; the defaults keep both loops rolled)."""
    from .forcing import force_fraction, next_samples

    mjx = import_mjx()

    bid = sim.grasp_body if body is None else body
    n_sub = sim.substeps if substeps is None else substeps
    if substeps is not None:
        model = model.replace(
            opt=model.opt.replace(
                timestep=sim.obs_dt / jnp.asarray(substeps, model.opt.timestep.dtype)
            )
        )
    dtype = model.body_pos.dtype
    ddir = jnp.asarray(sim.gravity_dir if direction is None else direction, dtype=dtype)
    site_local = jnp.asarray(site_local, dtype)
    data = mjx.make_data(model).replace(qpos=qpos_rest)
    data = mjx.kinematics(model, data)
    data = mjx.com_pos(model, data)
    grasp = lambda d: d.xpos[bid] + d.xmat[bid] @ site_local  # C in the world
    c_rest = grasp(data)
    nbody = sim.mj_model.nbody

    def push(d, f):
        force = f * ddir
        lever = grasp(d) - d.xipos[bid]
        wrench = jnp.concatenate([force, jnp.cross(lever, force)])
        return d.replace(xfrc_applied=jnp.zeros((nbody, 6), force.dtype).at[bid].set(wrench))

    def observe(carry, ff):
        d, ok = carry
        f0, f1 = ff

        def sub(k, dc):
            dd, c = dc
            f = f0 + force_fraction(sim.force_interp, k, n_sub, dtype) * (f1 - f0)
            dd = mjx.step(model, push(dd, f))
            # after the first substep, the kinematics hold C at the start of this interval
            return dd, jnp.where(k == 0, grasp(dd), c)

        # one traced mjx.step per rollout (MJX compiles slowly; a split first step doubles it)
        inner = {} if unroll_inner == 1 else {"unroll": unroll_inner}
        d, c = jax.lax.fori_loop(0, n_sub, sub, (d, c_rest), **inner)
        ok = ok & jnp.all(jnp.isfinite(d.qpos)) & jnp.all(jnp.abs(d.qvel) < sim.max_joint_speed)
        return (d, ok), c

    forces = forces.astype(dtype)
    (_, ok), cs = jax.lax.scan(
        observe, (data, jnp.bool_(True)), (forces, next_samples(forces)), unroll=unroll_outer
    )
    tau = (cs - c_rest) @ ddir
    ok = ok & jnp.all(jnp.isfinite(tau)) & jnp.all(jnp.abs(tau) < sim.max_displacement)
    return tau, ok


def put_model(mj_model):
    """The MJX model (device arrays) of a MuJoCo C model."""
    return import_mjx().put_model(mj_model)


def _prepare(sim: Simulator, kp, kd, dtype):
    model = with_gains(sim, kp, kd)
    qpos_rest, settled = settle_one(sim, model)
    return model, qpos_rest, settled


def _pull(
    sim: Simulator, model, qpos_rest, forces, site_local, unroll_outer=1, unroll_inner=1, **kw
):
    return pull_one(sim, model, qpos_rest, forces, site_local, unroll_outer, unroll_inner, **kw)


class Backend(NamedTuple):
    """A simulator backend: ``prepare(sim, kp [R], kd [R], dtype) -> (state, qpos_rest [nq],
    settled)`` for one parameter set, then ``pull(sim, state, qpos_rest, forces [T],
    site_local [3], unroll_outer, unroll_inner, direction=None, body=None, substeps=None) ->
    (tau [T] m, ok)`` per force profile (``direction`` [3] unit pull direction, None: gravity's;
    ``body``: grasped MuJoCo body, None: the simulator's; ``substeps``: a traced step count)."""

    name: str
    prepare: object
    pull: object


BACKEND = Backend("mjx", _prepare, _pull)
