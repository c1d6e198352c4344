"""The fused hinge-tree step as ONE GPU kernel per block of rollouts (``backend="pallas"``).

Why: on a GPU the fused backend (:mod:`treeinfer.sim.fused`) runs each simulation step as ~2
XLA kernels inside a ``while`` loop; the standard problem needs 300 observations x 4 substeps =
1200 *sequential* steps per rollout, so an NNSVGD iteration is bound by kernel launches and
loop overhead (~15 us per step on an H100), not by arithmetic. XLA's loop levers (command
buffers with WHILE, unrolling, while-loop double buffering) were measured in
``BENCHMARKS.md``: none comes near the 5 ms target. Here one Pallas kernel (Triton on the GPU)
loops over every observation and substep itself; each lane of a [BLOCK] vector is one
(parameter set, force profile) rollout whose state stays in registers, the force profile is read
one sample per observation and ``tau`` written one sample per observation.

The arithmetic is :func:`treeinfer.sim.fused.step` itself, unchanged: its element functions
work on [BLOCK] arrays as they work on scalars (only ``+ - * /``, ``sin``, ``cos``, ``where``).
The settle (static Newton solve) and the observation bookkeeping are shared with the fused
backend, so the two agree to float32 rounding (``tests/test_pallas_backend.py``, interpret mode
on the CPU). Profiles grouped by grasp branch or a traced ``substeps`` (the accuracy check) are
handed to the fused path unchanged.

Exact forward-mode tangents: :func:`simulate_with_tangents` carries K tangent directions of
(kp, kd) through the same kernel, in one of three layouts (:data:`TANGENT_LAYOUTS`): ``"rows"``
and ``"lanes"`` push each tangent through ``jax.linearize`` of the whole step (the linearised
kinematics, bias forces, mass matrix and LDL once per tangent); ``"sensitivity"`` computes the
step's state Jacobian once per substep from the primal (:mod:`treeinfer.sim.sensitivity`, the
fused backend's rule on the CPU) and applies it to each tangent with ~100 multiply-adds.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

DEFAULT_BLOCK = 32  # rollouts per kernel instance (one warp): spreads small batches over SMs
# in the interpreter (CPU), blocks of at least this many rows become one program over all rows
INTERPRET_WHOLE_BATCH = 32


# The substep count as a runtime operand of the (value-only) kernel, a loop bound, instead of a
# constant: one compiled kernel then serves every accurate step, so a new data set whose step
# differs, the multi-fidelity fit's coarse step and the step check (issue 15 item 4) reuse it.
# On by default since it was timed on an H100 (BENCHMARKS.md, "H100: a cold process on a NEW
# data set"): a new recording of the bucket then compiles nothing (3.9 s to a posterior, against
# 7.2-8.6 s with one kernel compile per new step), and an empty cache compiles 6.8 s instead of
# 8.3 s; checked in the interpreter against the fused backend
# (tests/test_pallas_traced_substeps.py). Gradients (simulate_with_tangents) keep the constant
# count. Environment switch for timing it: TREEINFER_PALLAS_TRACED_SUBSTEPS=on|off (read once).
def _switch(name: str) -> bool:
    import os

    from ..errors import ConfigError

    value = os.environ.get(name, "on").strip().lower()
    if value not in ("on", "off", "1", "0"):
        raise ConfigError(f"{name}: expected on or off, got {value!r}")
    return value in ("on", "1")


TRACED_SUBSTEPS = _switch("TREEINFER_PALLAS_TRACED_SUBSTEPS")


# How simulate_with_tangents (and so the kernel's exact JVP) lays its K tangents out:
# * "rows": one tangent per lane beside its own copy of the primal, the step linearised with
#   jax.linearize (K copies of the primal plus K linearised steps: ~12-15 rollouts of arithmetic
#   for K = 6; a kernel as small as the primal's plus one; 1.0x central differences on an H100);
# * "lanes": one primal and all K tangents per lane, each tangent the whole linearised step
#   (~10 rollouts of arithmetic for K = 6; Triton took 182 s to compile it on an H100);
# * "sensitivity": one primal and all K tangents per lane, the step's state Jacobian computed
#   ONCE per substep from the primal (sensitivity.step_linearization) and applied to each
#   tangent (sensitivity.step_tangent: ~100 multiply-adds and a back-substitution), the rule
#   that brought the fused backend on the CPU to 0.20-0.24x of central differences.
# Timed on an H100 (BENCHMARKS.md, "exact gradients at half the cost of central differences"):
# once the GPU is full "sensitivity" takes 0.50x the wall time of central differences at
# P = 65536 (46.7 against 94.0 ms; 0.66x at 16384, where "rows" is 1.02-1.09x), but Triton
# compiles it in 90-98 s per batch shape, and at the standard problem's P = 128, where the
# rollouts are latency-bound and central differences cost one rollout's time, it is 3.5x slower
# than central differences ("rows": 1.7x). So "rows" stays the default; a long run at a large
# batch with a warm persistent cache sets TREEINFER_PALLAS_TANGENT_LAYOUT=sensitivity
# (rows|lanes|sensitivity, read once at import).
TANGENT_LAYOUTS = ("rows", "lanes", "sensitivity")


def _tangent_layout(name: str = "TREEINFER_PALLAS_TANGENT_LAYOUT", default: str = "rows") -> str:
    """The tangent layout named by environment variable ``name`` (unset or empty: ``default``);
    a ConfigError names the variable and the accepted values otherwise."""
    import os

    from ..errors import ConfigError

    value = os.environ.get(name, "").strip().lower() or default
    if value not in TANGENT_LAYOUTS:
        raise ConfigError(f"{name}: expected one of {', '.join(TANGENT_LAYOUTS)}, got {value!r}")
    return value


TANGENT_LAYOUT = _tangent_layout()


def available() -> bool:
    """Whether the Pallas Triton lowering can run here (a CUDA GPU and jax's Pallas).

    Looked up, not imported: importing Pallas and its Triton lowering costs 0.2-0.5 s of a cold
    process (issue 15), and a run whose programs come from the persistent caches never traces
    the kernel; the kernel's builder imports them when it does."""
    import importlib.util

    if jax.devices()[0].platform != "gpu":
        return False
    try:
        return importlib.util.find_spec("jax.experimental.pallas") is not None
    except (ImportError, ValueError):  # pragma: no cover - depends on the jax build
        return False


# ``backend="auto"`` picks the kernel on a GPU (measured faster there: ``BENCHMARKS.md``); on a
# CPU the interpreter is far slower than the fused XLA loop, so "auto" stays "fused".
AUTO_ON_GPU = True


def resolve(backend: str) -> str:
    """The backend a hinge-tree model runs on for the requested ``backend``: ``"pallas"`` when
    asked for, or for ``"auto"`` on a GPU with Pallas; ``"fused"`` otherwise."""
    if backend == "pallas" or (backend == "auto" and AUTO_ON_GPU and available()):
        return "pallas"
    return "fused"


def supported(sim, grasp_branch=None, substeps=None) -> bool:
    """Whether :func:`simulate` runs the kernel for this call (else the fused path does)."""
    from .fused_backend import uses_levels

    # the kernel runs the scalar (unrolled) fused step; big trees take the level layout
    return (
        sim.hinge_tree is not None
        and grasp_branch is None
        and (substeps is None or TRACED_SUBSTEPS)
        and not uses_levels(sim)
    )


def _rows(x, n_profiles: int):
    """[P, K] per particle -> [K, P * B] per rollout row (row = particle * B + profile)."""
    return jnp.repeat(x, n_profiles, axis=0).T


def _pad(x, n: int):
    """Pad the last axis to ``n`` by repeating its first column (finite, discarded later)."""
    extra = n - x.shape[-1]
    if extra == 0:
        return x
    return jnp.concatenate([x, jnp.broadcast_to(x[..., :1], x.shape[:-1] + (extra,))], axis=-1)


def _rollout_kernel(
    sim, n_steps: int, n_tangents: int, has_dir: bool, traced: bool, rule: str, *refs
):
    """Kernel body: every observation and substep of BLOCK rollouts.

    Refs (each [K, BLOCK] unless said): kp [R], kd [R], q_rest [nv], site [3], (dir [3]),
    forces [T], next forces [T], (with ``traced``: substeps [1], int32, the same in every
    column), then for tangents: d kp [K*R], d kd [K*R], d q_rest [K*nv];
    outputs: tau [T], ok [1], (d tau [K*T]). ``rule``: how a substep carries the tangents,
    ``"linearize"`` (``jax.linearize`` of the whole step, applied to each tangent) or
    ``"sensitivity"`` (the step's state Jacobian once, :func:`_sensitivity_substep`)."""
    from . import fused as hd
    from .forcing import force_fraction
    from .fused_backend import _gains as _fused_gains

    refs = list(refs)
    kp_ref, kd_ref, q_ref, site_ref = refs[:4]
    refs = refs[4:]
    dir_ref = refs.pop(0) if has_dir else None
    f_ref, fn_ref = refs[:2]
    refs = refs[2:]
    sub_ref = refs.pop(0) if traced else None
    if n_tangents:
        dkp_ref, dkd_ref, dq_ref = refs[:3]
        refs = refs[3:]
    tau_ref, ok_ref = refs[:2]
    dtau_ref = refs[2] if n_tangents else None

    t = sim.hinge_tree
    nv, n_j = t.nv, sim.n_joints
    dtype = f_ref.dtype
    bid = sim.grasp_body
    if traced:  # a reduction, not an element read: a scalar of the block in Triton's terms
        n_sub = jnp.max(sub_ref[0, :])
        dt = jnp.asarray(sim.obs_dt, dtype) / n_sub.astype(dtype)
    else:
        n_sub = sim.substeps
        dt = sim.sim_dt
    row = lambda ref, i: ref[i, :]
    kp = tuple(row(kp_ref, i) for i in range(n_j))
    kd = tuple(row(kd_ref, i) for i in range(n_j))
    q0 = tuple(row(q_ref, i) for i in range(nv))
    site_local = tuple(row(site_ref, i) for i in range(3))
    if has_dir:
        ddir = tuple(row(dir_ref, i) for i in range(3))
    else:
        ddir = tuple(float(x) for x in sim.gravity_dir)
    cast = lambda xs: tuple(jnp.asarray(x, dtype) + jnp.zeros_like(kp[0]) for x in xs)

    def rest(q0, kp, kd):
        kin = hd.kinematics(t, list(q0))
        c_rest = hd.point(kin, bid, site_local)
        return cast(c_rest), cast(hd.vsub(c_rest, kin.com[bid]))

    def substep(j, f0, f1, kp, kd, q, v, lever):
        """The fused backend's substep (``_fused_pull_one.sub``) without the Kahan sum."""
        stiffness, damping, spring = _fused_gains(sim, kp, kd)
        frac = force_fraction(sim.force_interp, j, n_sub, dtype)
        force = hd.vscale(f0 + frac * (f1 - f0), ddir)
        out = hd.step(t, q, v, stiffness, damping, spring, dt, bid, site_local, force, lever)
        return cast(out.qvel), cast(out.lever), cast(out.site)

    def kahan(q, comp, v_new):
        # qpos += dt * qvel, compensated as in the fused backend (float32 drift otherwise)
        y = tuple(dt * v - c for v, c in zip(v_new, comp))
        q_new = tuple(a + b for a, b in zip(q, y))
        comp = tuple((a - b) - c for a, b, c in zip(q_new, q, y))
        return q_new, comp

    zero = jnp.zeros_like(kp[0])
    true = jnp.ones_like(kp[0])
    if not n_tangents:
        c_rest, lever0 = rest(q0, kp, kd)

        def observe(k, carry):
            q, v, lever, comp, ok = carry
            f0, f1 = f_ref[k, :], fn_ref[k, :]

            def sub(j, st):
                q, v, lever, c, comp = st
                v_new, lever, site = substep(j, f0, f1, kp, kd, q, v, lever)
                c = tuple(jnp.where(j == 0, a, b) for a, b in zip(site, c))
                q, comp = kahan(q, comp, v_new)
                return q, v_new, lever, c, comp

            q, v, lever, c, comp = jax.lax.fori_loop(0, n_sub, sub, (q, v, lever, c_rest, comp))
            tau = hd.dot(hd.vsub(c, c_rest), ddir)
            tau_ref[k, :] = tau
            good = jnp.isfinite(tau) & (jnp.abs(tau) < sim.max_displacement)
            for i in range(nv):
                good = good & jnp.isfinite(q[i]) & (jnp.abs(v[i]) < sim.max_joint_speed)
            return q, v, lever, comp, jnp.where(good, ok, zero)

        zeros = (zero,) * nv
        carry = (q0, zeros, lever0, zeros, true)
        ok = jax.lax.fori_loop(0, n_steps, observe, carry)[-1]
        ok_ref[0, :] = ok
        return

    # ---- primal + K tangents per lane. "linearize": jax.linearize of the whole step per
    # substep, its linear map (the linearised kinematics, dynamics and solve: ~1.6x the primal's
    # arithmetic on the three-branch tree) applied to each tangent; "sensitivity": the step's
    # state Jacobian once per substep (~3.8x the primal's arithmetic), then ~160 operations per
    # tangent (_sensitivity_substep): the fewer operations from K = 3 tangents on (jaxpr counts
    # after CSE, one substep of the three-branch tree: primal 580, K = 6 "linearize" 6200,
    # K = 6 "sensitivity" 3145)
    dkp = tuple(tuple(row(dkp_ref, a * n_j + i) for i in range(n_j)) for a in range(n_tangents))
    dkd = tuple(tuple(row(dkd_ref, a * n_j + i) for i in range(n_j)) for a in range(n_tangents))
    dq0 = tuple(tuple(row(dq_ref, a * nv + i) for i in range(nv)) for a in range(n_tangents))
    (c_rest, lever0), rest_lin = jax.linearize(rest, q0, kp, kd)
    d_rest = tuple(rest_lin(dq0[a], dkp[a], dkd[a]) for a in range(n_tangents))
    dc_rest = tuple(d[0] for d in d_rest)
    dlever0 = tuple(d[1] for d in d_rest)

    if rule == "sensitivity":
        # the per-lane values the sensitivity substep reads (one lane = one rollout)
        lanes = {"kp": kp, "kd": kd, "site": site_local, "dkp": dkp, "dkd": dkd}
        if has_dir:
            lanes["dir"] = ddir
        const_dir = None if has_dir else ddir  # Python floats: gravity's, folded
        sens = functools.partial(_sensitivity_substep, sim, n_tangents, n_sub, dt, dtype, const_dir)
        # jax.vmap over the lanes: the sensitivity functions pass Python-float unit tangents to
        # jax.jvp (sensitivity._jvp_sparse), whose shape () must match the primal's, so they
        # run on one lane's scalars, as the fused backend runs them under its vmap
        sens = jax.vmap(sens, in_axes=(None, 0, 0))
    elif rule != "linearize":
        raise ValueError(f"rule: 'linearize' or 'sensitivity', got {rule!r}")

    def observe_t(k, carry):
        (q, v, lever, comp, ok), (dq, dv, dlever) = carry
        f0, f1 = f_ref[k, :], fn_ref[k, :]

        def sub(j, st):
            if rule == "sensitivity":
                return sens(j, {**lanes, "f0": f0, "f1": f1}, st)
            (q, v, lever, c, comp), (dq, dv, dlever, dc) = st
            fn = lambda kp, kd, q, v, lever: substep(j, f0, f1, kp, kd, q, v, lever)
            (v_new, lever, site), lin = jax.linearize(fn, kp, kd, q, v, lever)
            tan = [lin(dkp[a], dkd[a], dq[a], dv[a], dlever[a]) for a in range(n_tangents)]
            c = tuple(jnp.where(j == 0, a, b) for a, b in zip(site, c))
            dc = tuple(
                tuple(jnp.where(j == 0, a, b) for a, b in zip(tn[2], dc_a))
                for tn, dc_a in zip(tan, dc)
            )
            q, comp = kahan(q, comp, v_new)
            dq = tuple(tuple(a + dt * b for a, b in zip(dq_a, tn[0])) for dq_a, tn in zip(dq, tan))
            dv = tuple(tn[0] for tn in tan)
            dlever = tuple(tn[1] for tn in tan)
            return (q, v_new, lever, c, comp), (dq, dv, dlever, dc)

        st = ((q, v, lever, c_rest, comp), (dq, dv, dlever, dc_rest))
        (q, v, lever, c, comp), (dq, dv, dlever, dc) = jax.lax.fori_loop(0, n_sub, sub, st)
        tau = hd.dot(hd.vsub(c, c_rest), ddir)
        tau_ref[k, :] = tau
        for a in range(n_tangents):
            dtau_ref[a * n_steps + k, :] = hd.dot(hd.vsub(dc[a], dc_rest[a]), ddir)
        good = jnp.isfinite(tau) & (jnp.abs(tau) < sim.max_displacement)
        for i in range(nv):
            good = good & jnp.isfinite(q[i]) & (jnp.abs(v[i]) < sim.max_joint_speed)
        return (q, v, lever, comp, jnp.where(good, ok, zero)), (dq, dv, dlever)

    zeros = (zero,) * nv
    tzeros = ((zero,) * nv,) * n_tangents
    carry = ((q0, zeros, lever0, zeros, true), (dq0, tzeros, dlever0))
    (_, _, _, _, ok), _ = jax.lax.fori_loop(0, n_steps, observe_t, carry)
    ok_ref[0, :] = ok


def _sensitivity_substep(sim, n_tangents, n_sub, dt, dtype, ddir, j, lane, st):
    """One substep of ONE rollout (scalars; the kernel vmaps it over its lanes) and its K
    tangents by the sensitivity rule: the fused backend's ``pull_with_tangent`` substep.

    ``lane``: kp, kd [R], site [3], dkp, dkd [K][R], f0, f1 (this observation's force samples),
    with a per-profile direction ``dir`` [3] (else ``ddir``, Python floats, is used);
    ``st``: ``((q, v, lever, c, comp), (dq, dv, dlever, dc))``, tangents [K][...]. The step's
    Jacobian (:func:`treeinfer.sim.sensitivity.step_linearization`, no staging: a ``lax.cond``
    has no place in a kernel) is computed once from the primal and applied to each tangent
    (:func:`~treeinfer.sim.sensitivity.step_tangent`)."""
    from . import fused as hd
    from . import sensitivity as sn
    from .forcing import force_fraction
    from .fused_backend import _gains as _fused_gains

    t = sim.hinge_tree
    nv = t.nv
    (q, v, lever, c, comp), (dq, dv, dlever, dc) = st
    ddir = lane["dir"] if "dir" in lane else ddir
    stiffness, damping, spring = _fused_gains(sim, lane["kp"], lane["kd"])
    f0, f1 = lane["f0"], lane["f1"]
    force = hd.vscale(f0 + force_fraction(sim.force_interp, j, n_sub, dtype) * (f1 - f0), ddir)
    lin = sn.step_linearization(
        t, q, v, stiffness, damping, spring, dt, sim.grasp_body, lane["site"], force, lever
    )
    as_dtype = lambda xs: tuple(jnp.asarray(x, dtype) for x in xs)
    tangents = []
    for a in range(n_tangents):
        # gain tangents per dof, Python 0.0 for the joints that are not inferred (fold away)
        dstiff, ddamp = [0.0] * nv, [0.0] * nv
        for col, dof in enumerate(sim.dof_ids):
            dstiff[int(dof)] = lane["dkp"][a][col]
            ddamp[int(dof)] = lane["dkd"][a][col]
        tangents.append(sn.step_tangent(t, lin, dt, dq[a], dv[a], dlever[a], dstiff, ddamp))
    out = lin.out
    first = j == 0  # the observation reads the grasp point at the observation's first substep
    c = tuple(jnp.where(first, a, b) for a, b in zip(out.site, c))
    dc = tuple(
        tuple(jnp.where(first, a, b) for a, b in zip(tn[3], dc_a)) for tn, dc_a in zip(tangents, dc)
    )
    # qpos += dt * qvel, Kahan-compensated as in the fused backend; the tangent is dq + dt dv'
    # (step_tangent's dq'), the compensation's rounding has none
    v_new = as_dtype(out.qvel)
    y = tuple(dt * a - b for a, b in zip(v_new, comp))
    q_new = tuple(a + b for a, b in zip(q, y))
    comp = tuple((a - b) - e for a, b, e in zip(q_new, q, y))
    primal = (q_new, v_new, as_dtype(out.lever), as_dtype(c), comp)
    tangent = (
        tuple(as_dtype(tn[0]) for tn in tangents),
        tuple(as_dtype(tn[1]) for tn in tangents),
        tuple(as_dtype(tn[2]) for tn in tangents),
        tuple(as_dtype(d) for d in dc),
    )
    return primal, tangent


def _use_interpret(interpret):
    return (jax.devices()[0].platform != "gpu") if interpret is None else interpret


@functools.partial(jax.jit, static_argnums=(0,), static_argnames=("block", "interpret", "rule"))
def _rollout_rows(
    sim, kp, kd, q_rest, site, dirs, f, fn, dkp, dkd, dq, substeps=None, *, block, interpret,
    rule="linearize",
):  # fmt: skip
    """Run the kernel on rows: kp, kd [R, N], q_rest [nv, N], site [3, N], dirs None or
    [3, N], f, fn [T, N]; tangents None or [K*R, N], [K*R, N], [K*nv, N] (tangent a, component
    i at row a * X + i); ``substeps`` None (the simulator's, a constant) or a traced integer
    (no tangents then); ``rule``: how the kernel carries tangents (:func:`_rollout_kernel`).
    Returns (tau [T, N], ok [N] float, dtau [K*T, N] or None)."""
    from jax.experimental import pallas as pl

    n_steps, n = f.shape
    interpret = _use_interpret(interpret)
    if interpret and block >= INTERPRET_WHOLE_BATCH:
        block = n  # the interpreter loops over programs one by one: one program, all rows
    n_pad = -(-n // block) * block
    k = 0 if dkp is None else dkp.shape[0] // sim.n_joints
    ins = [kp, kd, q_rest, site] + ([] if dirs is None else [dirs]) + [f, fn]
    traced = substeps is not None
    if traced:
        if k:
            raise ValueError("the kernel's tangents run the simulator's own substeps only")
        ins.append(jnp.full((1, n), substeps, jnp.int32))
    ins += [] if k == 0 else [dkp, dkd, dq]
    ins = [_pad(x, n_pad) for x in ins]
    spec = lambda rows: pl.BlockSpec((rows, block), lambda i: (0, i))
    out_shape = [
        jax.ShapeDtypeStruct((n_steps, n_pad), f.dtype),
        jax.ShapeDtypeStruct((1, n_pad), f.dtype),
    ]
    if k:
        out_shape.append(jax.ShapeDtypeStruct((k * n_steps, n_pad), f.dtype))
    params = None
    if not interpret:
        from jax.experimental.pallas import triton as plt

        params = plt.CompilerParams(num_warps=max(1, block // 32), num_stages=1)
    kernel = functools.partial(_rollout_kernel, sim, n_steps, k, dirs is not None, traced, rule)
    outs = pl.pallas_call(
        kernel,
        out_shape=out_shape,
        grid=(n_pad // block,),
        in_specs=[spec(x.shape[0]) for x in ins],
        out_specs=[spec(s.shape[0]) for s in out_shape],
        interpret=interpret,
        compiler_params=params,
        name="treeinfer_rollout",
    )(*ins)
    tau, ok = outs[0][:, :n], outs[1][0, :n]
    return tau, ok, (outs[2][:, :n] if k else None)


def _prepare(sim, kp, kd, forces, grasp_fraction, direction):
    """Settle P parameter sets (fused backend's Newton solve) and lay out rollout rows."""
    from .fused_backend import _prepare as _fused_prepare

    dtype = sim.dtype
    kp, kd = jnp.atleast_2d(kp).astype(dtype), jnp.atleast_2d(kd).astype(dtype)
    forces = jnp.atleast_2d(forces).astype(dtype)
    n_profiles = forces.shape[0]

    def settle(a, b):
        _, q, ok = _fused_prepare(sim, a, b, dtype)
        return q, ok

    q_rest, settled = jax.vmap(settle)(kp, kd)
    if grasp_fraction is None:
        site = jnp.broadcast_to(
            jnp.asarray(sim.mj_model.site_pos[sim.grasp_site], dtype), (n_profiles, 3)
        )
    else:
        frac = jnp.broadcast_to(jnp.asarray(grasp_fraction, dtype), (n_profiles,))
        length = float(np.linalg.norm(sim.grasp_end - sim.grasp_start))
        site = sim.branch_point(None, length, frac)
    dirs = None
    if direction is not None:
        dirs = jnp.broadcast_to(jnp.asarray(direction, dtype), (n_profiles, 3))
        dirs = dirs / jnp.linalg.norm(dirs, axis=-1, keepdims=True)
    n_particles = kp.shape[0]
    tile = lambda x: jnp.tile(x, (n_particles, 1)).T  # [B, K] -> [K, P * B]
    from .forcing import next_samples

    rows = {
        "kp": _rows(kp, n_profiles),
        "kd": _rows(kd, n_profiles),
        "q_rest": _rows(q_rest, n_profiles),
        "site": tile(site),
        "dirs": None if dirs is None else tile(dirs),
        "f": tile(forces),
        "fn": tile(jax.vmap(next_samples)(forces)),
    }
    return rows, q_rest, settled, (n_particles, n_profiles, forces.shape[1])


def _finish(sim, tau_rows, ok_rows, settled, shape):
    from . import Rollout, velocity

    n_particles, n_profiles, n_steps = shape
    tau = tau_rows.T.reshape(n_particles, n_profiles, n_steps)
    ok = (ok_rows.reshape(n_particles, n_profiles) > 0.5) & settled[:, None]
    tau = jnp.where(ok[..., None], tau, 0.0)
    tau_dot = jnp.where(ok[..., None], velocity(tau, sim.obs_dt), 0.0)
    return Rollout(tau=tau, tau_dot=tau_dot, stable=ok)


def simulate(
    sim,
    kp,
    kd,
    forces,
    grasp_fraction=None,
    direction=None,
    block: int | None = None,
    interpret=None,
    substeps=None,
):
    """:func:`treeinfer.sim.simulate` through the whole-rollout kernel (same arguments and
    :class:`~treeinfer.sim.Rollout`; the grasp branch is the simulator's own). Differentiable
    in ``kp``/``kd`` (``jax.jvp``, ``jax.grad``): exact, from the kernel's tangents.

    ``substeps``: None (the simulator's own, a constant of the kernel), or a traced integer
    passed to the kernel as an operand (:data:`TRACED_SUBSTEPS`; values only, not
    differentiable).

    ``block``: rollouts per kernel instance (a power of two, >= 32 on the GPU; default
    ``DEFAULT_BLOCK``); ``interpret``: None (Triton on a GPU, Pallas's interpreter elsewhere),
    True or False."""
    block = DEFAULT_BLOCK if block is None else int(block)
    if substeps is not None:
        rows, _, settled, shape = _prepare(sim, kp, kd, forces, grasp_fraction, direction)
        tau, ok, _ = _rollout_rows(
            sim, rows["kp"], rows["kd"], rows["q_rest"], rows["site"], rows["dirs"], rows["f"],
            rows["fn"], None, None, None, substeps, block=block, interpret=interpret,
        )  # fmt: skip
        return _finish(sim, tau, ok, settled, shape)
    return _simulate_jvp(sim, block, interpret, kp, kd, forces, grasp_fraction, direction)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1, 2))
def _simulate_jvp(sim, block, interpret, kp, kd, forces, grasp_fraction, direction):
    rows, _, settled, shape = _prepare(sim, kp, kd, forces, grasp_fraction, direction)
    tau, ok, _ = _rollout_rows(
        sim, rows["kp"], rows["kd"], rows["q_rest"], rows["site"], rows["dirs"], rows["f"],
        rows["fn"], None, None, None, block=block, interpret=interpret,
    )  # fmt: skip
    return _finish(sim, tau, ok, settled, shape)


@_simulate_jvp.defjvp
def _simulate_jvp_rule(sim, block, interpret, primals, tangents):
    """Exact JVP in (kp, kd): the kernel pushes the 2R basis tangents (the Jacobian of the
    rollout, which does not depend on the incoming tangents, so ``vmap`` over tangent
    directions computes it once), and the output tangent is its product with the incoming
    tangent: linear and transposable, so reverse mode (``jax.grad``) works too. Tangents of the
    forces, grasp fraction and direction are not propagated (data, not parameters)."""
    kp, kd, forces, grasp_fraction, direction = primals
    kp, kd = jnp.atleast_2d(kp), jnp.atleast_2d(kd)
    dtheta = jnp.concatenate(
        [
            jnp.broadcast_to(_instantiate(tangents[0], kp), kp.shape),
            jnp.broadcast_to(_instantiate(tangents[1], kd), kd.shape),
        ],
        axis=-1,
    ).astype(sim.dtype)
    n_particles, r = kp.shape
    eye = jnp.eye(2 * r, dtype=sim.dtype)
    basis = jnp.broadcast_to(eye[:, None, :], (2 * r, n_particles, 2 * r))
    ro, jac = simulate_with_tangents(
        sim, kp, kd, forces, basis[..., :r], basis[..., r:], grasp_fraction, direction,
        block, interpret,
    )  # fmt: skip
    push = lambda j: jnp.einsum("kpbt,pk->pbt", j, dtheta)
    return ro, type(ro)(tau=push(jac.tau), tau_dot=push(jac.tau_dot), stable=_float0(ro.stable))


def _instantiate(x, like):
    if isinstance(x, jax.custom_derivatives.SymbolicZero) or x is None:
        return jnp.zeros_like(like)
    return x


def _float0(x):
    return np.zeros(np.shape(x), dtype=jax.dtypes.float0)


def simulate_with_tangents(
    sim,
    kp,
    kd,
    forces,
    dkp,
    dkd,
    grasp_fraction=None,
    direction=None,
    block: int | None = None,
    interpret=None,
    layout: str | None = None,
):
    """Rollout and K exact tangent rollouts in one kernel.

    Args: as :func:`simulate`; ``dkp``, ``dkd`` [K, P, R]: K tangent directions of the gains.
    Returns ``(Rollout, Rollout of tangents)`` with tangent ``tau``/``tau_dot`` [K, P, B, T]
    (``stable`` of the second is the first's). The settled rest pose's tangent comes from
    ``jax.jvp`` through the settle (a few Newton steps, XLA).

    ``layout`` (default :data:`TANGENT_LAYOUT`): ``"lanes"`` carries all K tangents in each lane
    beside one primal, each the whole linearised step (a large kernel, slow to compile),
    ``"rows"`` gives each tangent its own lanes with a copy of the primal (2K rollouts of
    arithmetic, but K times the parallelism for the GPU and a kernel as small as the primal's
    plus one), ``"sensitivity"`` carries all K tangents in each lane like ``"lanes"`` but
    linearises the step once per substep and applies that to each tangent (least
    arithmetic: the fused backend's rule)."""
    from .fused_backend import _prepare as _fused_prepare

    block = DEFAULT_BLOCK if block is None else int(block)
    dtype = sim.dtype
    kp, kd = jnp.atleast_2d(kp).astype(dtype), jnp.atleast_2d(kd).astype(dtype)
    dkp, dkd = jnp.asarray(dkp, dtype), jnp.asarray(dkd, dtype)
    n_tan = dkp.shape[0]
    rows, q_rest, settled, shape = _prepare(sim, kp, kd, forces, grasp_fraction, direction)
    n_particles, n_profiles, n_steps = shape

    def rest_q(a, b):
        return _fused_prepare(sim, a, b, dtype)[1]

    dq = jax.vmap(lambda ta, tb: jax.jvp(jax.vmap(rest_q), (kp, kd), (ta, tb))[1])(dkp, dkd)
    # [K, P, X] -> [K * X, P * B] rows (tangent a, component i at row a * X + i)
    layout = TANGENT_LAYOUT if layout is None else layout
    if layout in ("lanes", "sensitivity"):
        # [K, P, X] -> [K * X, P * B]: tangent a, component i at row a * X + i of every lane
        lay = lambda x: jnp.concatenate([_rows(x[a], n_profiles) for a in range(n_tan)], axis=0)
        rule = "linearize" if layout == "lanes" else "sensitivity"
        tau, ok, dtau = _rollout_rows(
            sim, rows["kp"], rows["kd"], rows["q_rest"], rows["site"], rows["dirs"], rows["f"],
            rows["fn"], lay(dkp), lay(dkd), lay(dq), block=block, interpret=interpret,
            rule=rule,
        )  # fmt: skip
    elif layout == "rows":
        # one tangent per lane: the lanes of tangent a are columns [a * N, (a + 1) * N)
        n = n_particles * n_profiles
        rep = {k: None if v is None else jnp.tile(v, (1, n_tan)) for k, v in rows.items()}
        lay = lambda x: jnp.concatenate([_rows(x[a], n_profiles) for a in range(n_tan)], axis=1)
        tau, ok, dtau = _rollout_rows(
            sim, rep["kp"], rep["kd"], rep["q_rest"], rep["site"], rep["dirs"], rep["f"],
            rep["fn"], lay(dkp), lay(dkd), lay(dq), block=block, interpret=interpret,
        )  # fmt: skip
        tau, ok = tau[:, :n], ok[:n]
        dtau = dtau.reshape(n_steps, n_tan, n).transpose(1, 0, 2).reshape(n_tan * n_steps, n)
    else:
        raise ValueError(f"layout: one of {', '.join(TANGENT_LAYOUTS)}, got {layout!r}")
    ro = _finish(sim, tau, ok, settled, shape)
    from . import velocity

    dtau = dtau.reshape(n_tan, n_steps, n_particles, n_profiles).transpose(0, 2, 3, 1)
    mask = ro.stable[None, ..., None]
    dtau = jnp.where(mask, dtau, 0.0)
    dtau_dot = jnp.where(mask, velocity(dtau, sim.obs_dt), 0.0)
    return ro, type(ro)(tau=dtau, tau_dot=dtau_dot, stable=ro.stable)
