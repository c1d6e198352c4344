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
2. **Pull.** The force profile acts straight down (along gravity) at C: the applied wrench at
   the grasp body's centre of mass is ``F`` plus the torque ``(C - com) x F``. Each observation
   interval ``dt_obs`` is split into ``substeps`` simulation steps with the force held constant.
3. **Observe.** ``tau[t] = (C(t * dt_obs) - C_rest) . g_hat`` (metres, positive downward);
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
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ConfigError, SimulationError, TreeFileError
from ..tree import Tree
from . import mjx as _mjx_backend
from .mjx import Backend

BACKENDS = ("auto", "fused", "mjx")
DEFAULT_MAX_SIM_DT = 0.005  # s: upper bound on the simulation step whatever the prior
STABILITY_MARGIN = 1.5  # require omega_max * dt <= this (explicit-spring limit is 2)
PRIOR_STIFFNESS_HEADROOM = 2.0  # particles may wander a little past the prior box's upper Kp


class Rollout(NamedTuple):
    """Simulator output.

    Attributes:
      tau: [P, B, T] m, displacement of the grasp point from its settled rest, positive downward.
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

    def grasp_point(self, fraction) -> jax.Array:
        """Grasp point in the grasped body's frame for a fraction of the branch length."""
        f = jnp.asarray(fraction, dtype=self.dtype)
        return jnp.asarray(self.grasp_start) + f[..., None] * jnp.asarray(self.grasp_end - self.grasp_start)


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


def choose_substeps(mj_model, joint_ids, kp_max, obs_dt: float, max_sim_dt: float = DEFAULT_MAX_SIM_DT) -> int:
    """Simulation steps per observation so that ``omega_max * dt <= STABILITY_MARGIN``."""
    omega = _stiff_corner_omega(mj_model, np.asarray(joint_ids), np.asarray(kp_max) * PRIOR_STIFFNESS_HEADROOM)
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
) -> Simulator:
    """Compile ``tree`` for batched rollouts observed every ``obs_dt`` seconds.

    Args:
      tree: the tree description (geometry, grasp, inferred joints, prior box).
      obs_dt: s, the trajectory sample interval (the CSV files' time step).
      substeps: simulation steps per observation; default: the fewest that keep the stiffest
        corner of the prior box stable and ``dt <= max_sim_dt``.
      model_file: a user's own MJCF (``.xml``) or URDF file to simulate instead of exporting
        ``tree``; it must have hinge joints named like the inferred joints and a body named like
        the grasp branch whose axis runs along its local x-axis from 0 to the branch length.
      backend: ``"fused"``, ``"mjx"`` or ``"auto"`` (fused when the model is a contact-free
        hinge tree it reproduces, which every tree treeinfer builds is; MJX otherwise). Both
        step the same MuJoCo model and agree with MuJoCo C to float32 rounding; the fused step
        is several times faster and compiles in seconds (``BENCHMARKS.md``).
    """
    import mujoco

    from ..export import GRASP_SITE, to_mjmodel

    if not (isinstance(obs_dt, (int, float)) and math.isfinite(obs_dt) and obs_dt > 0):
        raise ConfigError(f"obs_dt: must be a positive number of seconds, got {obs_dt!r}")
    if substeps is not None and (not isinstance(substeps, int) or substeps < 1):
        raise ConfigError(f"substeps: must be a positive integer, got {substeps!r}")
    if backend not in BACKENDS:
        raise ConfigError(f"backend: must be one of {', '.join(BACKENDS)}, got {backend!r}")
    mj_model = to_mjmodel(tree) if model_file is None else _prepare_user_model(model_file, tree)
    bad = [mj_model.joint(j).name for j in range(mj_model.njnt) if mj_model.jnt_type[j] != mujoco.mjtJoint.mjJNT_HINGE]
    if bad:
        raise TreeFileError(f"model: only hinge joints are supported, found other joint types: {bad}")

    def jid(name):
        i = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_JOINT, name)
        if i < 0:
            raise TreeFileError(f"model: no joint named '{name}' (inferred joints must exist in the model)")
        return i

    joint_ids = np.array([jid(n) for n in tree.inferred], dtype=np.int32)
    dof_ids = np.array([mj_model.jnt_dofadr[j] for j in joint_ids], dtype=np.int32)
    body = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_BODY, tree.grasp_branch)
    if body < 0:
        raise TreeFileError(f"model: no body named '{tree.grasp_branch}' (the grasp branch)")
    site = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_SITE, GRASP_SITE)
    if site < 0 or mj_model.site_bodyid[site] != body:
        raise TreeFileError(f"model: no site '{GRASP_SITE}' on body '{tree.grasp_branch}'")
    length = tree.branch(tree.grasp_branch).length
    start, end = np.zeros(3), np.array([length, 0.0, 0.0])

    _, kp_hi = tree.bounds_array()
    kp_max = kp_hi[: tree.n_inferred]
    if substeps is None:
        substeps = choose_substeps(mj_model, joint_ids, kp_max, obs_dt, max_sim_dt)
    mj_model.opt.timestep = obs_dt / substeps
    g = np.asarray(mj_model.opt.gravity, float)
    gdir = g / np.linalg.norm(g)
    hinge_tree = None
    if backend in ("auto", "fused"):
        from .fused import UnsupportedModel, from_mjmodel

        try:
            hinge_tree = from_mjmodel(mj_model)
        except UnsupportedModel as e:
            if backend == "fused":
                raise TreeFileError(f"model: {e}; use backend='mjx'") from None
    return Simulator(
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
        backend="mjx" if hinge_tree is None else "fused",
        hinge_tree=hinge_tree,
    )


def _prepare_user_model(model_file, tree: Tree):
    """Load a user's own MJCF or URDF and add the grasp site and contact-free options."""
    import mujoco

    from ..export import GRASP_SITE

    try:
        spec = mujoco.MjSpec.from_file(str(model_file))
    except Exception as e:  # MuJoCo's own message says what is wrong with the file
        raise TreeFileError(f"{model_file}: MuJoCo cannot load this model: {e}") from None
    body = spec.body(tree.grasp_branch)
    if body is None:
        raise TreeFileError(f"{model_file}: no body named '{tree.grasp_branch}' (the grasp branch)")
    if spec.site(GRASP_SITE) is None:
        length = tree.branch(tree.grasp_branch).length
        body.add_site(name=GRASP_SITE, pos=[tree.grasp_fraction * length, 0, 0], size=[0.01, 0.01, 0.01])
    # A contact-free articulated chain: no collision detection, no constraint solver.
    spec.option.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT | mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    try:
        return spec.compile()
    except Exception as e:
        raise TreeFileError(f"{model_file}: MuJoCo cannot compile this model: {e}") from None


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
    (q, r_first, r_last), _ = jax.lax.scan(newton, (zero, zero, zero), jnp.arange(sim.settle_iterations))
    scale = 1.0 + jnp.max(jnp.abs(r_first))
    ok = jnp.all(jnp.isfinite(q)) & (jnp.max(jnp.abs(r_last)) <= sim.settle_tolerance * scale)
    return q, ok


def _fused_prepare(sim: Simulator, kp, kd, dtype):
    kp, kd = kp.astype(dtype), kd.astype(dtype)
    qpos_rest, settled = _fused_settle_one(sim, kp, kd, dtype)
    return (kp, kd), qpos_rest, settled


def _fused_pull(sim: Simulator, gains, qpos_rest, forces, site_local, unroll_outer=1, unroll_inner=1):
    kp, kd = gains
    return _fused_pull_one(sim, kp, kd, qpos_rest, forces, site_local, unroll_outer, unroll_inner)


def _fused_pull_one(sim: Simulator, kp, kd, qpos_rest, forces, site_local, unroll_outer: int = 1, unroll_inner=1):
    """:func:`treeinfer.sim.mjx.pull_one` for the fused backend: same timing, force and observation."""
    from . import fused as hd

    t = sim.hinge_tree
    stiffness, damping, spring = _fused_gains(sim, kp, kd)
    gdir = tuple(float(x) for x in sim.gravity_dir)
    bid, dt = sim.grasp_body, sim.sim_dt
    site_local = tuple(site_local[i] for i in range(3))
    kin = hd.kinematics(t, [qpos_rest[i] for i in range(t.nv)])
    c_rest = hd.point(kin, bid, site_local)
    lever0 = hd.vsub(c_rest, kin.com[bid])
    dtype = qpos_rest.dtype

    def observe(carry, f):
        q, v, lever, ok = carry
        force = hd.vscale(f, gdir)

        def sub(k, st):
            q, v, lever, c = st
            out = hd.step(t, q, v, stiffness, damping, spring, dt, bid, site_local, force, lever)
            c = tuple(jnp.where(k == 0, a, b) for a, b in zip(out.site, c))
            # Stacked [nv] carries: carrying nv separate scalars makes XLA emit one multi-output
            # loop (1.3x faster for 6 joints at N = 131072 on an H100) but costs more per loop
            # iteration at the standard problem's size (26 ms vs 19 ms per NNSVGD iteration).
            stack = lambda xs: jnp.stack([jnp.asarray(x, dtype) for x in xs])
            return stack(out.qpos), stack(out.qvel), tuple(jnp.asarray(x, dtype) for x in out.lever), c

        inner = {} if unroll_inner == 1 else {"unroll": unroll_inner}
        c0 = tuple(jnp.asarray(x, dtype) for x in c_rest)
        q, v, lever, c = jax.lax.fori_loop(0, sim.substeps, sub, (q, v, lever, c0), **inner)
        ok = ok & jnp.all(jnp.isfinite(q)) & jnp.all(jnp.abs(v) < sim.max_joint_speed)
        return (q, v, lever, ok), hd.dot(hd.vsub(c, c_rest), gdir)

    carry = (qpos_rest, jnp.zeros_like(qpos_rest), tuple(jnp.asarray(x, dtype) for x in lever0), jnp.bool_(True))
    (_, _, _, ok), tau = jax.lax.scan(observe, carry, forces.astype(dtype), unroll=unroll_outer)
    ok = ok & jnp.all(jnp.isfinite(tau)) & jnp.all(jnp.abs(tau) < sim.max_displacement)
    return tau, ok


FUSED = Backend("fused", _fused_prepare, _fused_pull)
_BACKENDS = {"fused": FUSED, "mjx": _mjx_backend.BACKEND}


def backend_of(sim: Simulator) -> Backend:
    """THE backend switch: the :class:`~treeinfer.sim.mjx.Backend` (``prepare``, ``pull``) that
    steps ``sim`` (``sim.backend``: ``"fused"`` or ``"mjx"``, resolved by :func:`make_simulator`)."""
    return _BACKENDS[sim.backend]


def simulate(
    sim: Simulator, kp: jax.Array, kd: jax.Array, forces: jax.Array, grasp_fraction=None,
    unroll_outer: int = 1, unroll_inner=1,
) -> Rollout:
    """Roll out P parameter sets under B force profiles in one batched call.

    Args:
      sim: from :func:`make_simulator`.
      kp: [P, R] N m/rad, stiffness of the inferred joints (order ``sim.joint_names``).
      kd: [P, R] N m s/rad, damping of the inferred joints.
      forces: [B, T] N, force along gravity (downward) at the grasp point, one row per profile;
        ``forces[:, t]`` acts from ``t * obs_dt`` to ``(t + 1) * obs_dt``.
      grasp_fraction: None (the tree's), a scalar, or [B]: where along the grasped branch the
        force acts, as a fraction of its length from its parent joint.
      unroll_outer, unroll_inner: loop unrolling of the observation scan / substep loop
        (``True`` unrolls the substeps fully: faster steps, much longer compile).

    Returns:
      :class:`Rollout` with ``tau``, ``tau_dot`` [P, B, T] and ``stable`` [P, B].
    """
    kp = jnp.atleast_2d(kp)
    kd = jnp.atleast_2d(kd)
    forces = jnp.atleast_2d(forces)
    n_profiles = forces.shape[0]
    if grasp_fraction is None:
        site_local = jnp.asarray(sim.mj_model.site_pos[sim.grasp_site], sim.dtype)
        site_local = jnp.broadcast_to(site_local, (n_profiles, 3))
    else:
        frac = jnp.broadcast_to(jnp.asarray(grasp_fraction, sim.dtype), (n_profiles,))
        site_local = sim.grasp_point(frac)

    dtype = sim.dtype
    impl = backend_of(sim)

    def per_params(kp_i, kd_i):
        state, qpos_rest, settled = impl.prepare(sim, kp_i, kd_i, dtype)
        pull = lambda f, s: impl.pull(sim, state, qpos_rest, f, s, unroll_outer, unroll_inner)
        tau, ok = jax.vmap(pull)(forces, site_local)
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
