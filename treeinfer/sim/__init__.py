"""The batched branch simulator: a MuJoCo model rolled out for P parameter sets x B profiles.

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
``omega_max * dt <= 1.5`` at twice the box's upper Kp (explicit springs are stable for
``omega * dt < 2``).

Instability: a parameter set whose state becomes non-finite, whose joint speed exceeds
``max_joint_speed`` or whose displacement exceeds ``max_displacement`` (or that fails to
settle) gets ``stable = False`` and zeros in ``tau``/``tau_dot``; vmapped lanes are independent,
so it never affects other entries.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ConfigError, SimulationError
from . import fused_backend as _fused_backend
from . import mjx as _mjx_backend
from . import pallas as _pallas_hook
from .build import choose_substeps, make_simulator
from .mjx import Backend
from .simulator import (
    BACKENDS,
    DEFAULT_MAX_SIM_DT,
    DEFAULT_SIM_TOLERANCE,
    FORCE_INTERPS,
    PRIOR_STIFFNESS_HEADROOM,
    STABILITY_MARGIN,
    Rollout,
    Simulator,
)

__all__ = [
    "BACKENDS",
    "DEFAULT_MAX_SIM_DT",
    "DEFAULT_SIM_TOLERANCE",
    "FORCE_INTERPS",
    "PRIOR_STIFFNESS_HEADROOM",
    "STABILITY_MARGIN",
    "Backend",
    "Rollout",
    "Simulator",
    "backend_of",
    "check_stable_share",
    "choose_substeps",
    "make_simulator",
    "settle",
    "simulate",
    "velocity",
]


# ---- the batched rollout ----------------------------------------------------------------------
def velocity(tau: jax.Array, dt: float) -> jax.Array:
    """d tau / dt along the last axis: second-order central differences inside, second-order
    one-sided at both ends (``numpy.gradient(..., edge_order=2)``)."""
    from ..data.trajectories import velocity_from_displacement

    return velocity_from_displacement(tau, dt)


FUSED = _fused_backend.BACKEND
# "pallas" (treeinfer.sim.pallas) settles and falls back through the fused step
_BACKENDS = {"fused": FUSED, "mjx": _mjx_backend.BACKEND, "pallas": FUSED}


def backend_of(sim: Simulator) -> Backend:
    """THE backend switch: the :class:`~treeinfer.sim.mjx.Backend` (``prepare``, ``pull``) that
    steps ``sim`` (``sim.backend``: ``"fused"`` or ``"mjx"``, resolved by
    :func:`make_simulator`)."""
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
        world coordinates (normalised here; see :func:`treeinfer.data.direction.pull_direction`
        for ``"down"`` and ``"horizontal"``). The displacement ``tau`` is measured along it.
      grasp_branch: None (the tree's grasped branch), a branch name, or B names (Python
        strings, static under ``jit``): which branch each profile pulls. Profiles are grouped
        by branch, one vmapped rollout per group.

    Returns:
      :class:`Rollout` with ``tau``, ``tau_dot`` [P, B, T] and ``stable`` [P, B].

    The call is jitted with ``sim`` (hashed by content), the unrolling and ``grasp_branch``
    static: a second call with arrays of the same shapes and dtypes reuses the compiled
    program, also with another :class:`Simulator` built from the same tree and settings.
    """
    if isinstance(grasp_branch, list):
        grasp_branch = tuple(grasp_branch)
    return _simulate_jit(
        sim, kp, kd, forces, grasp_fraction, unroll_outer, unroll_inner, direction, grasp_branch
    )


def _traced_simulate(*args) -> Rollout:
    global TRACES
    TRACES += 1  # a Python side effect: runs once per trace, never in the compiled program
    return _simulate(*args)


TRACES = 0  # how many times simulate has been traced (tests count recompilations with it)
_simulate_jit = jax.jit(_traced_simulate, static_argnums=(0, 5, 6, 8))


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


def _vmap(fn, *args):
    """``jax.vmap(fn)(*args)``, or ``fn`` on the one row with the axis added back when every
    argument has one row. For the parameter sets: the force Jacobian takes one set under its
    own vmap over pulls and jacfwd, and a vmap of one more level is one that JAX's while-loop
    batching rule traces through again for every loop of the step (the Jacobian program's trace
    11 CPU-s before, 6 after on the 2-core box, the same program values: BENCHMARKS.md,
    ``tests/test_simulator.py``). Not for the pulls as well: without both vmaps of one row XLA
    vectorises the step otherwise, and the rollout differs in float32 rounding."""
    if all(np.shape(a)[0] == 1 for a in args):
        out = fn(*(a[0] for a in args))
        return jax.tree_util.tree_map(lambda x: x[None], out)
    return jax.vmap(fn)(*args)


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
        return _pallas_hook.simulate(
            sim, kp, kd, forces, grasp_fraction, direction, substeps=substeps
        )
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
            site_local = _site_local(sim, grasp_fraction, body, length, frac[idx], dtype)
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

    tau, ok = _vmap(per_params, kp, kd)
    tau = jnp.where(ok[..., None], tau, 0.0)
    tau_dot = jnp.where(ok[..., None], velocity(tau, sim.obs_dt), 0.0)
    return Rollout(tau=tau, tau_dot=tau_dot, stable=ok)


def _site_local(sim: Simulator, grasp_fraction, body, length, frac, dtype):
    """``[n, 3]`` grasp points in their bodies' frames of ``n`` pulls of one grasp group."""
    if grasp_fraction is None and body is None:  # the model's own grasp site
        site = jnp.asarray(sim.mj_model.site_pos[sim.grasp_site], dtype)
        return jnp.broadcast_to(site, (np.shape(frac)[0], 3))
    return sim.branch_point(body, length, frac)


def _simulate_force_jacobian(sim: Simulator, kp, kd, forces, grasp_fraction=None, substeps=None):
    """``(tau [B, T], stable [B], J [B, T, T])`` of one parameter set (``kp``, ``kd`` [R]): the
    rollout of ``forces [B, T]`` and each pull's ``d tau / d forces`` (zero where unstable), as
    ``jax.jacfwd`` of :func:`_simulate` per pull gives them, with the force tangents carried by
    :func:`treeinfer.sim.fused_backend.pull_force_jacobian` (no vmap level for them: a much
    smaller trace). None where that does not apply (another backend, the levels layout, the
    sensitivity rule off): take ``jax.jacfwd``."""
    from . import fused_backend as fb

    if not fb.force_jacobian_applies(sim):
        return None
    dtype = sim.dtype
    n_b = forces.shape[0]
    frac = jnp.broadcast_to(
        jnp.asarray(sim.grasp_fraction if grasp_fraction is None else grasp_fraction, dtype),
        (n_b,),
    )
    gains, qpos_rest, settled = fb._prepare(sim, kp, kd, dtype)
    taus, oks, jacs, order = [], [], [], []
    for body, length, idx in _grasp_groups(sim, None, n_b):
        site_local = _site_local(sim, grasp_fraction, body, length, frac[idx], dtype)

        def pull(f, s, body=body):
            return fb.pull_force_jacobian(sim, gains, qpos_rest, f, s, body, substeps)

        tau, ok, jac = jax.vmap(pull)(forces[idx], site_local)
        taus.append(tau)
        oks.append(ok)
        jacs.append(jac)
        order.append(idx)
    back = np.argsort(np.concatenate(order))
    tau, ok, jac = (jnp.concatenate(x)[back] for x in (taus, oks, jacs))
    ok = ok & settled
    return jnp.where(ok[:, None], tau, 0.0), ok, jnp.where(ok[:, None, None], jac, 0.0)


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
            "narrow the Kp prior box, lower the simulation step (--max-sim-dt) or check the "
            "tree's units"
        )
