"""The static model's solver: the equilibrium of the hinge tree under each force sample.

For every force sample ``f_t`` it solves

    0 = -Kp (q - q_spring) - qfrc_bias(q) + J_C(q)^T (f_t d)

(spring, gravity, and the point force ``f_t`` along the unit direction ``d`` at the grasp point
C) by the clipped Newton iteration of the simulator's settle solver with exact Jacobians from
``jax.jacfwd``; see :mod:`treeinfer.inference.static` for when to use it. The Newton and
implicit-derivative solves use :func:`treeinfer.sim.small_solve.solve`, not ``jnp.linalg.solve``:
jaxlib 0.10's batched LAPACK LU deadlocks XLA's CPU thread pool when two of them run at once (issue
13's hang).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ...errors import ConfigError
from ...sim import Rollout, Simulator, velocity
from ...sim import fused as hd
from ...sim.small_solve import solve as small_solve

NEWTON_CLIP = 0.2  # rad per Newton step, as the simulator's settle solver


def _gains(sim: Simulator, kp):
    """Per-dof stiffness and spring reference: inferred dofs from ``kp`` [R], others constant."""
    m = sim.mj_model
    stiffness = [float(m.jnt_stiffness[m.dof_jntid[i]]) for i in range(m.nv)]
    for col, dof in enumerate(sim.dof_ids):
        stiffness[int(dof)] = kp[col]
    spring = [float(m.qpos_spring[m.jnt_qposadr[m.dof_jntid[i]]]) for i in range(m.nv)]
    return stiffness, spring


def _grasp_bodies(sim: Simulator, n: int, grasp_branch, tree) -> tuple[int, ...]:
    if grasp_branch is None:
        return (sim.grasp_body,) * n
    import mujoco

    names = [grasp_branch] * n if isinstance(grasp_branch, str) else list(grasp_branch)
    if len(names) != n:
        raise ConfigError(f"grasp_branch: {len(names)} names for {n} force profiles")
    out = []
    for name in names:
        b = mujoco.mj_name2id(sim.mj_model, mujoco.mjtObj.mjOBJ_BODY, name)
        if b < 0:
            raise ConfigError(f"grasp_branch: no body named '{name}' in the model")
        out.append(int(b))
    if tree is None and any(b != sim.grasp_body for b in out):
        raise ConfigError(
            "grasp_branch: pass the tree to pull on branches other than the grasp "
            "branch (their lengths set the grasp points)"
        )
    return tuple(out)


def _profile_geometry(sim: Simulator, kp, forces, grasp_fraction, direction, grasp_branch, tree):
    """Checked inputs of :func:`static_rollout`: ``kp`` [P, R], ``forces`` [B, T], the grasp
    bodies, the grasp points in their frames [B, 3] and the unit directions [B, 3]."""
    if sim.hinge_tree is None:
        raise ConfigError("the static model needs the fused hinge-tree backend (backend='fused')")
    dtype = sim.dtype
    kp = jnp.atleast_2d(jnp.asarray(kp, dtype))
    forces = jnp.atleast_2d(jnp.asarray(forces, dtype))
    b = forces.shape[0]
    bodies = _grasp_bodies(sim, b, grasp_branch, tree)
    # grasp points in each body's frame: start + f * (end - start), the branch along local x
    starts, ends = [], []
    for body in bodies:
        if body == sim.grasp_body:
            starts.append(sim.grasp_start)
            ends.append(sim.grasp_end)
        else:
            starts.append(np.zeros(3))
            ends.append(np.array([tree.branch(sim.mj_model.body(body).name).length, 0.0, 0.0]))
    ends_np = np.asarray(ends, float)
    starts, ends = jnp.asarray(np.asarray(starts), dtype), jnp.asarray(ends_np, dtype)
    if grasp_fraction is None:
        tree_site = np.asarray(sim.mj_model.site_pos[sim.grasp_site], float)
        sites = jnp.asarray(
            np.asarray(
                [tree_site if body == sim.grasp_body else e for body, e in zip(bodies, ends_np)]
            ),
            dtype,
        )
    else:
        frac = jnp.broadcast_to(jnp.asarray(grasp_fraction, dtype), (b,))
        sites = starts + frac[:, None] * (ends - starts)
    if direction is None:
        dirs = jnp.broadcast_to(jnp.asarray(sim.gravity_dir, dtype), (b, 3))
    else:
        dirs = jnp.broadcast_to(jnp.asarray(direction, dtype), (b, 3))
        if not isinstance(dirs, jax.core.Tracer):
            norms = np.linalg.norm(np.asarray(dirs), axis=1)
            if not np.all(np.isfinite(norms)) or np.any(norms == 0):
                raise ConfigError("direction: each must be a finite non-zero vector")
        dirs = dirs / jnp.linalg.norm(dirs, axis=1, keepdims=True)
    return kp, forces, bodies, sites, dirs


def static_rollout(
    sim: Simulator,
    kp,
    forces,
    grasp_fraction=None,
    direction=None,
    grasp_branch: str | Sequence[str] | None = None,
    tree=None,
    iterations: int | None = None,
) -> Rollout:
    """Equilibrium displacement of the grasp point under each force sample (no dynamics).

    Args:
        sim: from :func:`treeinfer.sim.make_simulator` with the fused backend (any tree
            treeinfer builds). ``sim.obs_dt`` is used only for ``tau_dot``.
        kp: [P, R] N m/rad, stiffness of the inferred joints (damping plays no role).
        forces: [B, T] N, force along ``direction`` at the grasp point.
        grasp_fraction: None (the tree's), a scalar or [B]: grasp point as a fraction of the
            grasped branch's length from its joint.
        direction: None (along gravity), [3] or [B, 3] world vectors (normalised here).
        grasp_branch: None (the simulator's grasp branch), a name, or B names (static: one
            compiled group per distinct branch); other branches need ``tree`` for lengths.
        iterations: Newton iterations per sample (default ``sim.settle_iterations``).

    Returns:
        :class:`~treeinfer.sim.Rollout`: ``tau`` [P, B, T] m along the direction from
        the gravity-settled rest, ``tau_dot`` its finite-difference derivative (the same scheme
        as recorded data), ``stable`` [P, B] False where an equilibrium was not found.
    """
    kp, forces, bodies, sites, dirs = _profile_geometry(
        sim, kp, forces, grasp_fraction, direction, grasp_branch, tree
    )
    n_iter = sim.settle_iterations if iterations is None else int(iterations)
    return _static_core(sim, bodies, n_iter, kp, forces, sites, dirs)


@functools.partial(jax.jit, static_argnums=(0, 1, 2))
def _static_core(sim: Simulator, bodies: tuple, n_iter: int, kp, forces, sites, dirs) -> Rollout:
    """Jitted once per (simulator, grasp bodies, iterations, shapes): one group per body."""
    dtype = kp.dtype
    b = forces.shape[0]
    tau = jnp.zeros((kp.shape[0], b, forces.shape[1]), dtype)
    ok = jnp.zeros((kp.shape[0], b), bool)
    for body in sorted(set(bodies)):
        idx = np.asarray([i for i, x in enumerate(bodies) if x == body])
        t_g, ok_g = _static_group(sim, body, n_iter, kp, forces[idx], sites[idx], dirs[idx])
        tau = tau.at[:, idx].set(t_g)
        ok = ok.at[:, idx].set(ok_g)
    tau = jnp.where(ok[..., None], tau, 0.0)
    tau_dot = jnp.where(ok[..., None], velocity(tau, sim.obs_dt), 0.0)
    return Rollout(tau=tau, tau_dot=tau_dot, stable=ok)


def _solver(sim: Simulator, body: int, n_iter: int, dtype):
    """``solve(kp_i, f, site, d, q0) -> (q [nv], ok)``: the equilibrium under a force ``f``
    along ``d`` at ``site`` on ``body`` from the start ``q0``, and its flag (the residual there
    is at most ``sim.settle_tolerance`` times ``1 + max|residual(q0)|``)."""
    t = sim.hinge_tree
    nv = t.nv
    moving = hd._ancestor_dofs(t, body)  # dofs whose hinge moves the grasp point

    def residual(q, kp_i, f, site, d):
        """Static torque plus J_C^T (f d): a hinge's column of the point Jacobian is
        ``axis x (C - anchor)``, so its generalised force is ``axis . ((C - anchor) x F)``
        (scalar arithmetic: compiles far faster than a nested ``jacfwd``)."""
        stiffness, spring = _gains(sim, kp_i)
        qs = [q[i] for i in range(nv)]
        kin = hd.kinematics(t, qs)
        c = hd.point(kin, body, tuple(site[i] for i in range(3)))
        force = tuple(f * d[i] for i in range(3))
        r = hd.static_torque(t, q, stiffness, spring)
        gen = [0.0] * nv
        for dof in moving:
            b = t.dof_body[dof]
            gen[dof] = hd.dot(kin.axis[b], hd.cross(hd.vsub(c, kin.anchor[b]), force))
        return r + jnp.stack([jnp.asarray(g, dtype) for g in gen])

    @jax.custom_jvp
    def equilibrium(kp_i, f, site, d, q0):
        """``n_iter`` clipped Newton steps on ``residual(q) = 0`` from ``q0``: ``q`` [nv]."""

        def newton(q, _):
            jac = jax.jacfwd(residual)(q, kp_i, f, site, d)
            dq = -small_solve(jac, residual(q, kp_i, f, site, d))
            return q + jnp.clip(dq, -NEWTON_CLIP, NEWTON_CLIP), None

        return jax.lax.scan(newton, q0, None, length=n_iter)[0]

    @equilibrium.defjvp
    def _equilibrium_jvp(primals, tangents):
        """The implicit function theorem at the solution: ``J dq = -(dr/dp) dp`` for the
        inputs p = (kp, f, site, d) (the start q0 leaves the solution unchanged). One Jacobian
        (nv forward passes) and one solve per sample, in forward and reverse mode and to any
        order, instead of differentiating the ``n_iter`` Newton steps (reverse mode through a
        scan of Jacobians: ~10x the forward solve, and as slow again under ``lax.custom_root``,
        whose transpose rebuilds the Jacobian one column at a time)."""
        kp_i, f, site, d, q0 = primals
        q = equilibrium(kp_i, f, site, d, q0)
        jac = jax.jacfwd(residual)(q, kp_i, f, site, d)
        _, dr = jax.jvp(
            lambda k, ff, ss, dd: residual(q, k, ff, ss, dd), (kp_i, f, site, d), tangents[:4]
        )
        return q, -small_solve(jac, dr)

    def solve(kp_i, f, site, d, q0):
        q = equilibrium(kp_i, f, site, d, q0)
        r0 = jax.lax.stop_gradient(residual(q0, kp_i, f, site, d))
        r_last = jax.lax.stop_gradient(residual(q, kp_i, f, site, d))
        ok = jnp.all(jnp.isfinite(q)) & (
            jnp.max(jnp.abs(r_last)) <= sim.settle_tolerance * (1.0 + jnp.max(jnp.abs(r0)))
        )
        return q, ok

    return solve


def _equilibria_group(sim: Simulator, body: int, n_iter: int, kp, forces, sites, dirs):
    """Equilibria of profiles grasped on one body: ``q`` [P, B, T, nv], the gravity-settled
    rest ``q_rest`` [P, nv] and the flags ``ok`` [P, B] (every sample and the rest found)."""
    solve = _solver(sim, body, n_iter, kp.dtype)
    zero = jnp.zeros(sim.hinge_tree.nv, kp.dtype)

    def per_params(kp_i):
        q_rest, ok_rest = solve(kp_i, jnp.asarray(0.0, kp.dtype), sites[0], dirs[0], zero)

        def per_profile(f_row, site, d):
            q, ok = jax.vmap(lambda f: solve(kp_i, f, site, d, q_rest))(f_row)  # [T, nv], [T]
            return q, jnp.all(ok) & ok_rest

        q, ok = jax.vmap(per_profile)(forces, sites, dirs)
        return q, q_rest, ok

    return jax.vmap(per_params)(kp)


def _static_group(sim: Simulator, body: int, n_iter: int, kp, forces, sites, dirs):
    """[P, B, T] displacements and [P, B] flags for profiles grasped on one body."""
    t = sim.hinge_tree
    nv = t.nv
    dtype = kp.dtype

    def point(q, site):
        kin = hd.kinematics(t, [q[i] for i in range(nv)])
        p = hd.point(kin, body, tuple(site[i] for i in range(3)))
        return jnp.stack([jnp.asarray(x, dtype) for x in p])

    q, q_rest, ok = _equilibria_group(sim, body, n_iter, kp, forces, sites, dirs)

    def per_profile(q_row, qr, site, d):  # [T, nv], [nv]
        c = jax.vmap(lambda qq: point(qq, site))(q_row)  # [T, 3]
        return (c - point(qr, site)) @ d

    tau = jax.vmap(  # over parameter sets, then profiles
        lambda qp, qr: jax.vmap(lambda qq, s, d: per_profile(qq, qr, s, d))(qp, sites, dirs)
    )(q, q_rest)
    good = ok & jnp.all(jnp.isfinite(tau), axis=-1)
    good = good & jnp.all(jnp.abs(tau) < sim.max_displacement, axis=-1)
    return tau, good


class Equilibria(NamedTuple):
    """:func:`static_equilibria`: joint angles ``q`` [P, B, T, nv] under each force sample,
    the gravity-settled rest ``q_rest`` [P, nv] and ``stable`` [P, B] (False where an
    equilibrium was not found)."""

    q: jax.Array
    q_rest: jax.Array
    stable: jax.Array


def static_equilibria(
    sim: Simulator,
    kp,
    forces,
    grasp_fraction=None,
    direction=None,
    grasp_branch: str | Sequence[str] | None = None,
    tree=None,
    iterations: int | None = None,
) -> Equilibria:
    """The joint angles of :func:`static_rollout`'s equilibria (same arguments), for
    observations other than the grasp point's displacement (inclinometers: the tilt of a link
    is read from the kinematics at ``q``; see :mod:`treeinfer.inference.pulltest`)."""
    kp, forces, bodies, sites, dirs = _profile_geometry(
        sim, kp, forces, grasp_fraction, direction, grasp_branch, tree
    )
    n_iter = sim.settle_iterations if iterations is None else int(iterations)
    return _equilibria_core(sim, bodies, n_iter, kp, forces, sites, dirs)


@functools.partial(jax.jit, static_argnums=(0, 1, 2))
def _equilibria_core(sim: Simulator, bodies: tuple, n_iter: int, kp, forces, sites, dirs):
    p, (b, n) = kp.shape[0], forces.shape
    nv = sim.hinge_tree.nv
    q = jnp.zeros((p, b, n, nv), kp.dtype)
    q_rest = jnp.zeros((p, nv), kp.dtype)
    ok = jnp.zeros((p, b), bool)
    for body in sorted(set(bodies)):
        idx = np.asarray([i for i, x in enumerate(bodies) if x == body])
        q_g, r_g, ok_g = _equilibria_group(
            sim, body, n_iter, kp, forces[idx], sites[idx], dirs[idx]
        )
        q = q.at[:, idx].set(q_g)
        q_rest = r_g  # the rest does not depend on the profiles
        ok = ok.at[:, idx].set(ok_g)
    return Equilibria(q=q, q_rest=q_rest, stable=ok)
