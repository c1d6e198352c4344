"""MuJoCo's ``implicitfast`` step for contact-free hinge trees, written to fuse.

Why this exists next to MJX: ``mjx.step`` is general (contacts, tendons, actuators, any joint
type) and lowers to ~220 separate XLA kernels per physics step. Our branch models use none of
that generality: a kinematic tree of rigid bodies, at most one hinge per body, springs and
dampers, gravity and one applied force. For them one step is a few hundred scalar multiply-adds
per particle, and when it is written as scalar arithmetic (no gathers, scatters, tiny matrix
products or level-by-level tree scans) XLA fuses the whole step into a handful of elementwise
kernels. The observation loop is then bound by arithmetic, not by kernel launches or memory
traffic (measured in ``BENCHMARKS.md``). MuJoCo Warp would be the library answer, but it is a
separate GPU-only stack; this file is the small, exact alternative for the models we build.

Everything is read from the compiled ``mujoco.MjModel`` (``body_pos``, ``body_quat``,
``jnt_pos``, ``jnt_axis``, ``body_ipos``, ``body_iquat``, ``body_inertia``, ``body_mass``,
``dof_armature``, ``qpos0``, ``qpos_spring``, gravity), so a user's own MJCF or URDF works too,
and the step is MuJoCo's, term for term:

* kinematics as ``mj_kinematics`` (hinge about ``jnt_axis`` through ``jnt_pos``);
* ``qfrc_bias`` by Newton-Euler (Coriolis, centrifugal, gravity) as ``mj_rne``;
* ``qfrc_applied`` from the applied force at the grasp body's centre of mass plus its
  lever-arm torque, as ``mj_xfrcAccumulate``;
* the passive spring-damper ``-Kp (q - qpos_spring) - Kd qdot`` as ``mj_passive``;
* ``implicitfast``: ``qacc = (M + dt diag(Kd))^-1 qfrc_smooth`` with the tree-sparse LDL of
  ``mj_factorM``, then ``qvel += dt qacc``, ``qpos += dt qvel``.

It is checked against ``mujoco.mj_step`` in ``tests/test_hinge_dynamics.py``. Models with
anything else (other joint types, several joints in one body, actuators, tendons, equality
constraints, fluid forces, friction loss) are refused with :class:`UnsupportedModel`, and the
simulator falls back to MJX.

Arithmetic is on *elements*: a Python float (a compile-time constant, so products with the
model's many exact zeros and ones vanish at trace time) or a JAX scalar. The functions work on
one particle; ``vmap`` turns each scalar op into one elementwise op over the batch.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from .elements import (  # noqa: F401 -- the step's arithmetic; also its old import path
    _EYE3,
    _ZERO3,
    _cmat,
    _const,
    _cvec,
    _is,
    add,
    cross,
    dot,
    matmul,
    matTvec,
    matvec,
    mul,
    sub,
    total,
    vadd,
    vscale,
    vsub,
)


class UnsupportedModel(ValueError):
    """The model uses a feature this step does not reproduce; use the MJX backend."""


def _quat_to_mat(q) -> np.ndarray:
    import mujoco

    out = np.zeros(9)
    mujoco.mju_quat2Mat(out, np.asarray(q, float) / np.linalg.norm(q))
    return out.reshape(3, 3)


# ---- the model ----------------------------------------------------------------------------------
class HingeTree(NamedTuple):
    """Static description of a hinge tree (Python floats and tuples, hashable constants).

    Bodies are MuJoCo's, world excluded, parents before children. ``dof[b]`` is the dof of
    body b's hinge or -1 if it is welded to its parent."""

    parent: tuple  # per body: parent body index, 0 = world
    dof: tuple  # per body: dof index or -1
    body_pos: tuple
    body_rot: tuple
    jnt_pos: tuple
    jnt_axis: tuple
    ipos: tuple
    irot: tuple  # body-frame rotation of the principal axes (body_iquat)
    inertia: tuple  # principal moments
    mass: tuple
    dof_body: tuple  # per dof: its body
    dof_parent: tuple  # per dof: parent dof or -1 (the tree sparsity of M)
    qpos0: tuple
    armature: tuple
    gravity: tuple
    nv: int

    @property
    def nbody(self) -> int:
        return len(self.parent)  # without the world


def from_mjmodel(m) -> HingeTree:
    """Read a compiled ``mujoco.MjModel``; :class:`UnsupportedModel` if it needs full MJX."""
    import mujoco

    problems = []
    if m.nu or m.na:
        problems.append("actuators")
    if m.ntendon:
        problems.append("tendons")
    if m.neq:
        problems.append("equality constraints")
    if np.any(np.asarray(m.jnt_type) != mujoco.mjtJoint.mjJNT_HINGE):
        problems.append("non-hinge joints")
    if np.any(np.asarray(m.body_jntnum)[1:] > 1):
        problems.append("bodies with several joints")
    if np.any(np.asarray(m.dof_frictionloss) != 0):
        problems.append("dof friction loss")
    if np.any(np.asarray(m.body_gravcomp) != 0):
        problems.append("gravity compensation")
    if m.opt.density != 0 or m.opt.viscosity != 0:
        problems.append("fluid forces")
    if m.opt.integrator != mujoco.mjtIntegrator.mjINT_IMPLICITFAST:
        problems.append("an integrator other than implicitfast")
    flags = int(m.opt.disableflags)
    needed_off = int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
    if not (flags & needed_off) and m.njnt and np.any(np.asarray(m.jnt_limited)):
        problems.append("joint limits with the constraint solver on")
    for bit in ("mjDSBL_GRAVITY", "mjDSBL_SPRING", "mjDSBL_DAMPER", "mjDSBL_PASSIVE"):
        if flags & int(getattr(mujoco.mjtDisableBit, bit, 0)):
            problems.append(f"disable flag {bit}")
    if problems:
        raise UnsupportedModel("the fused hinge-tree step does not model " + ", ".join(problems))

    nb = m.nbody
    dof = []
    for b in range(1, nb):
        dof.append(int(m.jnt_dofadr[m.body_jntadr[b]]) if m.body_jntnum[b] else -1)
    jnt = [int(m.body_jntadr[b]) if m.body_jntnum[b] else -1 for b in range(1, nb)]
    dof_body = [0] * m.nv
    for b, d in enumerate(dof):
        if d >= 0:
            dof_body[d] = b + 1
    return HingeTree(
        parent=tuple(int(m.body_parentid[b]) for b in range(1, nb)),
        dof=tuple(dof),
        body_pos=tuple(_cvec(m.body_pos[b]) for b in range(1, nb)),
        body_rot=tuple(_cmat(_quat_to_mat(m.body_quat[b])) for b in range(1, nb)),
        jnt_pos=tuple(_cvec(m.jnt_pos[j]) if j >= 0 else _ZERO3 for j in jnt),
        jnt_axis=tuple(_cvec(m.jnt_axis[j]) if j >= 0 else _ZERO3 for j in jnt),
        ipos=tuple(_cvec(m.body_ipos[b]) for b in range(1, nb)),
        irot=tuple(_cmat(_quat_to_mat(m.body_iquat[b])) for b in range(1, nb)),
        inertia=tuple(_cvec(m.body_inertia[b]) for b in range(1, nb)),
        mass=tuple(_const(m.body_mass[b]) for b in range(1, nb)),
        dof_body=tuple(dof_body),
        dof_parent=tuple(int(p) for p in m.dof_parentid),
        qpos0=tuple(_const(m.qpos0[m.jnt_qposadr[m.dof_jntid[d]]]) for d in range(m.nv)),
        armature=tuple(_const(a) for a in m.dof_armature),
        gravity=_cvec(m.opt.gravity),
        nv=int(m.nv),
    )


# ---- kinematics and dynamics of one particle ----------------------------------------------------
class Kinematics(NamedTuple):
    rot: tuple  # per body (world first): 3x3 world orientation
    pos: tuple  # per body: world origin
    com: tuple  # per body: world centre of mass (xipos)
    anchor: tuple  # per body: world joint anchor (origin for welded bodies)
    axis: tuple  # per body: world joint axis (zeros for welded bodies)


def _axis_rotation(axis, angle):
    """Rotation by ``angle`` about the constant unit ``axis``: I + s K + (1 - c) K^2."""
    s, one_minus_c = jnp.sin(angle), 1.0 - jnp.cos(angle)
    k = ((0.0, -axis[2], axis[1]), (axis[2], 0.0, -axis[0]), (-axis[1], axis[0], 0.0))
    k2 = np.asarray(k) @ np.asarray(k)
    return tuple(
        tuple(
            total(
                _const(float(i == j)), mul(_const(k[i][j]), s), mul(_const(k2[i][j]), one_minus_c)
            )
            for j in range(3)
        )
        for i in range(3)
    )


def kinematics(t: HingeTree, q) -> Kinematics:
    """World frames of every body for joint angles ``q`` (a sequence of nv elements)."""
    rot, pos, com, anchor, axis = [_EYE3], [_ZERO3], [_ZERO3], [_ZERO3], [_ZERO3]
    for b in range(t.nbody):
        p = t.parent[b]
        x = vadd(pos[p], matvec(rot[p], t.body_pos[b]))
        r = matmul(rot[p], t.body_rot[b])
        d = t.dof[b]
        if d >= 0:
            a = vadd(x, matvec(r, t.jnt_pos[b]))
            ax = matvec(r, t.jnt_axis[b])
            r = matmul(r, _axis_rotation(t.jnt_axis[b], sub(q[d], t.qpos0[d])))
            x = vsub(a, matvec(r, t.jnt_pos[b]))
        else:
            a, ax = x, _ZERO3
        rot.append(r)
        pos.append(x)
        com.append(vadd(x, matvec(r, t.ipos[b])))
        anchor.append(a)
        axis.append(ax)
    return Kinematics(tuple(rot), tuple(pos), tuple(com), tuple(anchor), tuple(axis))


def point(kin: Kinematics, body: int, local):
    """World position of a point given in ``body``'s frame (MuJoCo body index)."""
    return vadd(kin.pos[body], matvec(kin.rot[body], local))


def _body_inertia(irot: tuple, inertia: tuple) -> tuple:
    """A body's inertia tensor about its com in its own frame, ``irot diag(inertia) irot^T``,
    as constants: diagonal (its zeros fold) when the principal axes are the body's axes, as for
    every branch treeinfer builds, where it gives exactly the arithmetic of rotating to the
    principal axes; for rotated principal axes (merged masses, a user's model) it saves the
    27-product rotation ``rot @ irot`` in every call of :func:`_inertia_times`. (Not cached: a
    3x3 product at trace time, and no module keeps a cache, tests/test_architecture.py.)"""
    r = np.asarray(irot, float)
    full = r @ np.diag(np.asarray(inertia, float)) @ r.T
    return _cmat(0.5 * (full + full.T))


def _inertia_times(t: HingeTree, kin: Kinematics, b: int, v):
    """World inertia of body b (MuJoCo index) about its com, applied to the world vector v."""
    r = kin.rot[b]
    local = matTvec(r, v)
    return matvec(r, matvec(_body_inertia(t.irot[b - 1], t.inertia[b - 1]), local))


def _ancestor_dofs(t: HingeTree, b: int) -> list[int]:
    """Dofs that move MuJoCo body b, nearest first."""
    out = []
    while b > 0:
        d = t.dof[b - 1]
        if d >= 0:
            out.append(d)
        b = t.parent[b - 1]
    return out


def _subtree_sums(t: HingeTree, kin: Kinematics, force, moment):
    """Per dof: axis . (moment about its anchor of the body forces/torques in its subtree).

    ``force[b]``, ``moment[b]`` (MuJoCo body index; moment about the body's com) are summed
    leaves-to-root into a subtree force and a moment about the world origin, then each dof takes
    ``axis . (N - anchor x F)``: the transpose of the joint Jacobian, as in ``mj_rne``."""
    nb = t.nbody + 1
    f_sub = [force[b] for b in range(nb)]
    n_sub = [vadd(cross(kin.com[b], force[b]), moment[b]) for b in range(nb)]
    for b in range(nb - 1, 0, -1):
        p = t.parent[b - 1]
        if p > 0:
            f_sub[p] = vadd(f_sub[p], f_sub[b])
            n_sub[p] = vadd(n_sub[p], n_sub[b])
    out = [0.0] * t.nv
    for b in range(1, nb):
        d = t.dof[b - 1]
        if d >= 0:
            out[d] = dot(kin.axis[b], vsub(n_sub[b], cross(kin.anchor[b], f_sub[b])))
    return out


def bias_minus_applied(
    t: HingeTree,
    kin: Kinematics,
    qvel,
    applied_body=None,
    applied_force=_ZERO3,
    applied_torque=_ZERO3,
):
    """``qfrc_bias - qfrc_applied`` [nv]: Newton-Euler with velocity-product accelerations and
    gravity, minus the applied force/torque at ``applied_body``'s centre of mass."""
    nb = t.nbody + 1
    omega, alpha, acc = [_ZERO3] * nb, [_ZERO3] * nb, [_ZERO3] * nb
    force, moment = [_ZERO3] * nb, [_ZERO3] * nb
    minus_g = vscale(-1.0, t.gravity)
    for b in range(1, nb):
        p, d = t.parent[b - 1], t.dof[b - 1]
        w_rel = vscale(qvel[d], kin.axis[b]) if d >= 0 else _ZERO3
        w = vadd(omega[p], w_rel)
        al = vadd(alpha[p], cross(omega[p], w_rel))
        # com acceleration (velocity products only): parent com -> anchor -> this com
        r1 = vsub(kin.anchor[b], kin.com[p]) if p > 0 else _ZERO3
        r2 = vsub(kin.com[b], kin.anchor[b])
        a = acc[p]
        if p > 0:
            a = vadd(a, vadd(cross(alpha[p], r1), cross(omega[p], cross(omega[p], r1))))
        a = vadd(a, vadd(cross(al, r2), cross(w, cross(w, r2))))
        omega[b], alpha[b], acc[b] = w, al, a
        m = t.mass[b - 1]
        force[b] = vscale(m, vadd(a, minus_g))
        iw = _inertia_times(t, kin, b, w)
        moment[b] = vadd(_inertia_times(t, kin, b, al), cross(w, iw))
        if b == applied_body:
            force[b] = vsub(force[b], applied_force)
            moment[b] = vsub(moment[b], applied_torque)
    return _subtree_sums(t, kin, force, moment)


def mass_matrix(t: HingeTree, kin: Kinematics):
    """Joint-space inertia ``M`` as a dict {(i, j): element} for i <= j on the tree sparsity:
    ``sum_b m_b Jv_i . Jv_j + a_i . I_b a_j`` over the bodies b moved by both dofs."""
    entries: dict = {}
    for b in range(1, t.nbody + 1):
        dofs = _ancestor_dofs(t, b)
        if not dofs:
            continue
        lin = {
            d: cross(kin.axis[t.dof_body[d]], vsub(kin.com[b], kin.anchor[t.dof_body[d]]))
            for d in dofs
        }
        ang = {d: _inertia_times(t, kin, b, kin.axis[t.dof_body[d]]) for d in dofs}
        m = t.mass[b - 1]
        for i in dofs:
            for j in dofs:
                if i <= j:
                    term = add(mul(m, dot(lin[i], lin[j])), dot(kin.axis[t.dof_body[i]], ang[j]))
                    entries[(i, j)] = add(entries.get((i, j), 0.0), term)
    return entries


def _tree_ancestors(t: HingeTree) -> list[list[int]]:
    """Per dof: its ancestor dofs, nearest first."""
    out = []
    for i in range(t.nv):
        anc, j = [], t.dof_parent[i]
        while j >= 0:
            anc.append(j)
            j = t.dof_parent[j]
        out.append(anc)
    return out


def factor_tree(t: HingeTree, entries: dict, diagonal) -> dict:
    """MuJoCo's no-fill-in tree LDL of ``M + diag(diagonal)`` (``mj_factorM``): M's nonzeros lie
    on dof-ancestor pairs, so the factor does too. Returns {(row, col): element} with col an
    ancestor of row (the unit-lower factor L) and (i, i): D_i."""
    a = {}
    for (i, j), v in entries.items():
        a[(j, i)] = v  # store as (row, col) with col an ancestor of row (col <= row)
    for i in range(t.nv):
        a[(i, i)] = add(a.get((i, i), 0.0), diagonal[i])
    anc = _tree_ancestors(t)
    for k in range(t.nv - 1, -1, -1):
        for i in anc[k]:
            tmp = a.get((k, i), 0.0) / a[(k, k)] if not _is(a.get((k, i), 0.0), 0.0) else 0.0
            for j in [i] + anc[i]:
                a[(i, j)] = sub(a.get((i, j), 0.0), mul(tmp, a.get((k, j), 0.0)))
            a[(k, i)] = tmp
    return a


def solve_factored(t: HingeTree, a: dict, rhs):
    """Solve with the factor of :func:`factor_tree` (``mj_solveM``)."""
    anc = _tree_ancestors(t)
    x = list(rhs)
    for i in range(t.nv - 1, -1, -1):
        for j in anc[i]:
            x[j] = sub(x[j], mul(a.get((i, j), 0.0), x[i]))
    x = [x[i] / a[(i, i)] for i in range(t.nv)]
    for i in range(t.nv):
        for j in anc[i]:
            x[i] = sub(x[i], mul(a.get((i, j), 0.0), x[j]))
    return x


def solve_tree(t: HingeTree, entries: dict, diagonal, rhs):
    """Solve ``(M + diag(diagonal)) x = rhs`` by MuJoCo's no-fill-in tree LDL (``mj_factorM``,
    ``mj_solveM``): M's nonzeros lie on dof-ancestor pairs, so the factor does too."""
    return solve_factored(t, factor_tree(t, entries, diagonal), rhs)


# ---- the public per-particle functions ----------------------------------------------------------
def static_torque(t: HingeTree, q, stiffness, qpos_spring):
    """Net joint torque at rest (spring minus gravity bias) [nv] for angles ``q`` [nv]."""
    qs = [q[i] for i in range(t.nv)]
    kin = kinematics(t, qs)
    bias = bias_minus_applied(t, kin, [0.0] * t.nv)
    spring = [mul(-stiffness[i], sub(qs[i], qpos_spring[i])) for i in range(t.nv)]
    return jnp.stack([jnp.asarray(sub(s, b)) for s, b in zip(spring, bias)])


class StepOutput(NamedTuple):
    """Tuples of scalars; the caller decides the loop-carry layout. Stacked (``jnp.stack``), XLA
    fuses a concatenate that recomputes shared terms per output component; as separate scalars
    it emits one multi-output loop but carries nv buffers. ``benchmarks/carry_probe.py`` (bare
    step loop) and ``BENCHMARKS.md`` (whole rollouts) measure both."""

    qpos: tuple  # nv joint angles after the step
    qvel: tuple  # nv joint speeds after the step
    lever: tuple  # world (C - com) at the start of this step, for the next step's torque
    site: tuple  # world grasp point at the start of this step


def step(
    t: HingeTree,
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
    kin: Kinematics | None = None,
):
    """One ``implicitfast`` step of one particle; ``qpos``, ``qvel``: sequences of nv scalars.
    ``kin``: ``kinematics(t, qpos)`` if the caller already has it (the same arithmetic).

    ``force`` is the world force applied at body ``body``'s centre of mass with torque
    ``lever x force``: ``lever`` comes from the previous step's kinematics, as when a MuJoCo
    user writes ``xfrc_applied`` from ``site_xpos - xipos`` between ``mj_step`` calls (that is
    what the MJX path and the C reference do, so all three agree step for step)."""
    nv = t.nv
    q = [qpos[i] for i in range(nv)]
    v = [qvel[i] for i in range(nv)]
    kin = kinematics(t, q) if kin is None else kin
    site = point(kin, body, site_local)
    torque = cross(lever, force)
    rhs = bias_minus_applied(t, kin, v, body, force, torque)
    smooth = [
        sub(sub(mul(-stiffness[i], sub(q[i], qpos_spring[i])), mul(damping[i], v[i])), rhs[i])
        for i in range(nv)
    ]
    diag = [add(t.armature[i], mul(dt, damping[i])) for i in range(nv)]
    qacc = solve_tree(t, mass_matrix(t, kin), diag, smooth)
    v_new = [add(v[i], mul(dt, qacc[i])) for i in range(nv)]
    q_new = [add(q[i], mul(dt, v_new[i])) for i in range(nv)]
    return StepOutput(
        qpos=tuple(q_new), qvel=tuple(v_new), lever=vsub(site, kin.com[body]), site=site
    )
