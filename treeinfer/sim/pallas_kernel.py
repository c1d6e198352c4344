"""The Pallas kernel of the Pallas backend (:mod:`treeinfer.sim.pallas`): :func:`_rollout_kernel`,
the body that runs every observation and substep of a block of rollouts (and their tangents),
:func:`_sensitivity_substep`, its substep by the sensitivity rule, and :func:`_rollout_rows`,
the ``pallas_call`` over the packed rows (:mod:`treeinfer.sim.pallas_layout`).

Separate from the dispatch (:mod:`treeinfer.sim.pallas`: when the kernel runs, its switches and
the exact JVP) because it is the code that runs inside Triton, under Pallas's rules (element
arithmetic on ``[BLOCK]`` rows, no ``lax.cond``), and is read and timed on its own (issue 26).
:mod:`treeinfer.sim.pallas` re-exports every name (they lived there before the split), and its
callers look :func:`_rollout_rows` up there, so a test may wrap it there.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from .pallas_layout import _pad

# in the interpreter (CPU), blocks of at least this many rows become one program over all rows
INTERPRET_WHOLE_BATCH = 32


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
