"""Forward sensitivities of the fused hinge-tree step: its Jacobian once, then D cheap tangents.

Why this exists next to ``jax.jvp`` of :func:`treeinfer.sim.fused.step`: pushing D tangent
directions through the step with ``jax.jvp`` linearises the whole step (kinematics, Newton-Euler
bias, mass matrix, tree LDL) once per direction: ~950 scalar operations per direction against
~630 for the step itself on the three-branch tree, so D = 6 tangents cost ~10 steps of
arithmetic, and XLA:CPU fuses the batched tangent arithmetic badly (each tangent kernel
recomputes primal subexpressions; ``benchmarks/gradient_cost.py``: 26-33 rollouts per particle,
against 13 for central differences).

The gains ``theta = (Kp, Kd)`` enter one ``implicitfast`` step only through the passive torque
and the implicit damping term, and the step is

    H(q) a = s(q, v, lever, Kp, Kd),   H = M(q) + diag(armature + dt Kd),
    v' = v + dt a,   q' = q + dt v',   lever' = site(q) - com(q),

so its tangent is (forward sensitivity equations, exact)

    H da = Gq dq + Gv dv + Gl dlever - (q - q_spring) dKp - (v + dt a) dKd,
    Gq = d(s - M(q) a)/dq,  Gv = ds/dv,  Gl = ds/dlever   (a held fixed).

``Gq``, ``Gv``, ``Gl`` and the spatial Jacobians of the grasp point and the grasped body's
centre of mass depend on the primal state only: :func:`step_linearization` computes them once
per step (one ``jax.jvp`` per state component, each through only the part of the tree that the
component moves: the other components are closed over, so their zero tangents are symbolic and
fold away), and :func:`step_tangent` applies them to any number of tangent directions at ~100
multiply-adds each plus one back-substitution with the step's own tree factor. Under ``vmap``
over tangent directions the linearization stays unbatched (it depends on the primal only).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from . import fused as hd

STAGING = "auto"
"""Whether :func:`step_linearization` stages through :func:`materialize` in the pull:
``"auto"`` (on the CPU only: a ``lax.cond`` per stage is free there, while on a GPU a
conditional inside the step loop costs a device-to-host round trip and fusion is not the
problem), ``"on"`` or ``"off"``."""


def use_staging() -> bool:
    """:data:`STAGING` resolved for the default backend (at trace time)."""
    if STAGING == "auto":
        return jax.default_backend() == "cpu"
    return STAGING == "on"


def materialize(fn, pred):
    """``fn()`` (a pytree whose leaves are arrays or Python floats) evaluated inside a
    ``lax.cond`` on ``pred`` (a runtime-true, unbatched scalar such as a loop counter), so that
    XLA stores its array leaves once instead of fusing their whole expression trees into every
    consumer. Why: XLA:CPU does not merge sibling fusions (no multi-output fusion) and
    ``lax.optimization_barrier`` is expanded before fusion there, so a value read by many
    kernels is recomputed by each: this step's linearization executed 3-4x its operation count
    (measured in HLO). Python-float leaves (folded constants) pass around the cond unchanged."""
    box = {}

    def true_fn():
        leaves, tdef = jax.tree_util.tree_flatten(fn())
        box["tdef"], box["leaves"] = tdef, leaves
        return [x for x in leaves if not isinstance(x, float)]

    def false_fn():  # zeros shaped like true_fn's arrays (lax.cond traces true_fn first)
        if "leaves" not in box:
            jax.eval_shape(true_fn)
        live = [x for x in box["leaves"] if not isinstance(x, float)]
        return [jnp.zeros(jnp.shape(x), jnp.result_type(x)) for x in live]

    got = iter(jax.lax.cond(pred, true_fn, false_fn))
    leaves = [x if isinstance(x, float) else next(got) for x in box["leaves"]]
    return jax.tree_util.tree_unflatten(box["tdef"], leaves)


class StepLinearization(NamedTuple):
    """Primal step and its state Jacobian for one particle (tuples of scalar elements).

    ``jac[i][c]``: d qacc_i / d x_c for the state x = (q [nv], v [nv], lever [3]) (rad, rad/s,
    m; so 1/s^2, 1/s, rad/(s^2 m)); ``gain[i][j]`` = (H^-1)_{i, dof j}: the acceleration per
    unit torque at dof j (for the gain tangents); ``site_q[m][k]``, ``lever_q[m][k]``:
    d site_m / dq_k and d (site - com)_m / dq_k (m / rad); ``spring_arm`` [nv] = q - q_spring,
    ``damp_arm`` [nv] = v + dt qacc (the torque per unit Kp, Kd is minus these); ``force``
    [nv]: d qacc / d f for the applied force ``f * force_dir`` (1/(s^2 N)), None when not asked
    for (:func:`step_linearization`'s ``force_dir``)."""

    out: hd.StepOutput
    jac: tuple
    gain: tuple
    site_q: tuple
    lever_q: tuple
    spring_arm: tuple
    damp_arm: tuple
    force: tuple | None = None


def _moved_by(t: hd.HingeTree, body: int, dof: int) -> tuple[bool, bool]:
    """(frame moves, joint anchor/axis moves) of MuJoCo body ``body`` when ``dof`` turns: the
    frame moves for the body's own dof and its ancestors', the anchor and axis only for the
    strict ancestors'."""
    if body == 0:
        return False, False
    own = t.dof[body - 1]
    anc = hd._ancestor_dofs(t, body)
    return dof in anc, dof in anc and dof != own


def kinematics_tangent(t: hd.HingeTree, kin: hd.Kinematics, dof: int) -> hd.Kinematics:
    """d(kinematics)/dq_dof, exact and analytic: turning hinge ``dof`` rotates everything it
    moves about its world axis ``a`` through its anchor ``p``, so d R = [a]x R, d x = a x (x - p)
    for every moved point or direction. Python 0.0 where nothing moves (folds away)."""
    bk = t.dof_body[dof]
    a, p = kin.axis[bk], kin.anchor[bk]
    zero3 = (0.0, 0.0, 0.0)
    rot, pos, com, anchor, axis = [], [], [], [], []
    for b in range(t.nbody + 1):
        frame, joint = _moved_by(t, b, dof)
        if frame:
            cols = [hd.cross(a, tuple(kin.rot[b][i][j] for i in range(3))) for j in range(3)]
            rot.append(tuple(tuple(cols[j][i] for j in range(3)) for i in range(3)))
            pos.append(hd.cross(a, hd.vsub(kin.pos[b], p)))
            com.append(hd.cross(a, hd.vsub(kin.com[b], p)))
        else:
            rot.append((zero3, zero3, zero3))
            pos.append(zero3)
            com.append(zero3)
        if joint:
            anchor.append(hd.cross(a, hd.vsub(kin.anchor[b], p)))
            axis.append(hd.cross(a, kin.axis[b]))
        else:
            anchor.append(zero3)
            axis.append(zero3)
    return hd.Kinematics(tuple(rot), tuple(pos), tuple(com), tuple(anchor), tuple(axis))


def _jvp_sparse(fn, primals, tangents):
    """``jax.jvp(fn, (primals,), (tangents,))`` for pytrees whose leaves may be Python floats:
    leaves with a Python 0.0 tangent (or a float primal) are closed over, so their tangents are
    symbolic zeros and the operations on them fold away."""
    p_leaves, tdef = jax.tree_util.tree_flatten(primals)
    t_leaves = jax.tree_util.tree_leaves(tangents)
    live = [
        i
        for i, (x, dx) in enumerate(zip(p_leaves, t_leaves))
        if not isinstance(x, float) and not (isinstance(dx, float) and dx == 0.0)
    ]

    def along(*xs):
        leaves = list(p_leaves)
        for i, x in zip(live, xs):
            leaves[i] = x
        return fn(jax.tree_util.tree_unflatten(tdef, leaves))

    xs = [p_leaves[i] for i in live]
    dxs = [jnp.asarray(t_leaves[i], jnp.result_type(p_leaves[i])) for i in live]
    return jax.jvp(along, tuple(xs), tuple(dxs))[1]


def step_linearization(
    t: hd.HingeTree,
    qpos,
    qvel,
    stiffness,
    damping,
    qpos_spring,
    dt,
    body: int,
    site_local,
    force,
    lever,
    pred=None,
    force_dir=None,
) -> StepLinearization:
    """:func:`treeinfer.sim.fused.step` (same arguments, same primal arithmetic) and the state
    Jacobian its tangents need (:class:`StepLinearization`). ``pred``: a runtime-true unbatched
    scalar (the loop counter ``>= 0``) to stage the computation with :func:`materialize`
    (XLA:CPU speed only; None: no staging). ``force_dir`` (3 elements): also the column of a
    force tangent along it, ``H^-1 ds/dF force_dir`` (the force enters ``s`` linearly, through
    the applied force and its moment ``lever x F``; nothing else in the step reads it)."""
    nv = t.nv
    q = [qpos[i] for i in range(nv)]
    v = [qvel[i] for i in range(nv)]
    lever = tuple(lever)
    stage = (lambda fn: fn()) if pred is None else (lambda fn: materialize(fn, pred))
    kin = stage(lambda: hd.kinematics(t, q))

    def primal():
        out = hd.step(t, q, v, stiffness, damping, qpos_spring, dt, body, site_local, force,
                      lever, kin=kin)  # fmt: skip
        rhs = hd.bias_minus_applied(t, kin, v, body, force, hd.cross(lever, force))
        smooth = [
            hd.sub(
                hd.sub(
                    hd.mul(-stiffness[i], hd.sub(q[i], qpos_spring[i])), hd.mul(damping[i], v[i])
                ),
                rhs[i],
            )
            for i in range(nv)
        ]
        diag = tuple(hd.add(t.armature[i], hd.mul(dt, damping[i])) for i in range(nv))
        factor = hd.factor_tree(t, hd.mass_matrix(t, kin), diag)
        qacc = hd.solve_factored(t, factor, smooth)  # the step's own (XLA merges the two)
        return out, factor, qacc

    out, factor, qacc = stage(primal)

    def columns():
        # s(kin, v, lever) - M(kin) qacc with qacc fixed; the spring's direct q term is added
        # below (q enters everything else only through the kinematics)
        def resid(x):
            kin_, v_, lever_ = x
            rhs = hd.bias_minus_applied(t, kin_, v_, body, force, hd.cross(lever_, force))
            res = [hd.sub(hd.mul(-damping[i], v_[i]), rhs[i]) for i in range(nv)]
            for (i, j), m in hd.mass_matrix(t, kin_).items():
                res[i] = hd.sub(res[i], hd.mul(m, qacc[j]))
                if i != j:
                    res[j] = hd.sub(res[j], hd.mul(m, qacc[i]))
            site = hd.point(kin_, body, site_local)
            return tuple(res), site, hd.vsub(site, kin_.com[body])

        x0 = (kin, tuple(v), lever)
        zkin = kinematics_tangent(t, kin, 0)._replace()  # structure only
        zkin = jax.tree_util.tree_map(lambda _: 0.0, zkin)
        cols = []  # per state component: (d res [nv], d site [3], d lever [3])
        for k in range(nv):
            dx = (kinematics_tangent(t, kin, k), (0.0,) * nv, (0.0, 0.0, 0.0))
            dres, dsite, dlev = _jvp_sparse(resid, x0, dx)
            dres = list(dres)
            dres[k] = hd.sub(dres[k], stiffness[k])
            cols.append((dres, dsite, dlev))
        for k in range(nv):
            e = tuple(1.0 if i == k else 0.0 for i in range(nv))
            cols.append((_jvp_sparse(resid, x0, (zkin, e, (0.0, 0.0, 0.0)))[0], None, None))
        for m in range(3):
            e = tuple(1.0 if i == m else 0.0 for i in range(3))
            cols.append((_jvp_sparse(resid, x0, (zkin, (0.0,) * nv, e))[0], None, None))
        solved = [hd.solve_factored(t, factor, c[0]) for c in cols]
        jac = tuple(tuple(solved[c][i] for c in range(len(cols))) for i in range(nv))
        gain_cols = []
        for j in range(nv):
            if isinstance(stiffness[j], float) and isinstance(damping[j], float):
                gain_cols.append((0.0,) * nv)  # gains fixed: never perturbed
            else:
                e = [1.0 if i == j else 0.0 for i in range(nv)]
                gain_cols.append(tuple(hd.solve_factored(t, factor, e)))
        gain = tuple(tuple(gain_cols[j][i] for j in range(nv)) for i in range(nv))
        site_q = tuple(tuple(cols[k][1][m] for k in range(nv)) for m in range(3))
        lever_q = tuple(tuple(cols[k][2][m] for k in range(nv)) for m in range(3))
        fcol = None
        if force_dir is not None:

            def applied(f):  # s's force-dependent part (minus the applied generalized force)
                rhs = hd.bias_minus_applied(t, kin, tuple(v), body, f, hd.cross(lever, f))
                return tuple(hd.mul(-1.0, rhs[i]) for i in range(nv))

            dres = _jvp_sparse(applied, tuple(force), tuple(force_dir))
            fcol = tuple(hd.solve_factored(t, factor, list(dres)))
        return jac, gain, site_q, lever_q, fcol

    jac, gain, site_q, lever_q, fcol = stage(columns)
    spring_arm = tuple(hd.sub(q[i], qpos_spring[i]) for i in range(nv))
    damp_arm = tuple(hd.add(v[i], hd.mul(dt, qacc[i])) for i in range(nv))
    return StepLinearization(out, jac, gain, site_q, lever_q, spring_arm, damp_arm, fcol)


def _is_zero(x) -> bool:
    return isinstance(x, float) and x == 0.0


def step_tangent(
    t: hd.HingeTree, lin: StepLinearization, dt, dq, dv, dlever, dstiff, ddamp, dforce=0.0
):
    """Tangent of one step: ``(dq' [nv], dv' [nv], dlever' [3], dsite [3])`` for the state
    tangent ``dq``, ``dv`` [nv], ``dlever`` [3], gain tangents ``dstiff``, ``ddamp`` [nv]
    (N m/rad, N m s/rad; Python 0.0 for gains that are not inferred) and the applied force's
    tangent ``dforce`` (N along the linearization's ``force_dir``; Python 0.0: none; needs
    ``lin.force``). ``dlever'`` and ``dsite``
    are the tangents of the step's ``lever`` and ``site`` outputs (functions of the step's
    starting angles). ~(2 nv + 3 + R) multiply-adds per joint: no factorization, no solve."""
    nv = t.nv
    x = list(dq) + list(dv) + list(dlever)
    torque = []  # minus the gain tangents' torque per dof
    for j in range(nv):
        terms = []
        if not _is_zero(dstiff[j]):
            terms.append(hd.mul(lin.spring_arm[j], dstiff[j]))
        if not _is_zero(ddamp[j]):
            terms.append(hd.mul(lin.damp_arm[j], ddamp[j]))
        torque.append(hd.total(*terms))
    da = []
    for i in range(nv):
        acc = hd.total(*(hd.mul(lin.jac[i][c], x[c]) for c in range(len(x))))
        acc = hd.sub(acc, hd.total(*(hd.mul(lin.gain[i][j], torque[j]) for j in range(nv))))
        if not _is_zero(dforce):
            acc = hd.add(acc, hd.mul(lin.force[i], dforce))
        da.append(acc)
    dv_new = [hd.add(dv[i], hd.mul(dt, da[i])) for i in range(nv)]
    dq_new = [hd.add(dq[i], hd.mul(dt, dv_new[i])) for i in range(nv)]
    dsite = tuple(hd.total(*(hd.mul(lin.site_q[m][k], dq[k]) for k in range(nv))) for m in range(3))
    dlev = tuple(hd.total(*(hd.mul(lin.lever_q[m][k], dq[k]) for k in range(nv))) for m in range(3))
    return tuple(dq_new), tuple(dv_new), dlev, dsite
