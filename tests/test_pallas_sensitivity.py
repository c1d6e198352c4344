"""The Pallas kernel's ``"sensitivity"`` tangent layout (``treeinfer.sim.pallas``): the step's
state Jacobian computed once per substep and applied to every tangent in the lane.

Run in Pallas's interpreter on the CPU (tiny trees, short pulls). References: the ``"rows"``
layout (``jax.linearize`` of the whole step), the fused backend's exact JVP, the value-only
kernel for the primal, and central differences of the fused backend's rollout in float64
(independent of any autodiff and of the kernel).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_pallas_backend import pallas_chain

from treeinfer.data.forces import profile_set
from treeinfer.examples import example_path
from treeinfer.sim import make_simulator, simulate
from treeinfer.sim import pallas as pk
from treeinfer.sim.synthetic import default_true_params
from treeinfer.tree.description import load_tree

T = 24
K = 3  # random tangent directions per call
# float32 tangents of two exact methods: to ~1e-6 of their scale in the interpreter (measured
# <= 4e-7); Triton's FMA contraction is the GPU check's to bound (benchmarks/pallas_check.py)
TAN_TOL = 1e-5
DIRS = [[0.0, 0.0, -1.0], [1.0, 0.0, -1.0]]


def _problem(name: str):
    if name == "chain":
        tree, scale = pallas_chain(), 5.0
        sim = make_simulator(tree, obs_dt=0.01, substeps=2, backend="fused")
    else:
        tree, scale = load_tree(example_path("three_branch")), 1.0
        sim = make_simulator(tree, obs_dt=0.01, backend="fused")  # its own substeps (4)
    rng = np.random.default_rng(0)
    kp, kd = default_true_params(tree, rng)
    mult = np.exp(0.3 * rng.normal(size=(2, 2, kp.size)))  # P = 2 particles near the truth
    kp, kd = kp[None] * mult[0], kd[None] * mult[1]
    forces = scale * profile_set("mixed", n=2, duration=T * 0.01, dt=0.01, seed=1)[:, :T]
    # relative tangents of the gains (a step in log K), as the likelihood's gradient takes them
    dkp = kp[None] * rng.normal(size=(K,) + kp.shape)
    dkd = kd[None] * rng.normal(size=(K,) + kd.shape)
    return sim, kp, kd, forces, dkp, dkd


# The three-branch tree runs under -m slow (about 75 s of interpreted kernels): its sensitivity
# layout stays in the default run through test_sensitivity_tangents_match_float64_central_
# differences (the independent reference), and the chain runs both pulls here.
@pytest.fixture(
    scope="module", params=["chain", pytest.param("three_branch", marks=pytest.mark.slow)]
)
def problem(request):
    return request.param, _problem(request.param)


def _f32(*xs):
    return tuple(jnp.asarray(x, jnp.float32) for x in xs)


def _fused_jvp(sim, kp, kd, forces, dkp, dkd, frac, dirs):
    """The fused backend's exact tangents of (tau, tau_dot) for each of the K directions (one
    direction per call: compiles faster than a vmap over them)."""

    @jax.jit
    def one(a, b):
        f = lambda p, d: simulate(sim, p, d, forces, grasp_fraction=frac, direction=dirs)
        _, t = jax.jvp(f, (kp, kd), (a, b))
        return t.tau, t.tau_dot

    outs = [one(a, b) for a, b in zip(dkp, dkd)]
    return tuple(jnp.stack(x) for x in zip(*outs))


def _kernel(fn, sim, **kw):
    """``fn`` (a :mod:`pk` entry point) on ``sim`` in the interpreter, jitted as a whole (the
    settle and layout too: faster than eager, and the persistent cache keeps it)."""
    return jax.jit(functools.partial(fn, sim, block=4, interpret=True, **kw))


def _scaled_max(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return float(np.abs(a - b).max()), float(np.abs(a - b).max() / np.abs(b).max())


@pytest.mark.parametrize("pull", ["gravity", "direction"])
def test_sensitivity_tangents_match_rows_and_the_fused_jvp(problem, pull):
    name, (sim, kp, kd, forces, dkp, dkd) = problem
    kp, kd, forces, dkp, dkd = _f32(kp, kd, forces, dkp, dkd)
    frac, dirs = (None, None) if pull == "gravity" else (jnp.asarray([0.5, 1.0]), DIRS)
    run = lambda layout: _kernel(pk.simulate_with_tangents, sim, layout=layout)(
        kp, kd, forces, dkp, dkd, frac, dirs
    )
    ro, tan = run("sensitivity")
    ro_rows, tan_rows = run("rows")
    ref_tau, ref_tau_dot = _fused_jvp(sim, kp, kd, forces, dkp, dkd, frac, dirs)
    assert bool(ro.stable.all())
    assert float(jnp.abs(ro.tau).max()) > 1e-4  # the pull moves the branch
    scale = float(jnp.abs(ref_tau).max())
    assert scale > 1e-4 and tan.tau.shape == (K,) + ro.tau.shape
    for got, ref in ((tan.tau, tan_rows.tau), (tan.tau, ref_tau)):
        np.testing.assert_allclose(got, ref, atol=TAN_TOL * scale, rtol=0)
    # tau_dot is a finite difference of tau over obs_dt: its rounding is tau's over obs_dt
    dot_tol = TAN_TOL * scale / sim.obs_dt
    np.testing.assert_allclose(tan.tau_dot, ref_tau_dot, atol=dot_tol, rtol=0)
    # the primal of the tangent kernel is the value-only kernel's, to rounding (XLA compiles
    # each kernel on its own; in the interpreter they measured equal or within 2 ulp)
    value = _kernel(pk.simulate, sim)(kp, kd, forces, frac, dirs)
    tau_tol = 1e-6 * float(jnp.abs(value.tau).max())
    for other in (value, ro_rows):
        np.testing.assert_allclose(ro.tau, other.tau, rtol=1e-6, atol=tau_tol)
        np.testing.assert_array_equal(ro.stable, other.stable)


def test_sensitivity_tangents_match_float64_central_differences():
    """Independent of autodiff and of the kernel: central differences of the fused backend's
    rollout in float64, against the sensitivity layout's tangents in float64."""
    sim, kp, kd, forces, dkp, dkd = _problem("three_branch")
    h = 1e-5
    with jax.enable_x64(True):
        kp, kd, forces, dkp, dkd = (jnp.asarray(x, jnp.float64) for x in (kp, kd, forces, dkp, dkd))
        frac, dirs = jnp.asarray([0.5, 1.0], jnp.float64), jnp.asarray(DIRS, jnp.float64)
        run = _kernel(pk.simulate_with_tangents, sim, layout="sensitivity")
        ro, tan = run(kp, kd, forces, dkp, dkd, frac, dirs)
        assert tan.tau.dtype == jnp.float64

        @jax.jit
        def fd(a, b):
            tau = lambda s: simulate(sim, kp + s * a, kd + s * b, forces, frac, direction=dirs).tau
            return (tau(h) - tau(-h)) / (2 * h)

        ref = np.stack([np.asarray(fd(dkp[i], dkd[i])) for i in range(K)])
    assert bool(ro.stable.all())
    scale = float(np.abs(ref).max())
    # float64 FD error at h = 1e-5 (a relative step of the gains): ~h^2 |tau'''| + eps / h, a
    # few 1e-10 of the scale; measured ~1e-9
    np.testing.assert_allclose(tan.tau, ref, atol=1e-7 * scale, rtol=0)


def test_the_custom_jvp_runs_the_configured_layout(monkeypatch):
    """``jax.jvp`` of :func:`pk.simulate` (the likelihood's route) under
    ``TANGENT_LAYOUT = "sensitivity"`` runs the sensitivity kernel and matches the fused JVP."""
    sim, kp, kd, forces, dkp, dkd = _problem("chain")
    kp, kd, forces, dkp, dkd = _f32(kp, kd, forces, dkp, dkd)
    monkeypatch.setattr(pk, "TANGENT_LAYOUT", "sensitivity")
    monkeypatch.setattr(pk, "DEFAULT_BLOCK", 4)
    rules, real = [], pk._rollout_rows

    def spy(*args, **kw):
        rules.append(kw.get("rule", "linearize"))
        return real(*args, **kw)

    monkeypatch.setattr(pk, "_rollout_rows", spy)
    f = lambda p, d: pk.simulate(sim, p, d, forces, interpret=True).tau
    _, got = jax.jvp(f, (kp, kd), (dkp[0], dkd[0]))
    assert rules == ["sensitivity"]
    ref, _ = _fused_jvp(sim, kp, kd, forces, dkp[:1], dkd[:1], None, None)
    np.testing.assert_allclose(got, ref[0], atol=TAN_TOL * float(jnp.abs(ref).max()), rtol=0)
    with pytest.raises(ValueError, match="rows, lanes, sensitivity"):
        pk.simulate_with_tangents(sim, kp, kd, forces, dkp, dkd, layout="columns")


def test_the_layout_environment_variable_is_validated(monkeypatch):
    from treeinfer.errors import ConfigError

    name = "TREEINFER_PALLAS_TANGENT_LAYOUT"
    monkeypatch.delenv(name, raising=False)
    assert pk._tangent_layout(name) == "rows"  # the default until timed on a GPU
    assert pk.TANGENT_LAYOUT in pk.TANGENT_LAYOUTS
    for value in ("rows", "lanes", "sensitivity", " Sensitivity "):
        monkeypatch.setenv(name, value)
        assert pk._tangent_layout(name) == value.strip().lower()
    monkeypatch.setenv(name, "")
    assert pk._tangent_layout(name) == "rows"
    monkeypatch.setenv(name, "columns")
    with pytest.raises(ConfigError, match=f"{name}: expected one of rows, lanes, sensitivity"):
        pk._tangent_layout(name)
