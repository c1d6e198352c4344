"""The fused hinge-tree step laid out level by level, for big trees.

:mod:`treeinfer.sim.fused` writes MuJoCo's ``implicitfast`` step as scalar arithmetic unrolled
over every body and every mass-matrix entry: the fastest step for a few joints, but its program
grows with (joints x tree depth)^2 and a 120-joint tree took minutes and gigabytes to compile.
Here the same step works on arrays of one *depth level* of the tree at a time (all bodies at
depth L side by side), so the program has a few dozen array operations per level and its size
grows with the tree's depth, not its joint count:

* kinematics root to leaves, as ``mj_kinematics`` (the same frames as :func:`fused.kinematics`);
* the joint accelerations by Featherstone's articulated-body algorithm (ABA) in world-aligned
  spatial coordinates about the world origin (so no frame transforms between levels): velocities
  and velocity-product accelerations root to leaves, articulated inertias and bias forces leaves
  to root (children summed into their parents with ``segment_sum``), accelerations root to leaves.

The ABA solves ``(M + diag(armature + dt * damping)) qacc = qfrc_passive + qfrc_applied -
qfrc_bias`` exactly (a diagonal term added to M enters the ABA as a joint-space inertia in
``D_i``, Featherstone 2008, section 7.3), which is the system MuJoCo's ``implicitfast`` solves by
its tree LDL: the two agree to rounding (``tests/test_hinge_dynamics.py`` checks 1e-10 against
``mujoco.mj_step`` in float64). Why ABA rather than the LDL: the LDL's work and program grow with
the sum of squared dof depths, the ABA's linearly with the joints, and its passes vectorise per
level without index bookkeeping.

Welded (joint-less) bodies take part with a zero motion subspace and ``D = 1``: they add their
inertia to their parent and get no acceleration of their own.

All functions work on one particle (arrays over the tree's bodies); ``vmap`` batches them.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .fused import HingeTree


class Level(NamedTuple):
    """The bodies at one depth of the tree (numpy constants, W bodies)."""

    bodies: np.ndarray  # [W] MuJoCo body indices
    parent: np.ndarray | None  # [W] index of each parent in the previous level; None at depth 0
    dof: np.ndarray  # [W] dof of the body's hinge, or nv for a welded body
    body_pos: np.ndarray  # [W, 3] m
    body_rot: np.ndarray  # [W, 3, 3]
    jnt_pos: np.ndarray  # [W, 3] m
    jnt_axis: np.ndarray  # [W, 3]
    skew: np.ndarray  # [W, 3, 3] cross-product matrix of the joint axis
    skew2: np.ndarray  # [W, 3, 3] its square
    ipos: np.ndarray  # [W, 3] m
    irot: np.ndarray  # [W, 3, 3]
    inertia: np.ndarray  # [W, 3] kg m^2, principal moments
    mass: np.ndarray  # [W] kg
    qpos0: np.ndarray  # [W] rad (0 for welded bodies)


class Layout(NamedTuple):
    """A :class:`~treeinfer.sim.fused.HingeTree` grouped by depth."""

    levels: tuple  # of Level, root level first
    where: dict  # MuJoCo body index -> (level, index within the level)
    perm: np.ndarray  # [nv] index of each dof's body in the concatenated levels
    armature: np.ndarray  # [nv] kg m^2
    gravity: np.ndarray  # [3] m/s^2
    nv: int

    @property
    def depth(self) -> int:
        return len(self.levels)


@functools.lru_cache(maxsize=64)
def layout(t: HingeTree) -> Layout:
    """Group the bodies of ``t`` by depth (cached: ``t`` is a hashable tuple of constants)."""
    nb = t.nbody
    depth = [0] * (nb + 1)
    for b in range(1, nb + 1):
        p = t.parent[b - 1]
        depth[b] = 0 if p == 0 else depth[p] + 1
    levels, where = [], {}
    for d in range(max(depth[1:]) + 1 if nb else 0):
        bodies = [b for b in range(1, nb + 1) if depth[b] == d]
        for i, b in enumerate(bodies):
            where[b] = (d, i)
        parent = None if d == 0 else np.array([where[t.parent[b - 1]][1] for b in bodies])
        axis = np.array([t.jnt_axis[b - 1] for b in bodies], float)
        skew = np.zeros((len(bodies), 3, 3))
        skew[:, 0, 1], skew[:, 0, 2] = -axis[:, 2], axis[:, 1]
        skew[:, 1, 0], skew[:, 1, 2] = axis[:, 2], -axis[:, 0]
        skew[:, 2, 0], skew[:, 2, 1] = -axis[:, 1], axis[:, 0]
        dofs = np.array([t.dof[b - 1] if t.dof[b - 1] >= 0 else t.nv for b in bodies])
        levels.append(
            Level(
                bodies=np.array(bodies),
                parent=parent,
                dof=dofs,
                body_pos=np.array([t.body_pos[b - 1] for b in bodies], float),
                body_rot=np.array([t.body_rot[b - 1] for b in bodies], float),
                jnt_pos=np.array([t.jnt_pos[b - 1] for b in bodies], float),
                jnt_axis=axis,
                skew=skew,
                skew2=skew @ skew,
                ipos=np.array([t.ipos[b - 1] for b in bodies], float),
                irot=np.array([t.irot[b - 1] for b in bodies], float),
                inertia=np.array([t.inertia[b - 1] for b in bodies], float),
                mass=np.array([t.mass[b - 1] for b in bodies], float),
                qpos0=np.array([t.qpos0[d_] if d_ < t.nv else 0.0 for d_ in dofs], float),
            )
        )
    offsets = np.cumsum([0] + [len(lv.bodies) for lv in levels])
    perm = np.array([offsets[where[b][0]] + where[b][1] for b in t.dof_body], dtype=int)
    return Layout(
        levels=tuple(levels),
        where=where,
        perm=perm.reshape(t.nv),
        armature=np.asarray(t.armature, float),
        gravity=np.asarray(t.gravity, float),
        nv=t.nv,
    )


# ---- small linear algebra on trailing axes (elementwise, so XLA fuses it) -----------------------
def _mv(m, v):
    return jnp.sum(m * v[..., None, :], axis=-1)


def _mm(a, b):
    return jnp.sum(a[..., :, :, None] * b[..., None, :, :], axis=-2)


def _skew(c):
    z = jnp.zeros_like(c[..., 0])
    x, y, w = c[..., 0], c[..., 1], c[..., 2]
    rows = [jnp.stack(r, axis=-1) for r in ((z, -w, y), (w, z, -x), (-y, x, z))]
    return jnp.stack(rows, axis=-2)


def _crm(v, u):
    """Spatial motion cross product ``v x u`` of 6-vectors [angular; linear at the origin]."""
    w, vo, uw, uo = v[..., :3], v[..., 3:], u[..., :3], u[..., 3:]
    return jnp.concatenate([jnp.cross(w, uw), jnp.cross(w, uo) + jnp.cross(vo, uw)], axis=-1)


def _crf(v, f):
    """Spatial force cross product ``v x* f`` (f = [moment about the origin; force])."""
    w, vo, fn, ff = v[..., :3], v[..., 3:], f[..., :3], f[..., 3:]
    return jnp.concatenate([jnp.cross(w, fn) + jnp.cross(vo, ff), jnp.cross(w, ff)], axis=-1)


def _gather(x, idx):
    """Rows ``idx`` (numpy) of ``x``; a slice when they are 0..n-1 (no gather op)."""
    if idx is None:
        return x
    if len(idx) == x.shape[0] and np.array_equal(idx, np.arange(len(idx))):
        return x
    return x[idx]


def _to_parents(x, idx, n_parents: int):
    """Sum rows of ``x`` into their parents' rows (``idx`` [W] numpy) -> [n_parents, ...]."""
    if len(idx) == n_parents and np.array_equal(idx, np.arange(n_parents)):
        return x
    return jax.ops.segment_sum(x, jnp.asarray(idx), num_segments=n_parents)


# ---- kinematics ---------------------------------------------------------------------------------
class LevelKinematics(NamedTuple):
    rot: jax.Array  # [W, 3, 3] world orientation
    pos: jax.Array  # [W, 3] m, world origin of each body frame
    com: jax.Array  # [W, 3] m, world centre of mass (xipos)
    anchor: jax.Array  # [W, 3] m, world joint anchor
    axis: jax.Array  # [W, 3] world joint axis (zeros for welded bodies)


def kinematics(lay: Layout, q) -> list[LevelKinematics]:
    """World frames of every body, per level, for joint angles ``q`` [nv] (``mj_kinematics``)."""
    q = jnp.asarray(q)
    dtype = q.dtype
    c = lambda a: jnp.asarray(a, dtype)
    qpad = jnp.concatenate([q, jnp.zeros((1,), dtype)])
    out: list[LevelKinematics] = []
    for lev in lay.levels:
        if lev.parent is None:
            x, r = c(lev.body_pos), c(lev.body_rot)
        else:
            prev = out[-1]
            rp = _gather(prev.rot, lev.parent)
            x = _gather(prev.pos, lev.parent) + _mv(rp, c(lev.body_pos))
            r = _mm(rp, c(lev.body_rot))
        anchor = x + _mv(r, c(lev.jnt_pos))
        axis = _mv(r, c(lev.jnt_axis))
        angle = (qpad[lev.dof] - c(lev.qpos0))[:, None, None]
        turn = c(np.eye(3)) + jnp.sin(angle) * c(lev.skew) + (1.0 - jnp.cos(angle)) * c(lev.skew2)
        r = _mm(r, turn)
        x = anchor - _mv(r, c(lev.jnt_pos))
        out.append(LevelKinematics(r, x, x + _mv(r, c(lev.ipos)), anchor, axis))
    return out


def body_frame(lay: Layout, kin: list[LevelKinematics], body: int):
    """(rot [3, 3], pos [3], com [3]) of MuJoCo body ``body``."""
    level, i = lay.where[body]
    k = kin[level]
    return k.rot[i], k.pos[i], k.com[i]


def _spatial_inertia(lev: Level, k: LevelKinematics, dtype):
    """[W, 6, 6] spatial inertia about the world origin, world axes, [angular; linear]."""
    rb = _mm(k.rot, jnp.asarray(lev.irot, dtype))
    ic = _mm(rb * jnp.asarray(lev.inertia, dtype)[:, None, :], jnp.swapaxes(rb, -1, -2))
    m = jnp.asarray(lev.mass, dtype)[:, None, None]
    cx = _skew(k.com)
    mcx = m * cx
    top = jnp.concatenate([ic - _mm(mcx, cx), mcx], axis=-1)
    bottom = jnp.concatenate([-mcx, m * jnp.eye(3, dtype=dtype)], axis=-1)
    return jnp.concatenate([top, bottom], axis=-2)


def _motion_subspace(k: LevelKinematics):
    """[W, 6] hinge motion subspace [axis; anchor x axis] (the origin's velocity per rad/s)."""
    return jnp.concatenate([k.axis, jnp.cross(k.anchor, k.axis)], axis=-1)


def _pad(x, value: float):
    return jnp.concatenate([x, jnp.full((1,), value, x.dtype)])


# ---- the public per-particle functions ----------------------------------------------------------
def gravity_bias(lay: Layout, kin: list[LevelKinematics], dtype):
    """``qfrc_bias`` at zero velocity (gravity only) [nv]."""
    g = jnp.asarray(lay.gravity, dtype)
    n = len(lay.levels)
    sub = [None] * n
    for lv in range(n - 1, -1, -1):
        lev, k = lay.levels[lv], kin[lv]
        m = jnp.asarray(lev.mass, dtype)[:, None]
        f = jnp.concatenate([m * jnp.cross(k.com, -g), -m * g], axis=-1)  # I [0; -g]
        sub[lv] = f if sub[lv] is None else sub[lv] + f
        if lv > 0:
            up = _to_parents(sub[lv], lev.parent, len(lay.levels[lv - 1].bodies))
            sub[lv - 1] = up
    bias = jnp.concatenate([jnp.sum(_motion_subspace(k) * s, -1) for k, s in zip(kin, sub)])
    return bias[lay.perm]


def static_torque(lay: Layout, q, stiffness, qpos_spring):
    """Net joint torque at rest (spring minus gravity bias) [nv] for angles ``q`` [nv]."""
    q = jnp.asarray(q)
    kin = kinematics(lay, q)
    spring = -jnp.asarray(stiffness, q.dtype) * (q - jnp.asarray(qpos_spring, q.dtype))
    return spring - gravity_bias(lay, kin, q.dtype)


class StepOutput(NamedTuple):
    qpos: jax.Array  # [nv] joint angles after the step
    qvel: jax.Array  # [nv] joint speeds after the step
    lever: jax.Array  # [3] world (C - com) at the start of this step
    site: jax.Array  # [3] world grasp point at the start of this step


def step(
    lay: Layout,
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
) -> StepOutput:
    """One ``implicitfast`` step of one particle, as :func:`treeinfer.sim.fused.step`.

    Args:
      qpos, qvel: [nv] rad, rad/s. stiffness, damping, qpos_spring: [nv] per dof.
      dt: s. body: MuJoCo index of the body the force acts on. site_local: [3] m, the grasp
        point in that body's frame. force: [3] N, world force at the body's centre of mass,
        with torque ``lever x force`` (``lever`` [3] m from the previous step, see fused.step).
    """
    q = jnp.asarray(qpos)
    dtype = q.dtype
    c = lambda a: jnp.asarray(a, dtype)
    v = c(qvel)
    stiffness, damping = c(stiffness), c(damping)
    force, lever = c(jnp.stack([c(f) for f in force])), c(jnp.stack([c(x) for x in lever]))
    site_local = jnp.stack([c(s) for s in site_local])
    kin = kinematics(lay, q)
    rot_b, pos_b, com_b = body_frame(lay, kin, body)
    site = pos_b + _mv(rot_b, site_local)
    # applied wrench at the grasp body: force at its com plus the lever torque, about the origin
    f_ext = jnp.concatenate([jnp.cross(lever, force) + jnp.cross(com_b, force), force])
    tau = _pad(-stiffness * (q - c(qpos_spring)) - damping * v, 0.0)
    diag = _pad(c(lay.armature) + dt * damping, 1.0)  # welded bodies: D = 1, s = 0
    vpad = _pad(v, 0.0)
    n = len(lay.levels)
    s_, c_, ia, pa, vel = [None] * n, [None] * n, [None] * n, [None] * n, [None] * n
    b_level, b_index = lay.where[body]
    for lv, (lev, k) in enumerate(zip(lay.levels, kin)):  # velocities, root to leaves
        s = _motion_subspace(k)
        sq = s * vpad[lev.dof][:, None]
        vp = None if lev.parent is None else _gather(vel[lv - 1], lev.parent)
        vel[lv] = sq if vp is None else vp + sq
        c_[lv] = jnp.zeros_like(sq) if vp is None else _crm(vp, sq)
        inertia = _spatial_inertia(lev, k, dtype)
        p = _crf(vel[lv], _mv(inertia, vel[lv]))
        if lv == b_level:
            p = p.at[b_index].add(-f_ext)
        s_[lv], ia[lv], pa[lv] = s, inertia, p
    u_, d_, uu_ = [None] * n, [None] * n, [None] * n
    for lv in range(n - 1, -1, -1):  # articulated inertias and bias forces, leaves to root
        lev, s = lay.levels[lv], s_[lv]
        U = _mv(ia[lv], s)
        D = jnp.sum(s * U, -1) + diag[lev.dof]
        u = tau[lev.dof] - jnp.sum(s * pa[lv], -1)
        u_[lv], d_[lv], uu_[lv] = u, D, U
        if lv > 0:
            ia_child = ia[lv] - U[:, :, None] * (U / D[:, None])[:, None, :]
            pa_child = pa[lv] + _mv(ia_child, c_[lv]) + U * (u / D)[:, None]
            w = len(lay.levels[lv - 1].bodies)
            ia[lv - 1] = ia[lv - 1] + _to_parents(ia_child, lev.parent, w)
            pa[lv - 1] = pa[lv - 1] + _to_parents(pa_child, lev.parent, w)
    a0 = jnp.concatenate([jnp.zeros(3, dtype), -c(lay.gravity)])
    acc, qdd = [None] * n, []
    for lv, lev in enumerate(lay.levels):  # accelerations, root to leaves
        ap = a0[None, :] if lev.parent is None else _gather(acc[lv - 1], lev.parent)
        ap = ap + c_[lv]
        a = (u_[lv] - jnp.sum(uu_[lv] * ap, -1)) / d_[lv]
        acc[lv] = ap + s_[lv] * a[:, None]
        qdd.append(a)
    qacc = jnp.concatenate(qdd)[lay.perm]
    v_new = v + dt * qacc
    return StepOutput(qpos=q + dt * v_new, qvel=v_new, lever=site - com_b, site=site)
