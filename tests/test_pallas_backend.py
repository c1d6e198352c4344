"""The Pallas whole-rollout kernel (``treeinfer.sim.pallas``) against the fused XLA step.

Run in Pallas's interpreter on the CPU (small sizes); on a GPU ``benchmarks/pallas_check.py``
checks the Triton-compiled kernel the same way. References: the fused backend (the same
MuJoCo step as XLA loops) for rollouts and exact gradients, and central differences of the
kernel's own rollouts for the tangents (independent of any autodiff).
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from treeinfer.data.forces import profile_set
from treeinfer.model.gradients import central_difference, jvp_value_and_grad
from treeinfer.sim import make_simulator, simulate
from treeinfer.sim import pallas as pk
from treeinfer.sim.synthetic import default_true_params
from treeinfer.tree.generators import chain

T = 10
# exact gradients of the two backends agree to float32 rounding: to ~1e-5 of their scale in the
# CPU interpreter (the same XLA arithmetic); Triton contracts multiply-adds into FMAs where XLA
# does not, and the velocity term's differences amplify that to ~3e-4 on an H100
GRAD_TOL = 1e-4 if jax.devices()[0].platform == "cpu" else 1e-3


def pallas_chain():
    """The 2-link tilted chain of the Pallas kernel tests (also test_pallas_traced_substeps)."""
    return chain(
        2,
        lengths=[0.6, 0.4],
        radii=[0.03, 0.015],
        angles_deg=[0.0, -10.0],
        base_position=(0.0, 0.0, 1.5),
        base_pitch_deg=20.0,
        levels=2,
        name="c2",
    )


@pytest.fixture(scope="module")
def setup():
    tree = pallas_chain()
    sim = make_simulator(tree, obs_dt=0.01, substeps=2, backend="fused")
    rng = np.random.default_rng(0)
    kp, kd = default_true_params(tree, rng)
    truth = np.concatenate([np.log(kp), np.log(kd)])
    theta = jnp.asarray(truth + 0.3 * rng.normal(size=(3, truth.size)), jnp.float32)
    forces = jnp.asarray(profile_set("mixed", n=2, duration=T * 0.01, dt=0.01, seed=1)[:, :T])
    return sim, theta, forces.astype(jnp.float32) * 5.0


def _gains(sim, theta):
    r = sim.n_joints
    return jnp.exp(theta[:, :r]), jnp.exp(theta[:, r:])


def test_rollout_matches_fused_step(setup):
    sim, theta, forces = setup
    kp, kd = _gains(sim, theta)
    ref = simulate(sim, kp, kd, forces)
    out = pk.simulate(sim, kp, kd, forces, block=4, interpret=True)
    assert float(jnp.abs(ref.tau).max()) > 1e-4  # the pull moves the branch
    np.testing.assert_allclose(out.tau, ref.tau, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(out.tau_dot, ref.tau_dot, rtol=1e-5, atol=1e-5)
    assert np.array_equal(out.stable, ref.stable)
    # per-profile pull direction and grasp point
    dirs = jnp.asarray([[0.0, 0.0, -1.0], [1.0, 0.0, -1.0]])
    ref = simulate(sim, kp, kd, forces, grasp_fraction=jnp.asarray([0.5, 1.0]), direction=dirs)
    out = pk.simulate(sim, kp, kd, forces, jnp.asarray([0.5, 1.0]), dirs, block=4,
                      interpret=True)  # fmt: skip
    np.testing.assert_allclose(out.tau, ref.tau, rtol=1e-5, atol=1e-7)


@pytest.mark.gpu
def test_triton_compiled_kernel_matches_fused_step(setup):
    """On a GPU, the kernel as Triton compiles it (not the interpreter) against the fused step.
    Triton contracts multiply-adds into FMAs where XLA does not, so the tolerance is float32
    rounding amplified over the rollout (1 micrometre), not the interpreter's bit-level one."""
    sim, theta, forces = setup
    kp, kd = _gains(sim, theta)
    ref = simulate(sim, kp, kd, forces)
    out = pk.simulate(sim, kp, kd, forces, block=4)
    np.testing.assert_allclose(out.tau, ref.tau, rtol=1e-4, atol=1e-6)
    assert np.array_equal(out.stable, ref.stable)


def test_backend_hook_routes_to_kernel(setup):
    sim, theta, forces = setup
    assert pk.resolve("fused") == "fused" and pk.resolve("pallas") == "pallas"
    if jax.devices()[0].platform != "gpu":
        assert pk.resolve("auto") == "fused"  # the interpreter is never picked on a CPU
    psim = dataclasses.replace(sim, backend="pallas")
    kp, kd = _gains(sim, theta)
    a = simulate(psim, kp, kd, forces)
    b = pk.simulate(sim, kp, kd, forces)
    np.testing.assert_array_equal(a.tau, b.tau)


@pytest.mark.parametrize("layout", ["rows", "lanes"])
def test_exact_gradient_matches_fused_and_central_differences(setup, layout, monkeypatch):
    sim, theta, forces = setup
    monkeypatch.setattr(pk, "TANGENT_LAYOUT", layout)
    monkeypatch.setattr(pk, "DEFAULT_BLOCK", 4)

    def loglik(simfn):
        def f(th):
            ro = simfn(sim, *_gains(sim, th), forces)
            return -1e3 * jnp.sum(ro.tau**2 + 1e-3 * ro.tau_dot**2, axis=(1, 2))

        return f

    v_ref, g_ref = jax.jit(jvp_value_and_grad(loglik(simulate)))(theta)
    v, g = jax.jit(jvp_value_and_grad(loglik(pk.simulate)))(theta)
    np.testing.assert_allclose(v, v_ref, rtol=1e-5)
    scale = float(jnp.abs(g_ref).max())
    assert scale > 0
    np.testing.assert_allclose(g, g_ref, atol=GRAD_TOL * scale)
    # independent reference: central differences of the kernel's own rollouts (float64 would be
    # tighter; float32 FD error at the default step is ~1e-3 of the gradient's scale here)
    _, g_fd = jax.jit(central_difference(loglik(pk.simulate)))(theta)
    np.testing.assert_allclose(g, g_fd, atol=2e-2 * scale)


def test_reverse_mode_and_vmap_over_data_sets(setup, monkeypatch):
    """``jax.grad`` (the generative likelihoods' route) and a ``vmap`` over data sets (the
    calibration's) go through the kernel's custom JVP; both match the fused step's."""
    sim, theta, forces = setup
    monkeypatch.setattr(pk, "DEFAULT_BLOCK", 4)
    kp, kd = _gains(sim, theta)

    def loss(simfn, th, f):
        ro = simfn(sim, *_gains(sim, th), f)
        return 1e3 * jnp.sum(ro.tau**2)

    g_ref = jax.grad(lambda th: loss(simulate, th, forces))(theta)
    g = jax.grad(lambda th: loss(pk.simulate, th, forces))(theta)
    np.testing.assert_allclose(g, g_ref, atol=GRAD_TOL * float(jnp.abs(g_ref).max()))
    batch = jnp.stack([forces, 0.5 * forces])
    ref = jax.vmap(lambda f: simulate(sim, kp, kd, f).tau)(batch)
    out = jax.vmap(lambda f: pk.simulate(sim, kp, kd, f).tau)(batch)
    np.testing.assert_allclose(out, ref, rtol=1e-5, atol=1e-7)
