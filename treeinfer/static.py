"""Quasi-static pushes: the equilibrium of the hinge tree under each force sample.

A slow displacement-controlled test (a stepper pushing a stem, samples every 0.1-1 s for tens
of seconds) passes through equilibria: inertia and damping leave no trace in it. For such data
the *static model* replaces the rollout: for every force sample ``f_t`` it solves

    0 = -Kp (q - q_spring) - qfrc_bias(q) + J_C(q)^T (f_t d)

(spring, gravity, and the point force ``f_t`` along the unit direction ``d`` at the grasp point
C, whose generalised force is the transpose of C's positional Jacobian times the force), by the
clipped Newton iteration of the simulator's settle solver (:func:`treeinfer.sim.settle`)
with exact Jacobians from ``jax.jacfwd``. The samples are independent (no time stepping), so
they are solved in one ``vmap`` over particles x profiles x samples. The observed displacement
is ``tau_t = (C(q_t) - C(q_rest)) . d``. Only stiffness is identified; damping is not
(:func:`damping_note`).

:func:`natural_periods` and :func:`suggest_static` tell when a data set is quasi-static (its
sample interval far longer than the branch's slowest natural period), and
:func:`parameter_layout` gives the theta layout for inferring stiffness only
(``inference: {parameters: [kp]}``) with any model.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .errors import ConfigError
from .sim import Rollout, Simulator, velocity
from .sim import fused as hd
from .tree import PARAMETERS, parse_parameters

__all__ = [
    "MODEL_KINDS",
    "Model",
    "PARAMETERS",
    "QUASI_STATIC_RATIO",
    "ParameterLayout",
    "damping_note",
    "natural_periods",
    "parameter_layout",
    "model_for",
    "model_rollout",
    "model_with_pulls",
    "parse_model_kind",
    "parse_parameters",
    "quasi_static_notice",
    "run_tree",
    "static_rollout",
    "suggest_static",
    "tree_layout",
]

MODEL_KINDS = ("dynamic", "static")

QUASI_STATIC_RATIO = 5.0  # sample interval / slowest natural period above which data are static
NEWTON_CLIP = 0.2  # rad per Newton step, as the simulator's settle solver


# ----------------------------------------------------------------------------- the static model


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
    starts, ends = jnp.asarray(np.asarray(starts), dtype), jnp.asarray(np.asarray(ends), dtype)
    if grasp_fraction is None:
        tree_site = np.asarray(sim.mj_model.site_pos[sim.grasp_site], float)
        sites = jnp.asarray(
            np.asarray(
                [
                    tree_site if body == sim.grasp_body else e
                    for body, e in zip(bodies, np.asarray(ends))
                ]
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


def _static_group(sim: Simulator, body: int, n_iter: int, kp, forces, sites, dirs):
    """[P, B, T] displacements and [P, B] flags for profiles grasped on one body."""
    t = sim.hinge_tree
    nv = t.nv
    dtype = kp.dtype

    moving = hd._ancestor_dofs(t, body)  # dofs whose hinge moves the grasp point

    def point(q, site):
        kin = hd.kinematics(t, [q[i] for i in range(nv)])
        p = hd.point(kin, body, tuple(site[i] for i in range(3)))
        return jnp.stack([jnp.asarray(x, dtype) for x in p])

    def per_params(kp_i):
        stiffness, spring = _gains(sim, kp_i)

        def residual(q, f, site, d):
            """Static torque plus J_C^T (f d): a hinge's column of the point Jacobian is
            ``axis x (C - anchor)``, so its generalised force is ``axis . ((C - anchor) x F)``
            (scalar arithmetic: compiles far faster than a nested ``jacfwd``)."""
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

        def solve(f, site, d, q0):
            def newton(carry, i):
                q, r_first, _ = carry
                r = residual(q, f, site, d)
                jac = jax.jacfwd(residual)(q, f, site, d)
                dq = jnp.clip(-jnp.linalg.solve(jac, r), -NEWTON_CLIP, NEWTON_CLIP)
                return (q + dq, jnp.where(i == 0, r, r_first), r), None

            zero = jnp.zeros(nv, dtype)
            (q, r_first, r_last), _ = jax.lax.scan(newton, (q0, zero, zero), jnp.arange(n_iter))
            scale = 1.0 + jnp.max(jnp.abs(r_first))
            ok = jnp.all(jnp.isfinite(q)) & (
                jnp.max(jnp.abs(r_last)) <= sim.settle_tolerance * scale
            )
            return q, ok

        zero = jnp.zeros(nv, dtype)
        q_rest, ok_rest = solve(jnp.asarray(0.0, dtype), sites[0], dirs[0], zero)

        def per_profile(f_row, site, d):
            q, ok = jax.vmap(lambda f: solve(f, site, d, q_rest))(f_row)  # [T, nv], [T]
            c = jax.vmap(lambda qq: point(qq, site))(q)  # [T, 3]
            tau = (c - point(q_rest, site)) @ d
            good = jnp.all(ok) & ok_rest & jnp.all(jnp.isfinite(tau))
            good = good & jnp.all(jnp.abs(tau) < sim.max_displacement)
            return tau, good

        return jax.vmap(per_profile)(forces, sites, dirs)

    return jax.vmap(per_params)(kp)


# ----------------------------------------------------------------------------- detection


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

    from .sim.reference import settle_reference

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


# ----------------------------------------------------------------------------- parameter layout


class ParameterLayout(NamedTuple):
    """Which gains the samplers move, and how ``theta`` maps to (Kp, Kd).

    ``theta = [log Kp_1..R]`` (+ ``[log Kd_1..R]`` when ``"kd"`` is inferred); a gain that is
    not inferred is held at ``fixed_kd`` [R] N m s/rad.
    """

    parameters: tuple[str, ...]
    joints: tuple[str, ...]
    fixed_kd: np.ndarray
    lower: np.ndarray  # [D] log units
    upper: np.ndarray  # [D] log units

    @property
    def n_joints(self) -> int:
        return len(self.joints)

    @property
    def dim(self) -> int:
        return len(self.parameters) * self.n_joints

    @property
    def infers_damping(self) -> bool:
        return "kd" in self.parameters

    @property
    def labels(self) -> list[str]:
        out = [f"Kp[{n}]" for n in self.joints]
        if self.infers_damping:
            out += [f"Kd[{n}]" for n in self.joints]
        return out

    def gains(self, theta):
        """``theta [..., D]`` -> (Kp [..., R], Kd [..., R]) in natural units (jax)."""
        r = self.n_joints
        kp = jnp.exp(theta[..., :r])
        if self.infers_damping:
            kd = jnp.exp(theta[..., r : 2 * r])
        else:
            kd = jnp.broadcast_to(jnp.asarray(self.fixed_kd, kp.dtype), kp.shape)
        return kp, kd

    def theta(self, kp, kd=None) -> np.ndarray:
        """Inverse of :meth:`gains` (numpy); ``kd`` is needed only when it is inferred."""
        kp = np.asarray(kp, float)
        parts = [np.log(kp)]
        if self.infers_damping:
            if kd is None:
                raise ConfigError("theta: Kd is inferred in this layout; give kd")
            parts.append(np.log(np.asarray(kd, float)))
        return np.concatenate(parts, axis=-1)

    def full_theta(self, theta):
        """``[..., D]`` -> the full ``[..., 2R]`` (log Kp, log Kd) layout other code expects."""
        if self.infers_damping:
            return theta
        kd = jnp.broadcast_to(
            jnp.log(jnp.asarray(self.fixed_kd, theta.dtype)), theta.shape[:-1] + (self.n_joints,)
        )
        return jnp.concatenate([theta, kd], axis=-1)


def parameter_layout(tree, parameters=PARAMETERS, fixed_kd=None) -> ParameterLayout:
    """Theta layout for ``tree``'s inferred joints.

    Args:
        parameters: ``("kp",)`` (stiffness only) or ``("kp", "kd")``.
        fixed_kd: [R] or scalar N m s/rad held when Kd is not inferred; default the geometric
            mean of each joint's Kd prior bounds (it matters only for dynamic models).
    """
    params = parse_parameters(list(parameters))
    joints = tuple(tree.inferred)
    kd_bounds = np.asarray([tree.bounds[n].kd for n in joints], float)
    if fixed_kd is None:
        fixed = np.sqrt(kd_bounds[:, 0] * kd_bounds[:, 1])
    else:
        fixed = np.broadcast_to(np.asarray(fixed_kd, float), (len(joints),)).copy()
        if not np.all(np.isfinite(fixed)) or np.any(fixed <= 0):
            raise ConfigError(f"fixed_kd: must be finite and positive, got {fixed.tolist()}")
    lo, hi = tree.bounds_array()
    keep = slice(0, len(joints)) if params == ("kp",) else slice(0, 2 * len(joints))
    return ParameterLayout(params, joints, fixed, np.log(lo[keep]), np.log(hi[keep]))


def damping_note(layout: ParameterLayout | None = None, model_kind: str = "static") -> str:
    """The line a report prints about damping when it is not identified."""
    if model_kind == "static":
        return (
            "damping (Kd): not identified (static model: equilibria carry no damping information)"
        )
    if layout is not None and not layout.infers_damping:
        vals = ", ".join(f"{v:.3g}" for v in layout.fixed_kd)
        return f"damping (Kd): not inferred, held at [{vals}] N m s/rad"
    return ""


# ----------------------------------------------------------------------------- model of a run


def parse_model_kind(value, source: str = "--model-kind") -> str:
    """``dynamic`` (the rollout, the default) or ``static`` (equilibria, stiffness only)."""
    kind = "dynamic" if value is None else str(value).strip().lower()
    if kind not in MODEL_KINDS:
        raise ConfigError(f"{source}: expected one of {', '.join(MODEL_KINDS)}, got {value!r}")
    return kind


def run_tree(tree, model_kind: str = "dynamic"):
    """The tree a run infers: with the static model, stiffness only (``parameters: [kp]``), so
    that the run folder's ``tree.yaml`` and its parameter labels say what was inferred."""
    import dataclasses

    if parse_model_kind(model_kind) == "static" and tuple(tree.parameters) != ("kp",):
        return dataclasses.replace(tree, parameters=("kp",))
    return tree


def tree_layout(tree) -> ParameterLayout:
    """:func:`parameter_layout` of ``tree.parameters``; damping, when not inferred, is held at
    each joint's own ``kd`` in the tree file where given, else at its prior box's geometric
    mean."""
    joints = tuple(tree.inferred)
    lo, hi = (np.asarray([tree.bounds[n].kd[i] for n in joints], float) for i in (0, 1))
    own = [tree.branch(n).kd for n in joints]
    fixed = np.asarray([k if k is not None else math.sqrt(a * b) for k, a, b in zip(own, lo, hi)])
    return parameter_layout(tree, getattr(tree, "parameters", PARAMETERS), fixed_kd=fixed)


class Model(NamedTuple):
    """How a run maps its particles to predicted displacements.

    Attributes:
        kind: ``"dynamic"`` (time-stepped rollout) or ``"static"`` (:func:`static_rollout`).
        layout: the theta layout (:func:`tree_layout`).
        tree: the tree (static model: lengths of grasped branches, pull directions).
        direction: None (along gravity) or [3] / [B, 3] world vectors (static model only).
        grasp_branch: None (the tree's) or B names (static model only).
    """

    kind: str
    layout: ParameterLayout
    tree: object = None
    direction: object = None
    grasp_branch: object = None

    @property
    def labels(self) -> tuple[str, ...]:
        return tuple(self.layout.labels)


def model_for(tree, model_kind: str = "dynamic", direction=None, grasp_branch=None) -> Model:
    """The :class:`Model` of a run from its tree and ``--model-kind``. The static model pulls
    along ``direction`` (default: the tree file's ``pull.direction``, resolved on the grasp
    branch by :func:`treeinfer.pulls.pull_direction`)."""
    kind = parse_model_kind(model_kind)
    tree = run_tree(tree, kind)
    if kind == "static" and direction is None:
        from .pulls import pull_direction

        direction = pull_direction(tree, tree.grasp_branch, getattr(tree, "pull_direction", "down"))
    return Model(kind, tree_layout(tree), tree, direction, grasp_branch)


def model_rollout(sim: Simulator, model: Model | None, theta, forces, grasp_fraction=None):
    """Predicted :class:`~treeinfer.sim.Rollout` [P, B, T] of particles ``theta [P, D]`` (the
    model's layout; the full ``[log Kp, log Kd]`` when ``model`` is None) under ``forces
    [B, T]`` N. The dynamic model runs :func:`treeinfer.sim.simulate`, the static one
    :func:`static_rollout` (Kd plays no role there)."""
    from .sim import simulate

    theta = jnp.atleast_2d(jnp.asarray(theta))
    if model is None:
        r = sim.n_joints
        return simulate(
            sim, jnp.exp(theta[..., :r]), jnp.exp(theta[..., r:]), forces, grasp_fraction
        )
    kp, kd = model.layout.gains(theta)
    if model.kind == "static":
        return static_rollout(
            sim, kp, forces, grasp_fraction, model.direction, model.grasp_branch, model.tree
        )
    return simulate(sim, kp, kd, forces, grasp_fraction)


def model_with_pulls(model: Model, data_dir, sources: Sequence[str], grasp_fraction=None):
    """The static model with each recording's own pull from ``data_dir``'s ``pulls.yaml``
    (grasped branch, grasp point, direction: :func:`treeinfer.pulls.load_data_pulls`).

    Args:
        sources: the trajectories' file names, in stacked order.
        grasp_fraction: an explicit ``--grasp-fraction`` (overrides the files' points).

    Returns:
        (model, grasp fractions [B] or ``grasp_fraction``); the model unchanged (and
        ``grasp_fraction``) when it is not static or the folder has no ``pulls.yaml``.
    """
    from pathlib import Path

    from .pulls import PULLS_FILE, load_data_pulls, stack_resolved

    if model is None or model.kind != "static" or data_dir is None:
        return model, grasp_fraction
    if not (Path(data_dir) / PULLS_FILE).is_file():
        return model, grasp_fraction
    resolved = load_data_pulls(data_dir, model.tree, [Path(s).name for s in sources])
    branches, fractions, directions = stack_resolved(resolved, model.tree)
    model = model._replace(direction=directions, grasp_branch=branches)
    if grasp_fraction is not None:
        return model, grasp_fraction
    return model, fractions
