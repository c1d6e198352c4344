"""The batched branch simulator: MuJoCo MJX rolled out for P parameter sets x B force profiles.

One jittable function, :func:`simulate`, takes joint stiffness/damping for P parameter sets and B
force profiles and returns the downward displacement ``tau`` of the grasp point C from its
gravity-settled rest, its velocity ``tau_dot`` and a per-entry stability flag, each [P, B, ...],
in one batched call (``vmap`` over parameters and profiles; no Python loop over particles).

Physics, per parameter set:

1. **Settle.** A softer branch sags more under gravity, so each parameter set has its own rest
   pose. We find it by a *static solve*: Newton's method on the joint-space equilibrium
   ``qfrc_passive(q) - qfrc_bias(q) = 0`` at zero velocity (spring torque balances gravity),
   with the Jacobian from ``jax.jacfwd`` through MJX's position/velocity stages and a step clip
   for robustness. This is exact (no residual motion, unlike damped settling) and costs about
   ``settle_iterations * nv`` forward passes. The reference path does the same in MuJoCo C.
2. **Pull.** The force profile acts at C along the pull direction (gravity's by default, any
   unit vector per profile): the applied wrench at the grasp body's centre of mass is ``F`` plus
   the torque ``(C - com) x F``. Each observation interval ``dt_obs`` is split into ``substeps``
   simulation steps. *Force convention*: sample ``k`` of a profile is the force at
   ``t_k = k * dt_obs``. Between samples the force is interpolated linearly (first-order hold,
   ``force_interp="linear"``, the default: a sampled force signal is continuous) or held at
   sample ``k`` over ``[t_k, t_{k+1})`` (``force_interp="hold"``, for data that really are
   piecewise constant); each simulation step uses the force at its start time. After the last
   sample the force stays at the last sample's value (it never reaches an observation: the
   last one, ``tau[T-1]``, is at ``t_{T-1}``). The step size is chosen for stability
   (:func:`choose_substeps`) and, given the force profiles, for accuracy
   (:func:`treeinfer.sim.accuracy.choose_substeps_for_accuracy`).
3. **Observe.** ``tau[t] = (C(t * dt_obs) - C_rest) . d`` (metres, positive along the pull
   direction ``d``, i.e. downward by default);
   ``tau_dot`` is its time derivative by second-order finite differences (the same scheme used
   for recorded trajectories that have no velocity column, so both sides of the loss match).

Joint model: each hinge has ``stiffness = Kp``, ``damping = Kd`` and ``springref = 0``, so the
passive torque is ``-Kp * psi - Kd * psi_dot`` about the geometric rest angle, the paper's PD
controller with zero target. Integrator: ``implicitfast`` (damping implicit, so any Kd in the
prior is stable); the step is chosen from the stiffest corner of the prior box so that
``omega_max * dt <= 1.5`` at twice the box's upper Kp (explicit springs are stable for ``omega * dt < 2``).

Instability: a parameter set whose state becomes non-finite, whose joint speed exceeds
``max_joint_speed`` or whose displacement exceeds ``max_displacement`` (or that fails to
settle) gets ``stable = False`` and zeros in ``tau``/``tau_dot``; vmapped lanes are independent,
so it never affects other entries.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ConfigError, SimulationError, TreeFileError
from ..tree import Tree
from . import mjx as _mjx_backend
from . import pallas as _pallas_hook
from .mjx import Backend

BACKENDS = ("auto", "fused", "mjx", "pallas")
DEFAULT_MAX_SIM_DT = 0.005  # s: upper bound on the simulation step whatever the prior
FORCE_INTERPS = ("linear", "hold")
DEFAULT_SIM_TOLERANCE = 1e-4  # m: default accuracy target of the step when the noise is unknown
STABILITY_MARGIN = 1.5  # require omega_max * dt <= this (explicit-spring limit is 2)
PRIOR_STIFFNESS_HEADROOM = 2.0  # particles may wander a little past the prior box's upper Kp


class Rollout(NamedTuple):
    """Simulator output.

    Attributes:
      tau: [P, B, T] m, displacement of the grasp point from its settled rest along the pull
        direction (positive downward for the default pull along gravity).
      tau_dot: [P, B, T] m/s, its time derivative.
      stable: [P, B] bool; False where the rollout blew up (tau, tau_dot are zero there).
    """

    tau: jax.Array
    tau_dot: jax.Array
    stable: jax.Array


@dataclass(frozen=True, eq=False)  # eq=False: hashed by identity, usable as a static jit argument
class Simulator:
    """A compiled tree model ready for batched rollouts. Build with :func:`make_simulator`.

    Attributes:
      mj_model: the MuJoCo C model (reference path, exports).
      model: the MJX model (device arrays; built on first use).
      joint_names: names of the inferred joints (order of the Kp/Kd columns).
      joint_ids, dof_ids: their MuJoCo joint and dof indices.
      grasp_body, grasp_site: indices of the grasped body and the grasp-point site.
      grasp_start, grasp_end: [3] the grasped branch's axis in its body frame
        (grasp fraction f puts C at ``start + f * (end - start)``).
      obs_dt: s between observations. substeps: simulation steps per observation.
      gravity_dir: [3] unit vector along gravity (the "downward" axis).
      backend: ``"fused"`` (MuJoCo's implicitfast step for hinge trees, fused into a few XLA
        kernels: :mod:`treeinfer.sim.fused`) or ``"mjx"`` (``mjx.step``).
      hinge_tree: the fused backend's static model (None for ``"mjx"``).
      grasp_fraction: the tree's grasp fraction (the default of :func:`simulate`'s
        ``grasp_fraction`` on other branches).
      force_interp: ``"linear"`` (first-order hold between force samples) or ``"hold"``
        (zero-order hold); see the module docstring for the exact convention.
      prior_box: (lower [2R], upper [2R]) the tree's prior box (``Tree.bounds_array``), used to
        pick the parameter sets of the accuracy check.
      branches: {branch name: (body index, length in m)} of every body the force may grasp.
      branch_axes: {body index: (start [3], end [3])} m, link axes of a user model in their
        body frames (absent: the axis runs along local x from 0 to the branch length).
      model_report: a user model's preparation report (:mod:`treeinfer.usermodel`), else {}.
      step_info: how ``substeps`` was chosen: ``{"method": "given" | "stability" |
        "accuracy", "stability_substeps": int, "tolerance": m, "estimated_error": m}``.
    """

    mj_model: object
    joint_names: tuple[str, ...]
    joint_ids: np.ndarray
    dof_ids: np.ndarray
    grasp_body: int
    grasp_site: int
    grasp_start: np.ndarray
    grasp_end: np.ndarray
    obs_dt: float
    substeps: int
    gravity_dir: np.ndarray
    settle_iterations: int = 30
    max_displacement: float = 5.0
    max_joint_speed: float = 200.0
    settle_tolerance: float = 1e-3
    backend: str = "mjx"
    hinge_tree: object = None
    force_interp: str = "linear"
    grasp_fraction: float = 1.0
    prior_box: tuple = ()
    branches: dict = field(default_factory=dict)
    step_info: dict = field(default_factory=dict)
    branch_axes: dict = field(default_factory=dict)
    model_report: dict = field(default_factory=dict)

    @functools.cached_property
    def model(self):
        # eager even when first touched inside a jit trace: the cached arrays must be concrete
        with jax.ensure_compile_time_eval():
            return _mjx_backend.put_model(self.mj_model)

    @property
    def dtype(self):
        """Float type of the rollout: float32, or float64 when ``jax_enable_x64`` is on."""
        return jnp.asarray(0.0).dtype

    @property
    def n_joints(self) -> int:
        return len(self.joint_ids)

    @property
    def sim_dt(self) -> float:
        return self.obs_dt / self.substeps

    def branch_point(self, body, length: float, fraction) -> jax.Array:
        """[..., 3] point at ``fraction`` [...] of a branch's axis, in its body's frame (``body``
        None: the grasped body)."""
        f = jnp.asarray(fraction, dtype=self.dtype)[..., None]
        bid = self.grasp_body if body is None else int(body)
        if bid in self.branch_axes:
            a, e = (jnp.asarray(x, self.dtype) for x in self.branch_axes[bid])
            return a + f * (e - a)
        return f * jnp.asarray([length, 0.0, 0.0], self.dtype)

    def grasp_point(self, fraction) -> jax.Array:
        """Grasp point in the grasped body's frame for a fraction of the branch length."""
        f = jnp.asarray(fraction, dtype=self.dtype)
        return jnp.asarray(self.grasp_start) + f[..., None] * jnp.asarray(
            self.grasp_end - self.grasp_start
        )


# ---- construction ---------------------------------------------------------------------------
def _stiff_corner_omega(mj_model, joint_ids: np.ndarray, kp_max: np.ndarray) -> float:
    """Largest natural frequency (rad/s) at the rest pose with inferred joints at ``kp_max``."""
    import mujoco

    d = mujoco.MjData(mj_model)
    mujoco.mj_forward(mj_model, d)
    nv = mj_model.nv
    mass = np.zeros((nv, nv))
    mujoco.mj_fullM(mj_model, d, mass)
    k = np.zeros(nv)
    for j in range(mj_model.njnt):
        k[mj_model.jnt_dofadr[j]] = mj_model.jnt_stiffness[j]
    for jid, kp in zip(joint_ids, kp_max):
        k[mj_model.jnt_dofadr[jid]] = kp
    # generalized eigenvalues of K v = w^2 M v
    lm = np.linalg.cholesky(mass)
    li = np.linalg.inv(lm)
    w2 = np.linalg.eigvalsh(li @ np.diag(k) @ li.T)
    return float(np.sqrt(max(w2.max(), 0.0)))


def choose_substeps(
    mj_model, joint_ids, kp_max, obs_dt: float, max_sim_dt: float = DEFAULT_MAX_SIM_DT
) -> int:
    """Simulation steps per observation so that ``omega_max * dt <= STABILITY_MARGIN``."""
    omega = _stiff_corner_omega(
        mj_model, np.asarray(joint_ids), np.asarray(kp_max) * PRIOR_STIFFNESS_HEADROOM
    )
    dt_max = min(max_sim_dt, STABILITY_MARGIN / omega if omega > 0 else max_sim_dt)
    return max(1, int(math.ceil(obs_dt / dt_max - 1e-9)))


def make_simulator(
    tree: Tree,
    obs_dt: float = 0.01,
    substeps: int | None = None,
    max_sim_dt: float = DEFAULT_MAX_SIM_DT,
    model_file=None,
    settle_iterations: int = 30,
    backend: str = "auto",
    force_interp: str = "linear",
    forces=None,
    sim_tolerance: float | None = None,
    grasp_fraction=None,
    direction=None,
    grasp_branch=None,
) -> Simulator:
    """Compile ``tree`` for batched rollouts observed every ``obs_dt`` seconds.

    Args:
      tree: the tree description (geometry, grasp, inferred joints, prior box).
      obs_dt: s, the trajectory sample interval (the CSV files' time step).
      substeps: simulation steps per observation; default: the fewest that keep the stiffest
        corner of the prior box stable and ``dt <= max_sim_dt`` (s), refined for accuracy when
        ``forces`` or ``sim_tolerance`` is given (below). ``sim.step_info`` says how it was chosen.
      forces: [B, T] N, the force profiles the simulator will run (the data's): with them the
        step is refined until the step-doubling estimate of the discretisation error of ``tau``
        is at most ``sim_tolerance`` on parameter sets spanning the prior box
        (:func:`treeinfer.sim.accuracy.choose_substeps_for_accuracy`); ``grasp_fraction``,
        ``direction`` and ``grasp_branch`` are those profiles' (as in :func:`simulate`).
      sim_tolerance: m, the accuracy target (default ``DEFAULT_SIM_TOLERANCE`` = 0.1 mm; the run
        layer passes a tenth of the noise level when it knows it). Given without ``forces``,
        the check runs on a representative set of pulls (:func:`treeinfer.forces.profile_set`).
      force_interp: ``"linear"`` (first-order hold between force samples, the default) or
        ``"hold"`` (zero-order hold, each sample held until the next); see :func:`simulate`.
      model_file: a user's own MJCF (``.xml``) or URDF file to simulate instead of exporting
        ``tree`` (default: the tree's ``model:`` section, if any); prepared by
        :func:`treeinfer.usermodel.prepare_user_model` (name map, fixed gains, grasp axis,
        inertia and limit checks) with the settings of the tree's ``model:`` section.
      backend: ``"fused"``, ``"mjx"`` or ``"auto"`` (fused when the model is a contact-free
        hinge tree it reproduces, which every tree treeinfer builds is; MJX otherwise). Both
        step the same MuJoCo model and agree with MuJoCo C to float32 rounding; the fused step
        is several times faster and compiles in seconds (``BENCHMARKS.md``).
        ``"pallas"``: the fused step as one GPU kernel per block of rollouts
        (:mod:`treeinfer.sim.pallas`); ``"auto"`` picks it on a GPU.
    """
    import mujoco

    from ..export import GRASP_SITE, to_mjmodel

    if not (isinstance(obs_dt, (int, float)) and math.isfinite(obs_dt) and obs_dt > 0):
        raise ConfigError(f"obs_dt: must be a positive number of seconds, got {obs_dt!r}")
    if substeps is not None and (not isinstance(substeps, int) or substeps < 1):
        raise ConfigError(f"substeps: must be a positive integer, got {substeps!r}")
    if backend not in BACKENDS:
        raise ConfigError(f"backend: must be one of {', '.join(BACKENDS)}, got {backend!r}")
    if force_interp not in FORCE_INTERPS:
        raise ConfigError(
            f"force_interp: must be one of {', '.join(FORCE_INTERPS)}, got {force_interp!r}"
        )
    if not (isinstance(max_sim_dt, (int, float)) and math.isfinite(max_sim_dt) and max_sim_dt > 0):
        raise ConfigError(f"max_sim_dt: must be a positive number of seconds, got {max_sim_dt!r}")
    if sim_tolerance is not None and not (
        isinstance(sim_tolerance, (int, float))
        and math.isfinite(sim_tolerance)
        and sim_tolerance > 0
    ):
        raise ConfigError(
            f"sim_tolerance: must be a positive number of metres, got {sim_tolerance!r}"
        )
    user = None
    if model_file is not None or tree.model is not None:
        from ..usermodel import prepare_user_model

        user = prepare_user_model(tree, model_file)
    mj_model = to_mjmodel(tree) if user is None else user.mj_model
    bad = [
        mj_model.joint(j).name
        for j in range(mj_model.njnt)
        if mj_model.jnt_type[j] != mujoco.mjtJoint.mjJNT_HINGE
    ]
    if bad:
        raise TreeFileError(
            f"model: only hinge joints are supported, found other joint types: {bad}"
        )

    def jid(name):
        i = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_JOINT, name)
        if i < 0:
            raise TreeFileError(
                f"model: no joint named '{name}' (inferred joints must exist in the model)"
            )
        return i

    joint_ids = np.array([jid(n) for n in tree.inferred], dtype=np.int32)
    dof_ids = np.array([mj_model.jnt_dofadr[j] for j in joint_ids], dtype=np.int32)
    body = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_BODY, tree.grasp_branch)
    if body < 0:
        raise TreeFileError(f"model: no body named '{tree.grasp_branch}' (the grasp branch)")
    site = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_SITE, GRASP_SITE)
    if site < 0 or mj_model.site_bodyid[site] != body:
        raise TreeFileError(f"model: no site '{GRASP_SITE}' on body '{tree.grasp_branch}'")
    axes = {} if user is None else user.axes
    length = tree.branch(tree.grasp_branch).length
    start, end = axes.get(tree.grasp_branch, (np.zeros(3), np.array([length, 0.0, 0.0])))

    prior_lo, prior_hi = tree.bounds_array()
    kp_max = prior_hi[: tree.n_inferred]
    step_info = {"method": "given"}
    if substeps is None:
        substeps = choose_substeps(mj_model, joint_ids, kp_max, obs_dt, max_sim_dt)
        step_info = {
            "method": "stability",
            "stability_substeps": int(substeps),
            "max_sim_dt": float(max_sim_dt),
        }
    mj_model.opt.timestep = obs_dt / substeps
    g = np.asarray(mj_model.opt.gravity, float)
    gdir = g / np.linalg.norm(g)
    hinge_tree = None
    if backend in ("auto", "fused", "pallas"):
        from .fused import UnsupportedModel, from_mjmodel

        try:
            hinge_tree = from_mjmodel(mj_model)
        except UnsupportedModel as e:
            if backend in ("fused", "pallas"):
                raise TreeFileError(f"model: {e}; use backend='mjx'") from None
    branches, branch_axes = {}, {}
    for b in tree.branches:
        i = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_BODY, b.name)
        if i >= 0:
            a, e = axes.get(b.name, (np.zeros(3), np.array([b.length, 0.0, 0.0])))
            branches[b.name] = (int(i), float(np.linalg.norm(e - a)))
            if b.name in axes:
                branch_axes[int(i)] = (np.asarray(a, float), np.asarray(e, float))
    sim = Simulator(
        mj_model=mj_model,
        joint_names=tuple(tree.inferred),
        joint_ids=joint_ids,
        dof_ids=dof_ids,
        grasp_body=int(body),
        grasp_site=int(site),
        grasp_start=start,
        grasp_end=end,
        obs_dt=float(obs_dt),
        substeps=int(substeps),
        gravity_dir=gdir,
        settle_iterations=settle_iterations,
        max_displacement=max(5.0, 2.0 * tree.total_length()),
        backend="mjx" if hinge_tree is None else _pallas_hook.resolve(backend),
        hinge_tree=hinge_tree,
        force_interp=force_interp,
        grasp_fraction=float(tree.grasp_fraction),
        prior_box=(prior_lo, prior_hi),
        branches=branches,
        step_info=step_info,
        branch_axes=branch_axes,
        model_report={} if user is None else user.report,
    )
    if step_info["method"] == "stability" and (forces is not None or sim_tolerance is not None):
        from .accuracy import with_accurate_step

        sim = with_accurate_step(
            sim,
            forces,
            sim_tolerance,
            max_sim_dt,
            grasp_fraction=grasp_fraction,
            direction=direction,
            grasp_branch=grasp_branch,
        )
    return sim


# ---- the batched rollout ----------------------------------------------------------------------
def velocity(tau: jax.Array, dt: float) -> jax.Array:
    """d tau / dt along the last axis: second-order central differences inside, second-order
    one-sided at both ends (``numpy.gradient(..., edge_order=2)``)."""
    from ..trajectories import velocity_from_displacement

    return velocity_from_displacement(tau, dt)


# ---- the fused backend (treeinfer.sim.fused) ------------------------------------------------
def _fused_gains(sim: Simulator, kp: jax.Array, kd: jax.Array):
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


def _fused_settle_one(sim: Simulator, kp, kd, dtype):
    """:func:`treeinfer.sim.mjx.settle_one` for the fused backend: the same clipped Newton iteration and
    convergence test, with the exact Jacobian by forward-mode autodiff (cheap here)."""
    from . import fused as hd

    stiffness, _, spring = _fused_gains(sim, kp, kd)
    torque = lambda q: hd.static_torque(sim.hinge_tree, q, stiffness, spring)
    nv = sim.mj_model.nv

    def newton(carry, i):
        q, r_first, _ = carry
        r, jac = torque(q), jax.jacfwd(torque)(q)
        dq = jnp.clip(-jnp.linalg.solve(jac, r), -0.2, 0.2)
        return (q + dq, jnp.where(i == 0, r, r_first), r), None

    zero = jnp.zeros(nv, dtype)
    (q, r_first, r_last), _ = jax.lax.scan(
        newton, (zero, zero, zero), jnp.arange(sim.settle_iterations)
    )
    scale = 1.0 + jnp.max(jnp.abs(r_first))
    ok = jnp.all(jnp.isfinite(q)) & (jnp.max(jnp.abs(r_last)) <= sim.settle_tolerance * scale)
    return q, ok


def _fused_prepare(sim: Simulator, kp, kd, dtype):
    kp, kd = kp.astype(dtype), kd.astype(dtype)
    qpos_rest, settled = _fused_settle_one(sim, kp, kd, dtype)
    return (kp, kd), qpos_rest, settled


def _fused_pull(
    sim: Simulator, gains, qpos_rest, forces, site_local, unroll_outer=1, unroll_inner=1, **kw
):
    kp, kd = gains
    return _fused_pull_one(
        sim, kp, kd, qpos_rest, forces, site_local, unroll_outer, unroll_inner, **kw
    )


def _fused_pull_one(
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
):
    """:func:`_pull_one` for the fused backend: same timing, force and observation."""
    from . import fused as hd
    from .forcing import force_fraction, next_samples

    t = sim.hinge_tree
    stiffness, damping, spring = _fused_gains(sim, kp, kd)
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
    kin = hd.kinematics(t, [qpos_rest[i] for i in range(t.nv)])
    c_rest = hd.point(kin, bid, site_local)
    lever0 = hd.vsub(c_rest, kin.com[bid])

    def observe(carry, ff):
        q, v, lever, comp, ok = carry
        f0, f1 = ff

        def sub(k, st):
            q, v, lever, c, comp = st
            force = hd.vscale(
                f0 + force_fraction(sim.force_interp, k, n_sub, dtype) * (f1 - f0), ddir
            )
            out = hd.step(t, q, v, stiffness, damping, spring, dt, bid, site_local, force, lever)
            c = tuple(jnp.where(k == 0, a, b) for a, b in zip(out.site, c))
            # Stacked [nv] carries: carrying nv separate scalars makes XLA emit one multi-output
            # loop (1.3x faster for 6 joints at N = 131072 on an H100) but costs more per loop
            # iteration at the standard problem's size (26 ms vs 19 ms per NNSVGD iteration).
            stack = lambda xs: jnp.stack([jnp.asarray(x, dtype) for x in xs])
            v_new = stack(out.qvel)
            # qpos += dt * qvel with Kahan's compensated summation: thousands of small float32
            # increments otherwise drift by ~0.1 mm over a 3 s pull at sub-millisecond steps
            # (the floor that stopped the accuracy control's refinement).
            y = dt * v_new - comp
            q_new = q + y
            comp = (q_new - q) - y
            return q_new, v_new, tuple(jnp.asarray(x, dtype) for x in out.lever), c, comp

        inner = {} if unroll_inner == 1 else {"unroll": unroll_inner}
        c0 = tuple(jnp.asarray(x, dtype) for x in c_rest)
        q, v, lever, c, comp = jax.lax.fori_loop(0, n_sub, sub, (q, v, lever, c0, comp), **inner)
        ok = ok & jnp.all(jnp.isfinite(q)) & jnp.all(jnp.abs(v) < sim.max_joint_speed)
        return (q, v, lever, comp, ok), hd.dot(hd.vsub(c, c_rest), ddir)

    zero = jnp.zeros_like(qpos_rest)
    carry = (qpos_rest, zero, tuple(jnp.asarray(x, dtype) for x in lever0), zero, jnp.bool_(True))
    forces = forces.astype(dtype)
    (_, _, _, _, ok), tau = jax.lax.scan(
        observe, carry, (forces, next_samples(forces)), unroll=unroll_outer
    )
    ok = ok & jnp.all(jnp.isfinite(tau)) & jnp.all(jnp.abs(tau) < sim.max_displacement)
    return tau, ok


FUSED = Backend("fused", _fused_prepare, _fused_pull)
# "pallas" (treeinfer.sim.pallas) settles and falls back through the fused step
_BACKENDS = {"fused": FUSED, "mjx": _mjx_backend.BACKEND, "pallas": FUSED}


def backend_of(sim: Simulator) -> Backend:
    """THE backend switch: the :class:`~treeinfer.sim.mjx.Backend` (``prepare``, ``pull``) that
    steps ``sim`` (``sim.backend``: ``"fused"`` or ``"mjx"``, resolved by :func:`make_simulator`)."""
    return _BACKENDS[sim.backend]


def simulate(
    sim: Simulator,
    kp: jax.Array,
    kd: jax.Array,
    forces: jax.Array,
    grasp_fraction=None,
    unroll_outer: int = 1,
    unroll_inner=1,
    direction=None,
    grasp_branch=None,
) -> Rollout:
    """Roll out P parameter sets under B force profiles in one batched call.

    Args:
      sim: from :func:`make_simulator`.
      kp: [P, R] N m/rad, stiffness of the inferred joints (order ``sim.joint_names``).
      kd: [P, R] N m s/rad, damping of the inferred joints.
      forces: [B, T] N, force at the grasp point along the pull direction, one row per
        profile. ``forces[:, k]`` is the force at ``t_k = k * obs_dt``; between samples it is
        interpolated linearly (``sim.force_interp == "linear"``, the default) or held
        (``"hold"``: sample k over ``[t_k, t_{k+1})``); after the last sample it stays at that
        sample's value. Each simulation substep uses the force at its start time.
      grasp_fraction: None (the tree's), a scalar, or [B]: where along the grasped branch the
        force acts, as a fraction of its length from its parent joint.
      unroll_outer, unroll_inner: loop unrolling of the observation scan / substep loop
        (``True`` unrolls the substeps fully: faster steps, much longer compile).
      direction: None (along gravity: a downward pull), [3] or [B, 3]: the pull direction in
        world coordinates (normalised here; see :func:`treeinfer.sim.direction.pull_direction` for ``"down"`` and
        ``"horizontal"``). The displacement ``tau`` is measured along it.
      grasp_branch: None (the tree's grasped branch), a branch name, or B names (Python
        strings, static under ``jit``): which branch each profile pulls. Profiles are grouped
        by branch, one vmapped rollout per group.

    Returns:
      :class:`Rollout` with ``tau``, ``tau_dot`` [P, B, T] and ``stable`` [P, B].
    """
    return _simulate(
        sim, kp, kd, forces, grasp_fraction, unroll_outer, unroll_inner, direction, grasp_branch
    )


def _grasp_groups(
    sim: Simulator, grasp_branch, n_profiles: int
) -> list[tuple[int | None, float, np.ndarray]]:
    """[(body index or None for the sim's own, branch length m, profile indices)] per branch."""
    if grasp_branch is None:
        return [
            (None, float(np.linalg.norm(sim.grasp_end - sim.grasp_start)), np.arange(n_profiles))
        ]
    names = [grasp_branch] * n_profiles if isinstance(grasp_branch, str) else list(grasp_branch)
    if len(names) != n_profiles:
        raise ConfigError(f"grasp_branch: {len(names)} names for {n_profiles} force profiles")
    groups = []
    for name in dict.fromkeys(names):
        if name not in sim.branches:
            raise ConfigError(
                f"grasp_branch: unknown branch '{name}'; the model has: {', '.join(sim.branches)}"
            )
        body, length = sim.branches[name]
        idx = np.array([i for i, n in enumerate(names) if n == name])
        groups.append((None if body == sim.grasp_body else int(body), float(length), idx))
    return groups


def _simulate(
    sim: Simulator,
    kp,
    kd,
    forces,
    grasp_fraction=None,
    unroll_outer: int = 1,
    unroll_inner=1,
    direction=None,
    grasp_branch=None,
    substeps=None,
) -> Rollout:
    """:func:`simulate` with an optional traced ``substeps`` overriding ``sim.substeps``."""
    if sim.backend == "pallas" and _pallas_hook.supported(sim, grasp_branch, substeps):
        return _pallas_hook.simulate(sim, kp, kd, forces, grasp_fraction, direction)
    kp = jnp.atleast_2d(kp)
    kd = jnp.atleast_2d(kd)
    forces = jnp.atleast_2d(forces)
    n_profiles = forces.shape[0]
    dtype = sim.dtype
    frac = jnp.broadcast_to(
        jnp.asarray(sim.grasp_fraction if grasp_fraction is None else grasp_fraction, dtype),
        (n_profiles,),
    )
    dirs = None
    if direction is not None:
        dirs = jnp.broadcast_to(jnp.asarray(direction, dtype), (n_profiles, 3))
        dirs = dirs / jnp.linalg.norm(dirs, axis=-1, keepdims=True)
    groups = _grasp_groups(sim, grasp_branch, n_profiles)

    impl = backend_of(sim)

    def per_params(kp_i, kd_i):
        state, qpos_rest, settled = impl.prepare(sim, kp_i, kd_i, dtype)
        pull_fn = lambda *a, **k: impl.pull(sim, state, qpos_rest, *a, **k)
        taus, oks = [], []
        for body, length, idx in groups:
            if grasp_fraction is None and body is None:  # the model's own grasp site
                site_local = jnp.broadcast_to(
                    jnp.asarray(sim.mj_model.site_pos[sim.grasp_site], dtype), (len(idx), 3)
                )
            else:
                site_local = sim.branch_point(body, length, frac[idx])
            opts = {"body": body, "substeps": substeps}
            if dirs is None:
                pull = lambda f, s, o=opts: pull_fn(f, s, unroll_outer, unroll_inner, **o)
                tau, ok = jax.vmap(pull)(forces[idx], site_local)
            else:
                pull = lambda f, s, d, o=opts: pull_fn(
                    f, s, unroll_outer, unroll_inner, direction=d, **o
                )
                tau, ok = jax.vmap(pull)(forces[idx], site_local, dirs[idx])
            taus.append(tau)
            oks.append(ok)
        if len(groups) == 1:
            tau, ok = taus[0], oks[0]
        else:  # back to the profiles' order
            order = np.argsort(np.concatenate([idx for _, _, idx in groups]))
            tau, ok = jnp.concatenate(taus)[order], jnp.concatenate(oks)[order]
        return tau, ok & settled

    tau, ok = jax.vmap(per_params)(kp, kd)
    tau = jnp.where(ok[..., None], tau, 0.0)
    tau_dot = jnp.where(ok[..., None], velocity(tau, sim.obs_dt), 0.0)
    return Rollout(tau=tau, tau_dot=tau_dot, stable=ok)


def settle(sim: Simulator, kp: jax.Array, kd: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Settled joint angles [P, nq] and convergence flags [P] for P parameter sets."""
    impl, dtype = backend_of(sim), sim.dtype
    return jax.vmap(lambda a, b: impl.prepare(sim, a, b, dtype)[1:])(
        jnp.atleast_2d(kp), jnp.atleast_2d(kd)
    )


def check_stable_share(stable, max_unstable_share: float, what: str = "particles") -> None:
    """Raise :class:`SimulationError` if more than ``max_unstable_share`` of entries blew up."""
    stable = np.asarray(stable)
    share = 1.0 - stable.mean()
    if share > max_unstable_share:
        raise SimulationError(
            f"{share:.0%} of {what} gave unstable simulations (limit {max_unstable_share:.0%}); "
            "narrow the Kp prior box, lower the simulation step (--max-sim-dt) or check the tree's units"
        )
