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

Arithmetic is structure-of-arrays: a 3-vector is a tuple of three [W] arrays (one entry per
body of the level), a 6x6 inertia 36 of them, and the element functions of
:mod:`treeinfer.sim.fused` (``add``, ``mul``, ``cross`` ...) combine them, folding the
constants that are zero or one for a whole level. XLA then sees elementwise arithmetic on
[particles, W] arrays, which it fuses into few loops; [W, 6, 6] arrays with reductions over the
trailing axes were 25x slower on the CPU (many small unfused kernels).

All functions work on one particle; ``vmap`` batches them.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import fused as hd
from .fused import HingeTree, add, cross, dot, matmul, matvec, mul, sub, total


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


# ---- structure-of-arrays elements ---------------------------------------------------------------
def _elem(a, dtype):
    """A level constant [W] as an element: 0.0 / 1.0 when it is that for every body (folds),
    else a JAX array."""
    a = np.asarray(a, float)
    if np.all(a == 0.0):
        return 0.0
    if np.all(a == 1.0):
        return 1.0
    return jnp.asarray(a, dtype)


def _vec(a, dtype):
    """[W, 3] constants -> tuple of 3 elements."""
    return tuple(_elem(a[:, i], dtype) for i in range(3))


def _mat(a, dtype):
    """[W, 3, 3] constants -> 3x3 tuple of elements."""
    return tuple(tuple(_elem(a[:, i, j], dtype) for j in range(3)) for i in range(3))


def _take(x, idx):
    """Element ``x`` (float or [W_prev] array) at the parent indices ``idx`` (numpy [W])."""
    if isinstance(x, float) or idx is None:
        return x
    if len(idx) == x.shape[0] and np.array_equal(idx, np.arange(len(idx))):
        return x
    return x[idx]


def _take_all(xs, idx):
    return jax.tree_util.tree_map(lambda x: _take(x, idx), xs)


def _to_parents(elems: list, idx, width: int, n_parents: int, dtype) -> list:
    """Sum each element (float or [width] array) into its parent's row -> [n_parents] each, in
    one scatter for all elements."""
    if len(idx) == n_parents and np.array_equal(idx, np.arange(n_parents)):
        return list(elems)
    live = [i for i, e in enumerate(elems) if not (isinstance(e, float) and e == 0.0)]
    out = [0.0] * len(elems)
    if not live:
        return out
    stacked = jnp.stack([jnp.broadcast_to(jnp.asarray(elems[i], dtype), (width,)) for i in live])
    summed = jax.ops.segment_sum(stacked.T, jnp.asarray(idx), num_segments=n_parents).T
    for k, i in enumerate(live):
        out[i] = summed[k]
    return out


def _mv6(m, x):
    return tuple(total(*(mul(m[i][k], x[k]) for k in range(6))) for i in range(6))


def _dot6(a, b):
    return total(*(mul(x, y) for x, y in zip(a, b)))


def _crm(v, u):
    """Spatial motion cross product ``v x u`` of 6-vectors [angular; linear at the origin]."""
    w, vo, uw, uo = v[:3], v[3:], u[:3], u[3:]
    return cross(w, uw) + hd.vadd(cross(w, uo), cross(vo, uw))


def _crf(v, f):
    """Spatial force cross product ``v x* f`` (f = [moment about the origin; force])."""
    w, vo, fn, ff = v[:3], v[3:], f[:3], f[3:]
    return hd.vadd(cross(w, fn), cross(vo, ff)) + cross(w, ff)


# ---- kinematics ---------------------------------------------------------------------------------
class _Frames(NamedTuple):
    rot: tuple  # 3x3 elements, world orientation
    pos: tuple  # 3 elements, m
    com: tuple  # 3 elements, m
    anchor: tuple  # 3 elements, m
    axis: tuple  # 3 elements (zeros for welded bodies)


def _frames(lay: Layout, q) -> list[_Frames]:
    dtype = q.dtype
    qpad = jnp.concatenate([q, jnp.zeros((1,), dtype)])
    out: list[_Frames] = []
    for lev in lay.levels:
        if lev.parent is None:
            x, r = _vec(lev.body_pos, dtype), _mat(lev.body_rot, dtype)
        else:
            prev = out[-1]
            rp, xp = _take_all(prev.rot, lev.parent), _take_all(prev.pos, lev.parent)
            x = hd.vadd(xp, matvec(rp, _vec(lev.body_pos, dtype)))
            r = matmul(rp, _mat(lev.body_rot, dtype))
        jpos = _vec(lev.jnt_pos, dtype)
        anchor = hd.vadd(x, matvec(r, jpos))
        axis = matvec(r, _vec(lev.jnt_axis, dtype))
        angle = qpad[lev.dof] - jnp.asarray(lev.qpos0, dtype)
        sn, omc = jnp.sin(angle), 1.0 - jnp.cos(angle)
        k, k2 = _mat(lev.skew, dtype), _mat(lev.skew2, dtype)
        turn = tuple(
            tuple(total(float(i == j), mul(k[i][j], sn), mul(k2[i][j], omc)) for j in range(3))
            for i in range(3)
        )
        r = matmul(r, turn)
        x = hd.vsub(anchor, matvec(r, jpos))
        com = hd.vadd(x, matvec(r, _vec(lev.ipos, dtype)))
        out.append(_Frames(r, x, com, anchor, axis))
    return out


class LevelKinematics(NamedTuple):
    rot: jax.Array  # [W, 3, 3] world orientation
    pos: jax.Array  # [W, 3] m, world origin of each body frame
    com: jax.Array  # [W, 3] m, world centre of mass (xipos)
    anchor: jax.Array  # [W, 3] m, world joint anchor
    axis: jax.Array  # [W, 3] world joint axis (zeros for welded bodies)


def _stack_vec(v, w: int, dtype):
    return jnp.stack([jnp.broadcast_to(jnp.asarray(x, dtype), (w,)) for x in v], axis=-1)


def kinematics(lay: Layout, q) -> list[LevelKinematics]:
    """World frames of every body, per level, for joint angles ``q`` [nv] (``mj_kinematics``)."""
    q = jnp.asarray(q)
    out = []
    for lev, f in zip(lay.levels, _frames(lay, q)):
        w = len(lev.bodies)
        sv = lambda v: _stack_vec(v, w, q.dtype)
        rot = jnp.stack([sv(row) for row in f.rot], axis=-2)
        out.append(LevelKinematics(rot, sv(f.pos), sv(f.com), sv(f.anchor), sv(f.axis)))
    return out


def body_frame(lay: Layout, kin: list, body: int):
    """(rot [3, 3], pos [3], com [3]) of MuJoCo body ``body`` from :func:`kinematics`."""
    level, i = lay.where[body]
    k = kin[level]
    return k.rot[i], k.pos[i], k.com[i]


def _pick(v, i: int):
    """Entry ``i`` of each element of a tuple (floats stay)."""
    return tuple(x if isinstance(x, float) else x[i] for x in v)


def _spatial_inertia(lev: Level, f: _Frames, dtype):
    """6x6 elements: spatial inertia about the world origin, world axes, [angular; linear]."""
    rb = matmul(f.rot, _mat(lev.irot, dtype))
    inertia = _vec(lev.inertia, dtype)
    rbi = tuple(tuple(mul(rb[i][k], inertia[k]) for k in range(3)) for i in range(3))
    ic = tuple(
        tuple(total(*(mul(rbi[i][k], rb[j][k]) for k in range(3))) for j in range(3))
        for i in range(3)
    )
    m = _elem(lev.mass, dtype)
    c = f.com
    cc = dot(c, c)
    top_left = tuple(
        tuple(add(ic[i][j], mul(m, sub(cc if i == j else 0.0, mul(c[i], c[j])))) for j in range(3))
        for i in range(3)
    )
    cx = ((0.0, mul(-1.0, c[2]), c[1]), (c[2], 0.0, mul(-1.0, c[0])), (mul(-1.0, c[1]), c[0], 0.0))
    mcx = tuple(tuple(mul(m, cx[i][j]) for j in range(3)) for i in range(3))
    rows = [top_left[i] + mcx[i] for i in range(3)]
    rows += [  # bottom-left block: (m [c]x)^T
        tuple(mcx[i][j] for i in range(3)) + tuple(m if i == j else 0.0 for i in range(3))
        for j in range(3)
    ]
    return tuple(rows)


def _motion_subspace(f: _Frames):
    """6 elements: hinge motion subspace [axis; anchor x axis] (origin velocity per rad/s)."""
    return f.axis + cross(f.anchor, f.axis)


def _pad(x, value: float):
    return jnp.concatenate([x, jnp.full((1,), value, x.dtype)])


# ---- the public per-particle functions ----------------------------------------------------------
def gravity_bias(lay: Layout, frames: list[_Frames], dtype):
    """``qfrc_bias`` at zero velocity (gravity only) [nv]."""
    g = tuple(float(x) for x in lay.gravity)
    minus_g = tuple(-x for x in g)
    n = len(lay.levels)
    sub_f: list = [None] * n
    for lv in range(n - 1, -1, -1):
        lev, f = lay.levels[lv], frames[lv]
        m = _elem(lev.mass, dtype)
        own = tuple(mul(m, x) for x in cross(f.com, minus_g)) + tuple(mul(m, x) for x in minus_g)
        sub_f[lv] = own if sub_f[lv] is None else tuple(add(a, b) for a, b in zip(sub_f[lv], own))
        if lv > 0:
            w, wp = len(lev.bodies), len(lay.levels[lv - 1].bodies)
            sub_f[lv - 1] = tuple(_to_parents(list(sub_f[lv]), lev.parent, w, wp, dtype))
    parts = []
    for lev, f, sf in zip(lay.levels, frames, sub_f):
        b = _dot6(_motion_subspace(f), sf)
        parts.append(jnp.broadcast_to(jnp.asarray(b, dtype), (len(lev.bodies),)))
    return jnp.concatenate(parts)[lay.perm]


def static_torque(lay: Layout, q, stiffness, qpos_spring):
    """Net joint torque at rest (spring minus gravity bias) [nv] for angles ``q`` [nv]."""
    q = jnp.asarray(q)
    spring = -jnp.asarray(stiffness, q.dtype) * (q - jnp.asarray(qpos_spring, q.dtype))
    return spring - gravity_bias(lay, _frames(lay, q), q.dtype)


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
    force, lever, site_local = tuple(force), tuple(lever), tuple(site_local)
    frames = _frames(lay, q)
    b_level, b_index = lay.where[body]
    fb = frames[b_level]
    rot_b, pos_b, com_b = (
        tuple(_pick(row, b_index) for row in fb.rot),
        _pick(fb.pos, b_index),
        _pick(fb.com, b_index),
    )
    site = hd.vadd(pos_b, matvec(rot_b, site_local))
    # applied wrench at the grasp body: force at its com plus the lever torque, about the origin
    f_ext = hd.vadd(cross(lever, force), cross(com_b, force)) + force
    tau = _pad(-stiffness * (q - c(qpos_spring)) - damping * v, 0.0)
    diag = _pad(c(lay.armature) + dt * damping, 1.0)  # welded bodies: D = 1, s = 0
    vpad = _pad(v, 0.0)
    n = len(lay.levels)
    s_, c_, ia, pa, vel = [None] * n, [None] * n, [None] * n, [None] * n, [None] * n
    for lv, (lev, f) in enumerate(zip(lay.levels, frames)):  # velocities, root to leaves
        s = _motion_subspace(f)
        qd = vpad[lev.dof]
        sq = tuple(mul(x, qd) for x in s)
        if lev.parent is None:
            vel[lv], c_[lv] = sq, (0.0,) * 6
        else:
            vp = _take_all(vel[lv - 1], lev.parent)
            vel[lv], c_[lv] = tuple(add(a, b) for a, b in zip(vp, sq)), _crm(vp, sq)
        inertia = _spatial_inertia(lev, f, dtype)
        p = _crf(vel[lv], _mv6(inertia, vel[lv]))
        if lv == b_level:
            onehot = np.zeros(len(lev.bodies))
            onehot[b_index] = 1.0
            oh = _elem(onehot, dtype)
            p = tuple(sub(a, mul(oh, b)) for a, b in zip(p, f_ext))
        s_[lv], ia[lv], pa[lv] = s, inertia, p
    u_, d_, uu_ = [None] * n, [None] * n, [None] * n
    for lv in range(n - 1, -1, -1):  # articulated inertias and bias forces, leaves to root
        lev, s = lay.levels[lv], s_[lv]
        U = _mv6(ia[lv], s)
        D = add(_dot6(s, U), diag[lev.dof])
        u = sub(tau[lev.dof], _dot6(s, pa[lv]))
        u_[lv], d_[lv], uu_[lv] = u, D, U
        if lv > 0:
            ud = tuple(x / D if not isinstance(x, float) else mul(x, 1.0 / D) for x in U)
            ia_child = tuple(
                tuple(sub(ia[lv][i][j], mul(U[i], ud[j])) for j in range(6)) for i in range(6)
            )
            uod = u / D
            pa_child = tuple(
                add(add(a, b), mul(x, uod)) for a, b, x in zip(pa[lv], _mv6(ia_child, c_[lv]), U)
            )
            w, wp = len(lev.bodies), len(lay.levels[lv - 1].bodies)
            flat = [e for row in ia_child for e in row] + list(pa_child)
            up = _to_parents(flat, lev.parent, w, wp, dtype)
            ia[lv - 1] = tuple(
                tuple(add(ia[lv - 1][i][j], up[6 * i + j]) for j in range(6)) for i in range(6)
            )
            pa[lv - 1] = tuple(add(a, b) for a, b in zip(pa[lv - 1], up[36:]))
    a0 = (0.0, 0.0, 0.0) + tuple(-float(x) for x in lay.gravity)
    acc, qdd = [None] * n, []
    for lv, lev in enumerate(lay.levels):  # accelerations, root to leaves
        ap = a0 if lev.parent is None else _take_all(acc[lv - 1], lev.parent)
        ap = tuple(add(a, b) for a, b in zip(ap, c_[lv]))
        a = (u_[lv] - _dot6(uu_[lv], ap)) / d_[lv]
        acc[lv] = tuple(add(x, mul(y, a)) for x, y in zip(ap, s_[lv]))
        qdd.append(jnp.broadcast_to(a, (len(lev.bodies),)))
    qacc = jnp.concatenate(qdd)[lay.perm]
    v_new = v + dt * qacc
    stack3 = lambda t: jnp.stack([c(x) for x in t])
    lever_new = hd.vsub(site, com_b)
    return StepOutput(qpos=q + dt * v_new, qvel=v_new, lever=stack3(lever_new), site=stack3(site))
