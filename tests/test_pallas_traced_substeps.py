"""The Pallas kernel with the substep count as a runtime operand (``pallas.TRACED_SUBSTEPS``,
off by default): in Pallas's interpreter on the CPU, against the fused backend at the same
traced step. On a GPU the Triton lowering of the dynamic loop bound is the integrator's to
check (``benchmarks/pallas_check.py``)."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest
from test_pallas_backend import pallas_chain

from treeinfer.data.forces import profile_set
from treeinfer.sim import _simulate, make_simulator
from treeinfer.sim import pallas as pk
from treeinfer.sim.synthetic import default_true_params

T = 40


@pytest.fixture(scope="module")
def setup():
    tree = pallas_chain()
    sim = make_simulator(tree, obs_dt=0.01, substeps=2, backend="fused")
    kp, kd = default_true_params(tree, np.random.default_rng(0))
    kp = jnp.asarray(kp[None] * np.array([[1.0], [0.5], [2.0]]), jnp.float32)
    kd = jnp.asarray(kd[None] * np.array([[1.0], [2.0], [0.5]]), jnp.float32)
    forces = 5.0 * profile_set("mixed", n=2, duration=T * 0.01, dt=0.01, seed=1)[:, :T]
    return sim, kp, kd, jnp.asarray(forces, jnp.float32)


@pytest.mark.parametrize("substeps", [2, 5])
def test_kernel_with_a_runtime_step_matches_the_fused_backend(setup, substeps):
    sim, kp, kd, forces = setup
    s = jnp.int32(substeps)
    ref = _simulate(sim, kp, kd, forces, substeps=s)  # fused, traced step
    out = pk.simulate(sim, kp, kd, forces, block=4, interpret=True, substeps=s)
    assert float(jnp.abs(ref.tau).max()) > 1e-4
    np.testing.assert_allclose(out.tau, ref.tau, rtol=1e-5, atol=1e-7)
    assert np.array_equal(out.stable, ref.stable)
    if substeps == sim.substeps:  # the constant-step kernel at the same step: the same values
        own = pk.simulate(sim, kp, kd, forces, block=4, interpret=True)
        np.testing.assert_allclose(out.tau, own.tau, rtol=1e-5, atol=1e-7)


def test_the_switch_routes_a_traced_step_to_the_kernel(setup, monkeypatch):
    sim, kp, kd, forces = setup
    psim = dataclasses.replace(sim, backend="pallas")
    s = jnp.int32(3)
    monkeypatch.setattr(pk, "TRACED_SUBSTEPS", False)
    assert not pk.supported(psim, None, s)  # switched off: a traced step runs the fused path
    monkeypatch.setattr(pk, "TRACED_SUBSTEPS", True)
    assert pk.supported(psim, None, s)
    calls, real = [], pk.simulate

    def spy(*args, **kw):
        calls.append(kw.get("substeps"))
        return real(*args, **{**kw, "block": 4, "interpret": True})

    monkeypatch.setattr(pk, "simulate", spy)
    out = _simulate(psim, kp, kd, forces, substeps=s)
    assert calls == [s]  # the kernel ran, with the step as its operand
    ref = _simulate(sim, kp, kd, forces, substeps=s)
    np.testing.assert_allclose(out.tau, ref.tau, rtol=1e-5, atol=1e-7)
    with pytest.raises(ValueError, match="own substeps"):
        pk._rollout_rows(sim, *([jnp.zeros((1, 4))] * 4), None, jnp.zeros((T, 4)),
                         jnp.zeros((T, 4)), jnp.zeros((2, 4)), jnp.zeros((2, 4)),
                         jnp.zeros((2, 4)), s, block=4, interpret=True)  # fmt: skip


def test_the_environment_switch_is_validated(monkeypatch):
    from treeinfer.errors import ConfigError

    name = "TREEINFER_PALLAS_TRACED_SUBSTEPS"
    monkeypatch.delenv(name, raising=False)
    assert pk._switch(name) is True  # on by default (timed on an H100)
    monkeypatch.setenv(name, "off")
    assert pk._switch(name) is False
    monkeypatch.setenv(name, "on")
    assert pk._switch(name) is True
    monkeypatch.setenv(name, "maybe")
    with pytest.raises(ConfigError, match=name):
        pk._switch(name)
