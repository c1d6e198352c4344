"""The fused backend of :mod:`treeinfer.sim`: settle and pull with MuJoCo's ``implicitfast``
hinge-tree step written as JAX, in one of two layouts of the same arithmetic:

* ``"scalar"`` (:mod:`treeinfer.sim.fused`): unrolled scalar code per body and mass-matrix
  entry, fastest for a few joints (XLA fuses a step into a handful of kernels) but its program
  grows steeply with the joint count;
* ``"levels"`` (:mod:`treeinfer.sim.levels`): arrays over each depth level of the tree and the
  articulated-body algorithm, whose program grows with the tree's depth only.

``Simulator.step_layout == "auto"`` takes the scalar layout up to :data:`LEVELS_FROM_JOINTS` - 1
joints and the level layout from there (``BENCHMARKS.md``, "Compile time
and memory against joint count", has the measurements behind the threshold).
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np

from . import fused as hd
from . import levels as lv
from .mjx import Backend

# not jnp.linalg.solve: jaxlib 0.10's CPU batched LU deadlocks when two run at once
# (treeinfer.sim.small_solve says why)
from .small_solve import solve as small_solve

if TYPE_CHECKING:
    from .simulator import Simulator

LEVELS_FROM_JOINTS = 25  # auto: the level layout from this many joints (dofs) on
STEP_LAYOUTS = ("auto", "scalar", "levels")


def uses_levels(sim: Simulator) -> bool:
    """Whether ``sim``'s fused step runs in the level layout."""
    layout = getattr(sim, "step_layout", "auto")
    if layout == "auto":
        return sim.hinge_tree.nv >= LEVELS_FROM_JOINTS
    return layout == "levels"


def _gains(sim: Simulator, kp: jax.Array, kd: jax.Array):
    """Per-dof stiffness, damping and spring reference as elements: the inferred joints' from
    ``kp``/``kd`` [R], the others as Python constants (so they fold into the compiled step)."""
    m = sim.mj_model
    stiffness = [float(m.jnt_stiffness[m.dof_jntid[i]]) for i in range(m.nv)]
    damping = [float(m.dof_damping[i]) for i in range(m.nv)]
    for col, dof in enumerate(sim.dof_ids):
        stiffness[int(dof)] = kp[col]
        damping[int(dof)] = kd[col]
    spring = [float(m.qpos_spring[m.jnt_qposadr[m.dof_jntid[i]]]) for i in range(m.nv)]
    return stiffness, damping, spring


def _gain_arrays(sim: Simulator, kp: jax.Array, kd: jax.Array, dtype):
    """:func:`_gains` as [nv] arrays (the level layout's form)."""
    m = sim.mj_model
    dofs = np.asarray(sim.dof_ids)
    stiffness = np.asarray(m.jnt_stiffness)[np.asarray(m.dof_jntid)]
    stiffness = jnp.asarray(stiffness, dtype).at[dofs].set(kp.astype(dtype))
    damping = jnp.asarray(np.asarray(m.dof_damping), dtype).at[dofs].set(kd.astype(dtype))
    qadr = np.asarray(m.jnt_qposadr)[np.asarray(m.dof_jntid)]
    spring = jnp.asarray(np.asarray(m.qpos_spring)[qadr], dtype)
    return stiffness, damping, spring


def _value_and_jacobian(f, q):
    """``(f(q) [n], df/dq [n, n])`` by one ``jax.jvp`` per column, unrolled.

    Why not ``jax.jacfwd``: it vmaps the tangents, and under the particles' ``vmap`` XLA:CPU
    turns the [N, n] tangent arrays of the scalar step code into slow code: 7-10 ms per
    Jacobian of the 6-joint chain at N = 256 against 0.9 ms for the unrolled columns (same
    values; 0.12 ms for the torque alone)."""
    n = q.shape[0]
    cols = []
    for i in range(n):
        r, c = jax.jvp(f, (q,), (jnp.zeros(n, q.dtype).at[i].set(1.0),))
        cols.append(c)
    return r, jnp.stack(cols, axis=1)


def _settle_one(sim: Simulator, kp, kd, dtype, converged: bool = True):
    """:func:`treeinfer.sim.mjx.settle_one` for the fused backend: the same clipped Newton
    iteration, with the exact Jacobian by forward-mode autodiff.

    ``converged=True`` (default) stops after the Newton step that moved every joint by at most
    ``sqrt(eps)`` of the dtype (Newton converges quadratically, so that step left an error
    below rounding: ~1e-7 rad in float32), at most ``sim.settle_iterations``: typically 4 to 10
    iterations instead of the fixed 30 (``converged=False``, the earlier rule), which were most
    of the settle's cost (``BENCHMARKS.md``, CPU). Under ``vmap`` the loop runs until every lane
    has stopped; stopped lanes keep their values. Derivatives are the implicit ones
    (``lax.custom_root``). ``ok``: the residual at the returned angles (converged; the fixed
    rule: before its last step) is at most ``sim.settle_tolerance`` times ``1 + max|r(0)|``."""
    if uses_levels(sim):
        lay = lv.layout(sim.hinge_tree)
        stiffness, _, spring = _gain_arrays(sim, kp, kd, dtype)
        torque = lambda q: lv.static_torque(lay, q, stiffness, spring)
    else:
        stiffness, _, spring = _gains(sim, kp, kd)
        torque = lambda q: hd.static_torque(sim.hinge_tree, q, stiffness, spring)
    nv = sim.mj_model.nv

    def newton_step(f, q):
        r, jac = _value_and_jacobian(f, q)
        return r, jnp.clip(-small_solve(jac, r), -0.2, 0.2)

    zero = jnp.zeros(nv, dtype)
    if converged:
        stop = float(np.sqrt(np.finfo(np.dtype(dtype)).eps))

        def solve(f, q0):
            def cond(carry):
                i, _, big = carry
                return (i < sim.settle_iterations) & (big > stop)

            def body(carry):
                i, q, _ = carry
                _, dq = newton_step(f, q)
                big = jnp.max(jnp.abs(dq))
                # NaN steps (a singular Jacobian) stop the loop; ok below rejects them
                big = jnp.where(jnp.isfinite(big), big, jnp.zeros((), dtype))
                return i + 1, q + dq, big

            inf = jnp.asarray(np.inf, dtype)
            return jax.lax.while_loop(cond, body, (jnp.int32(0), q0, inf))[1]

        # lax.custom_root: derivatives by the implicit function theorem, dq = -J^-1 dr/dK, in
        # forward and reverse mode (a while_loop has no reverse-mode rule of its own)
        tangent_solve = lambda g, y: small_solve(_value_and_jacobian(g, y)[1], y)
        q = jax.lax.custom_root(torque, zero, solve, tangent_solve)
        r_first, r_last = torque(zero), torque(q)
    else:

        def newton(carry, i):
            q, r_first, _ = carry
            r, dq = newton_step(torque, q)
            return (q + dq, jnp.where(i == 0, r, r_first), r), None

        carry = (zero, zero, zero)
        (q, r_first, r_last), _ = jax.lax.scan(newton, carry, jnp.arange(sim.settle_iterations))
    scale = 1.0 + jnp.max(jnp.abs(r_first))
    ok = jnp.all(jnp.isfinite(q)) & (jnp.max(jnp.abs(r_last)) <= sim.settle_tolerance * scale)
    return q, ok


def _prepare(sim: Simulator, kp, kd, dtype):
    kp, kd = kp.astype(dtype), kd.astype(dtype)
    qpos_rest, settled = _settle_one(sim, kp, kd, dtype)
    return (kp, kd), qpos_rest, settled


def _pull(
    sim: Simulator, gains, qpos_rest, forces, site_local, unroll_outer=1, unroll_inner=1, **kw
):
    kp, kd = gains
    if SENSITIVITY_RULE and not kw.get("with_q") and not uses_levels(sim):
        # same values; derivatives in the gains and the forces by the step's sensitivity
        # equations. A substep count given as a Python int stays static (a constant loop
        # bound); a traced one (force_noise's Jacobian program) is a primal of the rule
        n = kw.get("substeps")
        static = n if n is None or isinstance(n, int) else None
        return _pull_sensitivity(
            sim, unroll_outer, unroll_inner, kw.get("body"), static,
            kp, kd, qpos_rest, forces, site_local, kw.get("direction"),
            None if static is not None or n is None else n,
        )  # fmt: skip
    return _pull_one(sim, kp, kd, qpos_rest, forces, site_local, unroll_outer, unroll_inner, **kw)


# ---- exact forward sensitivities (issue 15) -------------------------------------------------
# ``jax.jvp`` of ``_pull_one`` linearises the whole step once per tangent direction, and XLA:CPU
# recomputes primal subexpressions inside every batched tangent kernel: 26-33 rollouts per
# particle for the 2R = 6 gradient directions of the standard problem (central differences:
# 13). The rule below computes the step's state Jacobian once per step (``sensitivity.py``) and
# applies it to every tangent direction with a few multiply-adds; under ``vmap`` over tangent
# directions (``gradients.jvp_value_and_grad``, ``jax.jacfwd``) the Jacobian stays unbatched.
# Tangents of the forces go through the rule too (the force enters a step linearly through the
# applied wrench: one more column of the step's Jacobian, ``StepLinearization.force``): the
# errors-in-variables force Jacobian (``model.force_noise``, ``jax.jacfwd`` in T force samples)
# took 3.0 CPU-s per call on the standard problem by the plain JVP (``benchmarks/
# force_jacobian.py``) and 38 s on a QSM sapling's 4-joint chain (docs/qsm.md). Tangents of
# the grasp point or the pull direction still take the plain ``jax.jvp``.


SENSITIVITY_RULE = True
"""Read at trace time: False differentiates the plain step code (``jax.jvp`` of
:func:`_pull_one`), for comparisons (``benchmarks/gradient_cost.py --plain-jvp``,
``benchmarks/force_jacobian.py``) and as the tests' reference."""


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1, 2, 3, 4))
def _pull_sensitivity(
    sim, unroll_outer, unroll_inner, body, static_substeps,
    kp, kd, qpos_rest, forces, site_local, direction, traced_substeps,
):  # fmt: skip
    """:func:`_pull_one` (the same values) with :func:`_pull_sensitivity_jvp` as derivative.
    The substep count: ``static_substeps`` (None: the simulator's own; a Python int) or
    ``traced_substeps`` (an int32 array; None when static)."""
    n = static_substeps if traced_substeps is None else traced_substeps
    return _pull_one(
        sim, kp, kd, qpos_rest, forces, site_local, unroll_outer, unroll_inner,
        direction=direction, body=body, substeps=n,
    )  # fmt: skip


def _is_zero_tangent(x) -> bool:
    return x is None or isinstance(x, jax.custom_derivatives.SymbolicZero)


def _pull_sensitivity_jvp(
    sim, unroll_outer, unroll_inner, body, static_substeps, primals, tangents
):
    kp, kd, qpos_rest, forces, site_local, direction, traced_substeps = primals
    dkp, dkd, dq0, dforces, dsite, ddirection, _ = tangents
    n = static_substeps if traced_substeps is None else traced_substeps
    data = [dsite] + jax.tree_util.tree_leaves(
        ddirection, is_leaf=lambda x: isinstance(x, jax.custom_derivatives.SymbolicZero)
    )
    if not all(_is_zero_tangent(x) for x in data):
        inst = lambda x, p: jnp.zeros_like(p) if _is_zero_tangent(x) else x
        plain = lambda *a: _pull_one(
            sim, a[0], a[1], a[2], a[3], a[4], unroll_outer, unroll_inner, direction=a[5],
            body=body, substeps=n,
        )  # fmt: skip
        tan = tuple(
            jax.tree_util.tree_map(inst, t, p, is_leaf=_is_zero_tangent) if p is not None else None
            for t, p in zip(tangents[:6], primals[:6])
        )
        return jax.jvp(plain, primals[:6], tan)
    dtype = qpos_rest.dtype
    zero = lambda x, like: jnp.zeros_like(like) if _is_zero_tangent(x) else x.astype(dtype)
    (tau, ok), dtau = pull_with_tangent(
        sim, kp, kd, qpos_rest, forces, site_local, zero(dkp, kp), zero(dkd, kd),
        zero(dq0, qpos_rest), unroll_outer, unroll_inner, direction, body,
        dforces=None if _is_zero_tangent(dforces) else dforces.astype(dtype), substeps=n,
    )  # fmt: skip
    return (tau, ok), (dtau, np.zeros(np.shape(ok), jax.dtypes.float0))


_pull_sensitivity.defjvp(_pull_sensitivity_jvp, symbolic_zeros=True)


def pull_with_tangent(
    sim: Simulator,
    kp,
    kd,
    qpos_rest,
    forces,
    site_local,
    dkp,
    dkd,
    dq0,
    unroll_outer: int = 1,
    unroll_inner=1,
    direction=None,
    body: int | None = None,
    dforces=None,
    substeps=None,
):
    """One pull (:func:`_pull_one`, scalar layout) and its exact tangent for the gain tangents
    ``dkp``, ``dkd`` [R], rest-pose tangent ``dq0`` [nv] and force tangent ``dforces`` [T] (N;
    None: zero): ``((tau [T], ok), dtau [T])`` (m). ``substeps``: as :func:`_pull_one`'s (None:
    the simulator's own; a Python int or a traced count). The step's Jacobian is computed once
    per step (:func:`treeinfer.sim.sensitivity.step_linearization`) and does not depend on the
    tangent, so under ``vmap`` over tangent directions it is shared by all of them."""
    from . import sensitivity as sn
    from .forcing import force_fraction, next_samples

    dtype = qpos_rest.dtype
    t = sim.hinge_tree
    nv = t.nv
    if direction is None:
        ddir = tuple(float(x) for x in sim.gravity_dir)
    else:
        ddir = tuple(jnp.asarray(direction[i], dtype) for i in range(3))
    bid = sim.grasp_body if body is None else body
    n_sub = sim.substeps if substeps is None else substeps
    dt = sim.sim_dt if substeps is None else sim.obs_dt / jnp.asarray(substeps, dtype)
    site_local = tuple(site_local[i] for i in range(3))
    stiffness, damping, spring = _gains(sim, kp, kd)
    with_force = dforces is not None
    dstiff, ddamp = [0.0] * nv, [0.0] * nv
    for col, dof in enumerate(sim.dof_ids):
        dstiff[int(dof)] = dkp[col]
        ddamp[int(dof)] = dkd[col]
    staged = sn.use_staging()
    rest, _ = _stepper(sim, kp, kd, dtype, bid, site_local)
    (c_rest, lever0), (dc_rest, dlever0) = jax.jvp(rest, (qpos_rest,), (dq0,))
    as_dtype = lambda xs: tuple(jnp.asarray(x, dtype) for x in xs)
    # K force directions at once (dforces [T, K]): every state tangent carries a trailing [K]
    # axis, the step's Jacobian none (see pull_force_jacobian)
    n_dir = None if not with_force or jnp.ndim(dforces) == 1 else int(dforces.shape[1])
    wide = lambda x: x if n_dir is None else jnp.broadcast_to(
        jnp.asarray(x, dtype)[..., None], (*jnp.shape(x), n_dir)
    )  # fmt: skip
    dq0, dc_rest, dlever0 = wide(dq0), tuple(map(wide, dc_rest)), tuple(map(wide, dlever0))

    def observe(carry, ff):
        (q, v, lever, comp, ok), (dq, dv, dl) = carry
        f0, f1, df0, df1 = ff

        def sub(k, st):
            (q, v, lever, c, comp), (dq, dv, dl, dc) = st
            frac = force_fraction(sim.force_interp, k, n_sub, dtype)
            force = hd.vscale(f0 + frac * (f1 - f0), ddir)
            lin = sn.step_linearization(
                t, q, v, stiffness, damping, spring, dt, bid, site_local, force, lever,
                pred=(k >= 0) if staged else None, force_dir=ddir if with_force else None,
            )  # fmt: skip
            # the force tangent interpolated as the force (linear in the samples)
            dforce = hd.add(df0, hd.mul(frac, hd.sub(df1, df0))) if with_force else 0.0
            dq_new, dv_new, dl_new, dsite = sn.step_tangent(
                t, lin, dt, [dq[i] for i in range(nv)], [dv[i] for i in range(nv)], dl,
                dstiff, ddamp, dforce,
            )  # fmt: skip
            out = lin.out
            site = out.site
            c = tuple(jnp.where(k == 0, a, b) for a, b in zip(site, c))
            dc = tuple(jnp.where(k == 0, a, b) for a, b in zip(dsite, dc))
            v_new = jnp.stack([jnp.asarray(x, dtype) for x in out.qvel]).astype(dtype)
            # Kahan's compensated qpos += dt * qvel, as _pull_one (its tangent is dq + dt dv')
            y = dt * v_new - comp
            q_new = q + y
            comp = (q_new - q) - y
            tangent = (jnp.stack(as_dtype(dq_new)), jnp.stack(as_dtype(dv_new)),
                       as_dtype(dl_new), as_dtype(dc))  # fmt: skip
            return (q_new, v_new, as_dtype(out.lever), c, comp), tangent

        inner = {} if unroll_inner == 1 else {"unroll": unroll_inner}
        st = ((q, v, lever, as_dtype(c_rest), comp), (dq, dv, dl, as_dtype(dc_rest)))
        (q, v, lever, c, comp), (dq, dv, dl, dc) = jax.lax.fori_loop(0, n_sub, sub, st, **inner)
        ok = ok & jnp.all(jnp.isfinite(q)) & jnp.all(jnp.abs(v) < sim.max_joint_speed)
        obs = hd.dot(hd.vsub(c, c_rest), ddir)
        dobs = hd.dot(hd.vsub(dc, dc_rest), ddir)
        return ((q, v, lever, comp, ok), (dq, dv, dl)), (obs, dobs)

    zero = jnp.zeros_like(qpos_rest)
    carry = (
        (qpos_rest, zero, as_dtype(lever0), zero, jnp.bool_(True)),
        (dq0, wide(zero), as_dtype(dlever0)),
    )
    forces = forces.astype(dtype)
    # no force tangent: Python zeros per sample (they fold away in step_tangent)
    dforces = jnp.zeros((forces.shape[0], 0), dtype) if dforces is None else dforces[:, None]
    pick = (lambda d: d[0]) if with_force else (lambda d: 0.0)

    def observe_samples(carry, ff):
        f0, f1, d0, d1 = ff
        return observe(carry, (f0, f1, pick(d0), pick(d1)))

    (((_, _, _, _, ok), _), (tau, dtau)) = jax.lax.scan(
        observe_samples, carry, (forces, next_samples(forces), dforces, next_samples(dforces)),
        unroll=unroll_outer,
    )  # fmt: skip
    ok = ok & jnp.all(jnp.isfinite(tau)) & jnp.all(jnp.abs(tau) < sim.max_displacement)
    return (tau, ok), dtau


def pull_force_jacobian(sim: Simulator, gains, qpos_rest, forces, site_local, body=None,
                        substeps=None):  # fmt: skip
    """One pull's ``(tau [T], ok, J [T, T])``, ``J = d tau / d forces``: the values and tangents
    ``jax.jacfwd`` of :func:`_pull` in the forces gives through the sensitivity rule, with the T
    unit force tangents carried as one trailing axis of the state tangent instead of a ``vmap``
    level. Why: the vmap makes JAX batch every loop of the step (its while-loop batching rule
    traces each body again), which was most of the force Jacobian program's trace and much of
    its compile on a 2-core CPU (``treeinfer.model.force_noise``; BENCHMARKS.md). For the
    scalar layout with the rule on (:func:`force_jacobian_applies`)."""
    kp, kd = gains
    eye = jnp.eye(forces.shape[0], dtype=qpos_rest.dtype)
    (tau, ok), jac = pull_with_tangent(
        sim, kp, kd, qpos_rest, forces, site_local, jnp.zeros_like(kp), jnp.zeros_like(kd),
        jnp.zeros_like(qpos_rest), body=body, dforces=eye, substeps=substeps,
    )  # fmt: skip
    return tau, ok, jac


def force_jacobian_applies(sim: Simulator) -> bool:
    """Whether :func:`_pull` differentiates ``sim`` by the sensitivity rule (so that
    :func:`pull_force_jacobian` gives what ``jax.jacfwd`` of it would)."""
    return sim.backend == "fused" and SENSITIVITY_RULE and not uses_levels(sim)


def _stepper(sim: Simulator, kp, kd, dtype, bid: int, site_local):
    """(rest(q) -> (site [3], lever [3]), step(q, v, dt, force, lever) -> (v_new [nv],
    lever [3], site [3])) in the simulator's layout; 3-vectors as tuples of scalars."""
    if uses_levels(sim):
        lay = lv.layout(sim.hinge_tree)
        stiffness, damping, spring = _gain_arrays(sim, kp, kd, dtype)

        def rest(q):
            rot, pos, com = lv.body_frame(lay, lv.kinematics(lay, q), bid)
            site = pos + jnp.sum(rot * jnp.stack(site_local)[None, :], axis=-1)
            return tuple(site[i] for i in range(3)), tuple((site - com)[i] for i in range(3))

        def step(q, v, dt, force, lever):
            out = lv.step(lay, q, v, stiffness, damping, spring, dt, bid, site_local, force, lever)
            split = lambda x: tuple(x[i] for i in range(3))
            return out.qvel, split(out.lever), split(out.site)

        return rest, step
    t = sim.hinge_tree
    stiffness, damping, spring = _gains(sim, kp, kd)

    def rest(q):
        kin = hd.kinematics(t, [q[i] for i in range(t.nv)])
        site = hd.point(kin, bid, site_local)
        return site, hd.vsub(site, kin.com[bid])

    def step(q, v, dt, force, lever):
        out = hd.step(t, q, v, stiffness, damping, spring, dt, bid, site_local, force, lever)
        # Stacked [nv] carries: carrying nv separate scalars makes XLA emit one multi-output
        # loop (1.3x faster for 6 joints at N = 131072 on an H100) but costs more per loop
        # iteration at the standard problem's size (26 ms vs 19 ms per NNSVGD iteration).
        return jnp.stack([jnp.asarray(x, dtype) for x in out.qvel]), out.lever, out.site

    return rest, step


def _pull_one(
    sim: Simulator,
    kp,
    kd,
    qpos_rest,
    forces,
    site_local,
    unroll_outer: int = 1,
    unroll_inner=1,
    direction=None,
    body: int | None = None,
    substeps=None,
    with_q: bool = False,
):
    """:func:`treeinfer.sim.mjx.BACKEND`'s ``pull`` for the fused backend: same timing, force
    and observation. ``with_q``: also return the joint angles at every observation, ``q [T,
    nq]`` (the state whose grasp point ``tau`` reports; :mod:`treeinfer.sim.observe`)."""
    from .forcing import force_fraction, next_samples

    dtype = qpos_rest.dtype
    # gravity's direction as Python constants (its zeros fold away) unless given per profile
    if direction is None:
        ddir = tuple(float(x) for x in sim.gravity_dir)
    else:
        ddir = tuple(jnp.asarray(direction[i], dtype) for i in range(3))
    bid = sim.grasp_body if body is None else body
    n_sub = sim.substeps if substeps is None else substeps
    dt = sim.sim_dt if substeps is None else sim.obs_dt / jnp.asarray(substeps, dtype)
    site_local = tuple(site_local[i] for i in range(3))
    rest, step = _stepper(sim, kp, kd, dtype, bid, site_local)
    c_rest, lever0 = rest(qpos_rest)
    as_dtype = lambda xs: tuple(jnp.asarray(x, dtype) for x in xs)

    def observe(carry, ff):
        q, v, lever, comp, ok = carry
        f0, f1 = ff

        def sub(k, st):
            q, v, lever, c, comp = st
            force = hd.vscale(
                f0 + force_fraction(sim.force_interp, k, n_sub, dtype) * (f1 - f0), ddir
            )
            v_new, lever, site = step(q, v, dt, force, lever)
            c = tuple(jnp.where(k == 0, a, b) for a, b in zip(site, c))
            v_new = v_new.astype(dtype)
            # qpos += dt * qvel with Kahan's compensated summation: thousands of small float32
            # increments otherwise drift by ~0.1 mm over a 3 s pull at sub-millisecond steps
            # (the floor that stopped the accuracy control's refinement).
            y = dt * v_new - comp
            q_new = q + y
            comp = (q_new - q) - y
            return q_new, v_new, as_dtype(lever), c, comp

        inner = {} if unroll_inner == 1 else {"unroll": unroll_inner}
        st = (q, v, lever, as_dtype(c_rest), comp)
        q, v, lever, c, comp = jax.lax.fori_loop(0, n_sub, sub, st, **inner)
        q_obs = carry[0]  # the angles at t_k, where the first substep read the site c
        ok = ok & jnp.all(jnp.isfinite(q)) & jnp.all(jnp.abs(v) < sim.max_joint_speed)
        tau_k = hd.dot(hd.vsub(c, c_rest), ddir)
        return (q, v, lever, comp, ok), ((tau_k, q_obs) if with_q else tau_k)

    zero = jnp.zeros_like(qpos_rest)
    carry = (qpos_rest, zero, as_dtype(lever0), zero, jnp.bool_(True))
    forces = forces.astype(dtype)
    (_, _, _, _, ok), out = jax.lax.scan(
        observe, carry, (forces, next_samples(forces)), unroll=unroll_outer
    )
    tau = out[0] if with_q else out
    ok = ok & jnp.all(jnp.isfinite(tau)) & jnp.all(jnp.abs(tau) < sim.max_displacement)
    return (tau, ok, out[1]) if with_q else (tau, ok)


BACKEND = Backend("fused", _prepare, _pull)
