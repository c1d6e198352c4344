"""Forward sensitivities of the fused step and pull (``treeinfer.sim.sensitivity`` and the
``custom_jvp`` of ``fused_backend._pull_sensitivity``) against independent references:

* the analytic kinematic tangent against ``jax.jvp`` of the kinematics;
* one step's Jacobian-times-tangent against ``jax.jvp`` of ``fused.step`` (random states, gains
  and tangents, staged and unstaged), float64;
* whole pulls against ``jax.jvp`` of the plain pull, against central differences of the
  rollout (float64), on 1-, 2- and 3-joint trees, and against central differences of MuJoCo C;
* the likelihood gradient by forward mode (``jvp_value_and_grad``) against reverse mode (the
  rule's transpose); per-profile directions and grasp branches;
* force tangents (``force_noise``'s ``jax.jacfwd`` in the forces, at the simulator's own and at
  a traced substep count): one step against ``jax.jvp`` of ``fused.step`` in the force, whole
  pulls against the plain path and central differences of the rollout, and columns against
  central differences of MuJoCo C.

"The plain path" is ``jax.jvp`` of the step code, with
:data:`treeinfer.sim.fused_backend.SENSITIVITY_RULE` off while tracing (:func:`plain_jvp`).
"""

from __future__ import annotations

import contextlib
import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from test_forward_mode import GENERAL_MJCF  # tests/ is on sys.path (pytest prepend)

from treeinfer.examples import example_path
from treeinfer.model.gradients import autodiff_value_and_grad, jvp_value_and_grad
from treeinfer.sim import _simulate, _simulate_force_jacobian, make_simulator
from treeinfer.sim import fused as hd
from treeinfer.sim import fused_backend as fb
from treeinfer.sim import sensitivity as sn
from treeinfer.tree.description import load_tree, tree_from_dict

ONE_BRANCH = {
    "name": "one",
    "base": {"position": [0.0, 0.0, 1.0], "pitch_deg": 25.0, "yaw_deg": 0.0},
    "gravity": [0.0, 0.0, -9.81],
    "density": 700.0,
    "branches": [{"name": "b", "parent": None, "length": 0.7, "radius": 0.02}],
    "grasp": {"branch": "b", "fraction": 0.8},
    "inference": {"levels": 1, "prior": {"kp": [5.0, 500.0], "kd": [0.05, 10.0]}},
}


@contextlib.contextmanager
def plain_jvp():
    """Trace with the sensitivity rule off: ``jax.jvp`` of the plain step code (the reference)."""
    old, fb.SENSITIVITY_RULE = fb.SENSITIVITY_RULE, False
    try:
        yield
    finally:
        fb.SENSITIVITY_RULE = old


def _trees():
    yield "one", tree_from_dict(ONE_BRANCH)
    yield "two", load_tree(example_path("two_branch"))
    yield "three", load_tree(example_path("three_branch"))


TREES = dict(_trees())


def _hinge(name):
    if name == "general":
        return hd.from_mjmodel(mujoco.MjModel.from_xml_string(GENERAL_MJCF))
    return make_simulator(TREES[name], obs_dt=0.01).hinge_tree


@pytest.mark.parametrize("name", ["general", "one", "three"])
def test_kinematics_tangent_equals_jvp(name):
    t = _hinge(name)
    rng = np.random.default_rng(0)
    with jax.enable_x64(True):
        q = jnp.asarray(rng.normal(size=t.nv) * 0.5)
        kin = hd.kinematics(t, [q[i] for i in range(t.nv)])
        for k in range(t.nv):
            e = jnp.zeros(t.nv).at[k].set(1.0)
            _, ref = jax.jvp(lambda x: hd.kinematics(t, [x[i] for i in range(t.nv)]), (q,), (e,))
            ours = sn.kinematics_tangent(t, kin, k)
            for a, b in zip(jax.tree_util.tree_leaves(ours), jax.tree_util.tree_leaves(ref)):
                np.testing.assert_allclose(np.asarray(a, float), np.asarray(b), atol=1e-13)


def _random_step_args(t, rng, inferred):
    """Arguments of ``fused.step`` with traced gains at the ``inferred`` dofs, and a tangent."""
    q = jnp.asarray(rng.normal(size=t.nv) * 0.5)
    v = jnp.asarray(rng.normal(size=t.nv) * 1.5)
    stiff = [float(x) for x in rng.uniform(5, 80, t.nv)]
    damp = [float(x) for x in rng.uniform(0.1, 3, t.nv)]
    for i in inferred:
        stiff[i], damp[i] = jnp.asarray(stiff[i]), jnp.asarray(damp[i])
    spring = [float(x) for x in rng.normal(size=t.nv) * 0.1]
    force = tuple(jnp.asarray(x) for x in rng.normal(size=3) * 4)
    lever = tuple(jnp.asarray(x) for x in rng.normal(size=3) * 0.1)
    tangent = {
        "dq": jnp.asarray(rng.normal(size=t.nv)),
        "dv": jnp.asarray(rng.normal(size=t.nv)),
        "dl": tuple(jnp.asarray(x) for x in rng.normal(size=3)),
        "dstiff": [jnp.asarray(rng.normal() * 10) if i in inferred else 0.0 for i in range(t.nv)],
        "ddamp": [jnp.asarray(rng.normal()) if i in inferred else 0.0 for i in range(t.nv)],
    }
    return q, v, stiff, damp, spring, force, lever, tangent


@pytest.mark.parametrize(
    "name,staged", [("general", False), ("general", True), ("one", False), ("three", True)]
)
def test_step_tangent_equals_jvp_of_step(name, staged):
    t = _hinge(name)
    rng = np.random.default_rng(1)
    dt, body, site_local = 0.002, t.nbody, (0.1, 0.02, 0.0)
    inferred = list(range(t.nv))[-2:]
    with jax.enable_x64(True):
        for _ in range(1 if staged else 3):  # staged: one compile per state
            q, v, stiff, damp, spring, force, lever, tg = _random_step_args(t, rng, inferred)

            def full(q, v, lever, gk, gd):
                s, d = list(stiff), list(damp)
                for j, i in enumerate(inferred):
                    s[i], d[i] = gk[j], gd[j]
                out = hd.step(t, q, v, s, d, spring, dt, body, site_local, force, lever)
                qn = q + dt * jnp.stack(out.qvel)  # qpos += dt qvel', as the pull
                return qn, jnp.stack(out.qvel), jnp.stack(out.lever), jnp.stack(out.site)

            gk = jnp.stack([stiff[i] for i in inferred])
            gd = jnp.stack([damp[i] for i in inferred])
            dgk = jnp.stack([tg["dstiff"][i] for i in inferred])
            dgd = jnp.stack([tg["ddamp"][i] for i in inferred])
            primal, ref = jax.jvp(
                full, (q, v, lever, gk, gd), (tg["dq"], tg["dv"], tg["dl"], dgk, dgd)
            )
            step = lambda: sn.step_linearization(
                t, q, v, stiff, damp, spring, dt, body, site_local, force, lever,
                pred=jnp.asarray(True) if staged else None,
            )  # fmt: skip
            lin = jax.jit(step)() if staged else step()
            dq, dv, dl, dsite = sn.step_tangent(
                t, lin, dt, tg["dq"], tg["dv"], tg["dl"], tg["dstiff"], tg["ddamp"]
            )
            ours = (jnp.stack(dq), jnp.stack(dv), jnp.stack(dl), jnp.stack(dsite))
            for a, b in zip(ours, ref):
                np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10 * np.abs(b).max())
            np.testing.assert_array_equal(jnp.stack(lin.out.qvel), primal[1])


def _pull_data(name, n_steps=40):
    sim = make_simulator(TREES[name], obs_dt=0.01)
    t = np.arange(n_steps) * 0.01
    forces = np.stack([4.0 * np.clip(t / 0.2, 0, 1), 2.0 * np.sin(7 * t) + 2.0])
    return sim, forces


@pytest.mark.parametrize(
    "name,plain,staging", [("one", False, "off"), ("two", False, "auto"), ("three", True, "auto")]
)
def test_pull_tangent_equals_plain_jvp_and_central_differences(name, plain, staging, monkeypatch):
    monkeypatch.setattr(sn, "STAGING", staging)  # "off": the GPU's unstaged linearization
    sim, forces = _pull_data(name, 25)
    r = sim.n_joints
    rng = np.random.default_rng(2)
    with jax.enable_x64(True):
        kp = jnp.asarray(rng.uniform(30, 200, (2, r)))
        kd = jnp.asarray(rng.uniform(0.3, 3, (2, r)))
        f = jnp.asarray(forces)
        dkp = jnp.asarray(rng.normal(size=(2, r))) * kp
        dkd = jnp.asarray(rng.normal(size=(2, r))) * kd
        fast = lambda a, b: _simulate(sim, a, b, f).tau
        # the plain path: jax.jvp through the step code (traced with the rule off)
        slow = lambda a, b: _simulate(sim, a, b, f).tau
        tau, dtau = jax.jit(lambda a, b: jax.jvp(fast, (a, b), (dkp, dkd)))(kp, kd)
        scale = np.abs(np.asarray(dtau)).max()
        assert scale > 1e-4
        # one compiled rollout for the primal check and both central-difference evaluations
        rollout = jax.jit(fast)
        np.testing.assert_allclose(tau, rollout(kp, kd), rtol=1e-12, atol=1e-15)
        if plain:
            with plain_jvp():
                tau_p, dtau_p = jax.jit(lambda a, b: jax.jvp(slow, (a, b), (dkp, dkd)))(kp, kd)
            np.testing.assert_allclose(tau, tau_p, rtol=1e-12, atol=1e-15)
            np.testing.assert_allclose(dtau, dtau_p, rtol=1e-9, atol=1e-9 * scale)
        h = 1e-6
        fd = (rollout(kp + h * dkp, kd + h * dkd) - rollout(kp - h * dkp, kd - h * dkd)) / (2 * h)
        np.testing.assert_allclose(dtau, fd, rtol=1e-5, atol=1e-6 * scale)


def test_likelihood_gradient_forward_reverse_and_force_fallback():
    from treeinfer.data.trajectories import Trajectory, stack_trajectories
    from treeinfer.model.likelihood import boltzmann_log_likelihood
    from treeinfer.sim.reference import simulate_reference

    sim, forces = _pull_data("two", 20)
    kp, kd = np.array([120.0, 40.0]), np.array([1.0, 0.3])
    t = np.arange(forces.shape[1]) * 0.01
    trajs = [
        Trajectory(t, f, *simulate_reference(sim, kp, kd, f), f"p{i}") for i, f in enumerate(forces)
    ]
    obs = stack_trajectories(trajs)
    rng = np.random.default_rng(3)
    with jax.enable_x64(True):
        theta = jnp.asarray(np.log(np.concatenate([kp, kd])) + rng.normal(scale=0.3, size=(3, 4)))
        loglik = boltzmann_log_likelihood(sim, obs, kT=0.05)
        value, grad = jax.jit(jvp_value_and_grad(loglik))(theta)
        value_r, grad_r = jax.jit(autodiff_value_and_grad(loglik))(theta)
        np.testing.assert_allclose(value, value_r, rtol=1e-12)
        np.testing.assert_allclose(grad, grad_r, rtol=1e-9, atol=1e-9 * np.abs(grad).max())


def test_pull_uses_the_rule_for_the_scalar_layout_at_any_substep_count():
    sim, forces = _pull_data("two", 5)
    assert not fb.uses_levels(sim)
    f = jnp.asarray(forces)
    ones = jnp.ones((1, 2))
    for n in (None, 2):  # the simulator's own count, a static one
        jaxpr = str(jax.make_jaxpr(lambda a, n=n: _simulate(sim, a, a, f, substeps=n).tau)(ones))
        assert "name=_pull_sensitivity" in jaxpr

    def traced():  # a new function each time: make_jaxpr keeps the traces of one
        return jax.make_jaxpr(lambda a, n: _simulate(sim, a, a, f, substeps=n).tau)(
            ones, jnp.int32(3)
        )

    assert "name=_pull_sensitivity" in str(traced())
    with plain_jvp():
        assert "name=_pull_sensitivity" not in str(traced())
    lv_sim = dataclasses.replace(sim, step_layout="levels")
    jaxpr = str(jax.make_jaxpr(lambda a: _simulate(lv_sim, a, a, f).tau)(ones))
    assert "name=_pull_sensitivity" not in jaxpr


def test_step_force_tangent_equals_jvp_of_step():
    """The force column of the step's linearization against ``jax.jvp`` of ``fused.step`` in
    the force magnitude (float64, random states, a general tree, staged and unstaged)."""
    t = _hinge("general")
    rng = np.random.default_rng(7)
    dt, body, site_local = 0.002, t.nbody, (0.1, 0.02, 0.0)
    with jax.enable_x64(True):
        for staged in (False, True):
            q, v, stiff, damp, spring, _, lever, tg = _random_step_args(t, rng, [])
            fdir = tuple(float(x) for x in rng.normal(size=3))
            f0, df = jnp.asarray(3.7), jnp.asarray(rng.normal())

            def full(q, v, lever, f):
                force = tuple(f * d for d in fdir)
                out = hd.step(t, q, v, stiff, damp, spring, dt, body, site_local, force, lever)
                qn = q + dt * jnp.stack(out.qvel)
                return qn, jnp.stack(out.qvel), jnp.stack(out.lever), jnp.stack(out.site)

            _, ref = jax.jvp(full, (q, v, lever, f0), (tg["dq"], tg["dv"], tg["dl"], df))

            def step(q, v, f):
                return sn.step_linearization(
                    t, q, v, stiff, damp, spring, dt, body, site_local,
                    tuple(f * d for d in fdir), lever,
                    pred=jnp.asarray(True) if staged else None, force_dir=fdir,
                )  # fmt: skip

            lin = jax.jit(step)(q, v, f0) if staged else step(q, v, f0)
            zeros = [0.0] * t.nv
            dq, dv, dl, dsite = sn.step_tangent(
                t, lin, dt, tg["dq"], tg["dv"], tg["dl"], zeros, zeros, df
            )
            ours = (jnp.stack(dq), jnp.stack(dv), jnp.stack(dl), jnp.stack(dsite))
            assert np.abs(np.asarray(lin.force)).max() > 0
            for a, b in zip(ours, ref):
                np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10 * np.abs(b).max())


@pytest.mark.parametrize("name,traced", [("one", False), ("two", True), ("three", True)])
def test_force_jacobian_equals_plain_jvp_and_central_differences(name, traced):
    """``jax.jacfwd`` in the force samples (``force_noise.force_jacobian``'s program) through the
    rule against the plain path and against central differences of the rollout in each force
    sample (float64), at the simulator's own step or a traced substep count, with a pull
    direction per profile on the two-branch tree."""
    sim, forces = _pull_data(name, 12)
    rng = np.random.default_rng(11)
    opts = {"direction": jnp.asarray([[1.0, 0.0, -0.3], [0.0, 0.4, -1.0]])} if name == "two" else {}
    with jax.enable_x64(True):
        kp = jnp.asarray(rng.uniform(30, 200, (1, sim.n_joints)))
        kd = jnp.asarray(rng.uniform(0.3, 3, (1, sim.n_joints)))
        f = jnp.asarray(forces)
        n = jnp.int32(sim.substeps + 1) if traced else None

        def tau(x, n):
            return _simulate(sim, kp, kd, x, substeps=n, **opts).tau[0]

        jac = jax.jit(jax.jacfwd(tau))(f, n)  # [B, T, B, T]
        with plain_jvp():
            jac_p = jax.jit(jax.jacfwd(tau))(f, n)
        scale = np.abs(np.asarray(jac)).max()
        assert scale > 1e-5
        np.testing.assert_allclose(jac, jac_p, rtol=1e-9, atol=1e-10 * scale)
        # pulls are independent, the response causal
        b, t = forces.shape
        assert np.abs(np.asarray(jac)[0, :, 1]).max() == 0.0
        assert np.abs(np.asarray(jac)[0, :, 0][np.triu_indices(t, 1)]).max() == 0.0
        rollout = jax.jit(tau)
        h = 1e-5
        for s in (0, 3, t - 1):
            e = jnp.zeros_like(f).at[:, s].set(h)
            fd = (rollout(f + e, n) - rollout(f - e, n)) / (2 * h)
            ours = jac[:, :, :, s].sum(-1)  # every pull's sample s moved
            np.testing.assert_allclose(ours, fd, rtol=1e-6, atol=1e-7 * scale)


@pytest.mark.parametrize("name,traced", [("one", False), ("two", True), ("three", True)])
def test_force_jacobian_as_one_tangent_axis_equals_jacfwd(name, traced):
    """``_simulate_force_jacobian`` (the T force tangents carried as one trailing axis of the
    state tangent, no vmap level: ``force_noise``'s program since session 14) against
    ``jax.jacfwd`` of ``_simulate`` per pull under vmap (the program before), in the
    simulator's float32: the rollout, the stability flags and J; and None where the rule does
    not apply."""
    sim, forces = _pull_data(name, 12)
    rng = np.random.default_rng(5)
    kp = jnp.asarray(rng.uniform(30, 200, (1, sim.n_joints)), jnp.float32)
    kd = jnp.asarray(rng.uniform(0.3, 3, (1, sim.n_joints)), jnp.float32)
    f = jnp.asarray(forces, jnp.float32)
    n = jnp.int32(sim.substeps + 1) if traced else None

    def per_pull(x, n):
        def tau(fb):
            ro = _simulate(sim, kp, kd, fb[None], substeps=n)
            return ro.tau[0, 0], ro.stable[0, 0]

        return jax.vmap(jax.jacfwd(tau, has_aux=True))(x)

    jac_ref, ok_ref = jax.jit(per_pull)(f, n)
    tau, ok, jac = jax.jit(lambda x, n: _simulate_force_jacobian(sim, kp[0], kd[0], x, None, n))(
        f, n
    )
    scale = np.abs(np.asarray(jac_ref)).max()
    assert scale > 1e-5 and np.all(np.asarray(ok_ref))
    np.testing.assert_array_equal(ok, ok_ref)
    np.testing.assert_allclose(jac, jac_ref, rtol=1e-6, atol=1e-6 * scale)
    # the rule's primal (pull_with_tangent) rounds a few values otherwise than the plain rollout
    plain = np.asarray(_simulate(sim, kp, kd, f, substeps=n).tau[0])
    np.testing.assert_allclose(tau, plain, rtol=1e-6, atol=1e-4 * np.abs(plain).max())
    with plain_jvp():
        assert _simulate_force_jacobian(sim, kp[0], kd[0], f) is None


def test_force_jacobian_matches_central_differences_of_mujoco_c():
    """An independent reference for the force columns: central differences of the MuJoCo C
    rollout (``simulate_reference``, ``mj_step`` in float64) in single force samples."""
    from treeinfer.sim.reference import simulate_reference

    sim = make_simulator(TREES["three"], obs_dt=0.01)
    t = np.arange(30) * 0.01
    f = 4.0 * np.clip(t / 0.2, 0, 1)
    kp, kd = np.array([120.0, 60.0, 30.0]), np.array([1.0, 0.5, 0.3])
    with jax.enable_x64(True):
        tau = lambda x: _simulate(sim, kp[None], kd[None], x[None]).tau[0, 0]
        jac = np.asarray(jax.jit(jax.jacfwd(tau))(jnp.asarray(f)))
        for s in (0, 5, 17):
            h = 1e-4
            up, down = f.copy(), f.copy()
            up[s] += h
            down[s] -= h
            ref = simulate_reference(sim, kp, kd, up)[0] - simulate_reference(sim, kp, kd, down)[0]
            ref = ref / (2 * h)
            assert np.abs(ref).max() > 1e-6
            np.testing.assert_allclose(jac[:, s], ref, rtol=1e-6, atol=1e-6 * np.abs(ref).max())


def test_pull_tangent_with_direction_grasp_branch_and_fraction():
    """Per-profile pull directions, another grasped branch and a grasp fraction (issue 13's
    pulls) go through the rule too: same tangent as the plain path."""
    sim, forces = _pull_data("two", 15)
    rng = np.random.default_rng(5)
    with jax.enable_x64(True):
        kp = jnp.asarray(rng.uniform(30, 200, (2, 2)))
        kd = jnp.asarray(rng.uniform(0.3, 3, (2, 2)))
        dkp, dkd = jnp.asarray(rng.normal(size=(2, 2))) * kp, jnp.asarray(rng.normal(size=(2, 2)))
        f = jnp.asarray(forces)
        opts = {
            "direction": jnp.asarray([[1.0, 0.0, -0.3], [0.0, 1.0, 0.0]]),
            "grasp_branch": ("parent", "child"),
            "grasp_fraction": jnp.asarray([0.6, 0.9]),
        }
        fast = lambda a, b: _simulate(sim, a, b, f, **opts).tau
        _, dtau = jax.jvp(fast, (kp, kd), (dkp, dkd))
        with plain_jvp():
            _, dtau_p = jax.jvp(fast, (kp, kd), (dkp, dkd))
        scale = np.abs(np.asarray(dtau_p)).max()
        assert scale > 1e-5
        np.testing.assert_allclose(dtau, dtau_p, rtol=1e-9, atol=1e-9 * scale)


def test_pull_tangent_matches_central_differences_of_mujoco_c():
    """An independent reference: central differences of the MuJoCo C rollout
    (``simulate_reference``, ``mj_step`` in float64) in each gain, three-branch tree (its side
    joint's gains are fixed constants)."""
    from treeinfer.sim.reference import simulate_reference

    sim = make_simulator(TREES["three"], obs_dt=0.01)
    t = np.arange(30) * 0.01
    f = 4.0 * np.clip(t / 0.2, 0, 1)
    kp, kd = np.array([120.0, 60.0, 30.0]), np.array([1.0, 0.5, 0.3])
    with jax.enable_x64(True):
        tau = lambda a, b: _simulate(sim, a[None], b[None], jnp.asarray(f)[None]).tau[0, 0]
        push = jax.jit(lambda da, db: jax.jvp(tau, (jnp.asarray(kp), jnp.asarray(kd)), (da, db)))
        for j in range(6):
            e = np.zeros(6)
            e[j] = 1.0
            gains = np.concatenate([kp, kd])
            _, ours = push(jnp.asarray((e * gains)[:3]), jnp.asarray((e * gains)[3:]))
            h = 1e-5
            up, down = gains * (1 + h * e), gains * (1 - h * e)
            ref = (
                simulate_reference(sim, up[:3], up[3:], f)[0]
                - simulate_reference(sim, down[:3], down[3:], f)[0]
            ) / (2 * h)
            assert np.abs(ref).max() > 1e-5
            np.testing.assert_allclose(ours, ref, rtol=1e-6, atol=1e-6 * np.abs(ref).max())
