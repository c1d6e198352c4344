"""Samplers and the run driver on an analytic 2-D correlated Gaussian.

The gradient samplers get the finite-difference gradient (central_difference)
of the analytic log-density, as they will get the simulator likelihood's.
"""

import json

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from scipy.spatial.distance import pdist

from treeinfer.errors import ConfigError
from treeinfer.inference.samplers import (
    SAMPLERS,
    make_sampler,
    median_length_scale,
    run,
    sghmc,
    sgld,
    stein_direction,
    svgd,
)
from treeinfer.model.gradients import central_difference
from treeinfer.sim.program_cache import ProgramCache

MU = np.array([1.0, -0.5])
SD = np.array([1.0, 0.5])
RHO = 0.8
COV = np.array([[SD[0] ** 2, RHO * SD[0] * SD[1]], [RHO * SD[0] * SD[1], SD[1] ** 2]])
PREC = jnp.asarray(np.linalg.inv(COV), jnp.float32)


def logp(theta):
    d = theta - jnp.asarray(MU, theta.dtype)
    return -0.5 * jnp.einsum("pi,ij,pj->p", d, PREC.astype(theta.dtype), d)


VG = central_difference(logp)

# Hyperparameters per sampler for the Gaussian test, and particle counts.
CONFIGS = {
    "svgd": ({"value_and_grad_fn": VG, "learning_rate": 0.05}, 128, 300),
    "nnsvgd": ({"value_and_grad_fn": VG, "learning_rate": 0.05}, 128, 300),
    "sgld": ({"value_and_grad_fn": VG, "step_size": 0.02}, 1000, 500),
    "sghmc": ({"value_and_grad_fn": VG, "step_size": 0.02, "alpha": 1.5}, 1000, 500),
    "mh": ({"logdensity_fn": logp, "proposal_scale": [0.8, 0.4]}, 1000, 500),
}


def start(n, seed=1):
    """Initial particles away from the target: N((-1, 1), 0.5^2 I)."""
    return jax.random.normal(jax.random.key(seed), (n, 2)) * 0.5 + jnp.array([-1.0, 1.0])


@pytest.mark.parametrize("name", list(CONFIGS))
def test_recovers_correlated_gaussian(name):
    kwargs, n, iters = CONFIGS[name]
    result = run(make_sampler(name, **kwargs), 0, start(n), iters, progress=False, trace_every=None)
    x = result.final_positions
    assert np.all(np.isfinite(x))
    # Tolerance: mean within 0.15 sd per coordinate; covariance entries within
    # 0.2 * sd_i * sd_j (20% of the variances, 25% of the covariance 0.4*...).
    np.testing.assert_array_less(np.abs(x.mean(0) - MU) / SD, 0.15)
    np.testing.assert_array_less(np.abs(np.cov(x.T) - COV) / np.outer(SD, SD), 0.2)
    assert result.settings["sampler"] == name
    assert len(result.diagnostics["mean_logdensity"]) == iters


@pytest.mark.parametrize("name", ["svgd", "sgld", "sghmc", "mh"])
def test_fixed_seed_reproducible_and_resume_equals_uninterrupted(name):
    kwargs, _, _ = CONFIGS[name]
    alg = make_sampler(name, **kwargs)
    key = jax.random.key(7)
    full = run(alg, key, start(32), 60, progress=False, trace_every=5, chunk_size=20)

    # a fixed seed gives bit-identical particles (fresh algorithm object, same key)
    again = run(make_sampler(name, **kwargs), key, start(32), 60, progress=False, trace_every=5)
    np.testing.assert_array_equal(again.trace_positions, full.trace_positions)
    if name != "svgd":  # stochastic samplers: another key differs
        other = run(alg, jax.random.key(8), start(32), 60, progress=False, chunk_size=20)
        assert not np.array_equal(other.final_positions, full.final_positions)

    saved = {}
    first = run(
        alg,
        key,
        start(32),
        40,
        progress=False,
        trace_every=5,
        chunk_size=20,
        callback=lambda it, state: saved.__setitem__(it, state),
        callback_every=20,
    )
    assert sorted(saved) == [20, 40]
    # resume from the checkpoint at 20 with a chunk size that does not align with it
    rest = run(
        alg,
        key,
        None,
        60,
        progress=False,
        trace_every=5,
        chunk_size=15,
        initial_state=saved[20],
        start_iteration=20,
    )
    np.testing.assert_array_equal(rest.final_positions, full.final_positions)
    jax.tree.map(np.testing.assert_array_equal, rest.final_state, full.final_state)
    # traces line up: first part up to 20 + resumed part == uninterrupted
    head = first.trace_iterations <= 20
    np.testing.assert_array_equal(
        np.concatenate([first.trace_iterations[head], rest.trace_iterations]), full.trace_iterations
    )
    np.testing.assert_array_equal(
        np.concatenate([first.trace_positions[head], rest.trace_positions]), full.trace_positions
    )
    np.testing.assert_array_equal(
        rest.diagnostics["mean_logdensity"], full.diagnostics["mean_logdensity"][20:]
    )


def test_one_batched_evaluation_per_step():
    calls = []

    def counted(theta):
        calls.append(theta.shape)  # Python side effect: runs when traced, not when executed
        return logp(theta)

    vg = central_difference(counted)
    for name in SAMPLERS:
        calls.clear()
        fn = {"logdensity_fn": counted} if name == "mh" else {"value_and_grad_fn": vg}
        extra = {"proposal_scale": 0.5} if name == "mh" else {}
        alg = make_sampler(name, **fn, **extra)
        state = jax.jit(alg.init)(jax.random.key(0), start(8))
        step = jax.jit(alg.step)
        for i in range(3):
            state, _ = step(jax.random.key(i), state)
        assert len(calls) == 2, name  # one trace for init + one for step, executed 3 times
        expected = (8 * 5, 2) if name != "mh" else (8, 2)  # FD stacks P * (2D + 1) rows
        assert calls[-1] == expected, name

        if name != "mh":  # the driver is generic: one sampler suffices
            continue
        # a whole run traces the target a fixed number of times, however long
        for n_iter in (10, 25):
            calls.clear()
            alg = make_sampler(name, **fn, **extra)  # fresh closures: no compilation cache hits
            run(alg, 0, start(8), n_iter, progress=False, chunk_size=10)
            # shape inference of init and of step + one compiled chunk (init folded into it)
            assert len(calls) == 3 + 1, name


def test_a_fresh_run_compiles_one_program():
    """``init`` is folded into the chunk: a fresh run (and its resumption) compiles exactly one
    XLA program, counted from JAX's compile events (persistent cache off, so every program the
    run needs is compiled here and counted)."""
    from jax._src import dispatch

    compiled = []

    def listener(event, duration, **kw):
        if event == dispatch.BACKEND_COMPILE_EVENT:
            compiled.append(kw.get("fun_name"))

    before = jax.config.jax_enable_compilation_cache
    jax.config.update("jax_enable_compilation_cache", False)
    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        run(svgd(VG, learning_rate=0.05), 0, start(8), 12, progress=False, chunk_size=4)
        compiled.clear()  # the run above compiled the small eager helpers of these shapes
        alg = svgd(VG, learning_rate=0.05)  # new closures: nothing of it is compiled yet
        cache = ProgramCache()  # the caller's: the resumed run below finds the program here
        full = run(alg, 1, start(8), 12, progress=False, chunk_size=4, cache=cache)
        assert compiled == ["jit(chunk)"], compiled
        part = run(alg, 1, start(8), 4, progress=False, chunk_size=4, cache=cache)
        rest = run(
            alg,
            1,
            None,
            12,
            initial_state=part.final_state,
            start_iteration=4,
            chunk_size=4,
            progress=False,
            cache=cache,
        )
        assert compiled == ["jit(chunk)"], compiled  # same shapes: the resumed run reuses it
        assert cache.builds == 1 and len(cache) == 1
        np.testing.assert_array_equal(rest.final_positions, full.final_positions)
        assert full.trace_iterations[0] == 0
        np.testing.assert_array_equal(full.trace_positions[0], np.asarray(start(8)))
        init_state = jax.jit(alg.init)(jax.random.key(0), start(8))
        np.testing.assert_allclose(
            full.trace_logdensity[0], np.asarray(init_state.logdensity), rtol=1e-6
        )
    finally:
        jax.monitoring.clear_event_listeners()
        jax.config.update("jax_enable_compilation_cache", before)


def test_compiled_programs_live_in_the_callers_cache_only():
    """Two runs of one algorithm share a compiled chunk only through a ProgramCache the caller
    owns: without one, every run compiles its own (nothing is kept in a module); with one,
    the second run compiles nothing and equals the first."""
    from jax._src import dispatch

    compiled = []

    def listener(event, duration, **kw):
        if event == dispatch.BACKEND_COMPILE_EVENT and kw.get("fun_name") == "jit(chunk)":
            compiled.append(1)

    before = jax.config.jax_enable_compilation_cache
    jax.config.update("jax_enable_compilation_cache", False)
    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        alg = svgd(VG, learning_rate=0.05)
        run(alg, 0, start(8), 6, progress=False, chunk_size=3)
        run(alg, 0, start(8), 6, progress=False, chunk_size=3)
        assert len(compiled) == 2  # no cache given: a program per run, none kept
        compiled.clear()
        cache = ProgramCache(max_size=2)
        a = run(alg, 0, start(8), 6, progress=False, chunk_size=3, cache=cache)
        b = run(alg, 0, start(8, seed=2), 6, progress=False, chunk_size=3, cache=cache)
        assert len(compiled) == 1 and cache.builds == 1
        np.testing.assert_array_equal(
            a.final_positions,
            run(alg, 0, start(8), 6, progress=False, chunk_size=3).final_positions,
        )
        assert not np.allclose(a.final_positions, b.final_positions)  # other data, same program
        run(alg, 0, start(16), 6, progress=False, chunk_size=3, cache=cache)  # new shapes
        run(alg, 0, start(8), 2, progress=False, chunk_size=3, cache=cache)  # shorter chunk
        assert len(cache) == 2 and cache.builds == 3  # the oldest entry was dropped
    finally:
        jax.monitoring.clear_event_listeners()
        jax.config.update("jax_enable_compilation_cache", before)
    with pytest.raises(ConfigError, match="ProgramCache"):
        run(alg, 0, start(8), 3, progress=False, cache={})


def test_svgd_warmup_ramps_the_learning_rate():
    """``warmup=W``: Adam's step sizes ramp linearly from lr / 20 to lr over W iterations
    (optax.linear_schedule), so the first move from a good start is 20x smaller."""
    x0 = start(16)
    moves = {}
    for w in (0, 10):
        r = run(svgd(VG, learning_rate=0.1, warmup=w), 0, x0, 1, progress=False)
        moves[w] = np.abs(np.asarray(r.final_positions) - np.asarray(x0)).max()
    # Adam's first update is lr * sign(g) (bias-corrected m / sqrt(v)), up to its epsilon
    np.testing.assert_allclose(moves[0], 0.1, rtol=1e-3)
    np.testing.assert_allclose(moves[10], 0.1 / 20, rtol=1e-3)
    alg = svgd(VG, learning_rate=0.1, warmup=10)
    assert alg.settings["warmup"] == 10 and "warmup" not in svgd(VG).settings
    with pytest.raises(ConfigError):
        svgd(VG, warmup=-1)
    with pytest.raises(ConfigError):
        svgd(VG, warmup=3, optimizer=optax.sgd(0.1))


def test_collapsed_and_single_particles_do_not_nan():
    same = jnp.ones((50, 2))
    assert float(median_length_scale(same)) == pytest.approx(1e-6)
    assert float(median_length_scale(same[:1])) == 1.0
    alg = svgd(VG, learning_rate=0.05)  # one object and one cache: compiled chunks are reused
    programs = ProgramCache()
    for positions in (same, same[:1]):
        r = run(alg, 0, positions, 100, progress=False, cache=programs)
        assert np.all(np.isfinite(r.final_positions))
        assert np.all(np.isfinite(r.diagnostics["bandwidth"]))
        assert np.all(r.diagnostics["bandwidth"] > 0)
    # single particle: SVGD is gradient ascent -> moves to the mode
    r = run(alg, 0, jnp.zeros((1, 2)), 300, progress=False, cache=programs)
    np.testing.assert_allclose(r.final_positions[0], MU, atol=0.05)
    # nearly collapsed (distinct) particles spread out again; exactly identical
    # ones cannot (SVGD is deterministic and treats them identically)
    nearly = same + 1e-4 * jax.random.normal(jax.random.key(2), same.shape)
    r = run(alg, 0, nearly, 200, progress=False, cache=programs)
    assert np.std(r.final_positions[:, 0]) > 0.3


def test_nonfinite_target_region_does_not_leak():
    # log p = -inf for theta_0 > 2.5 (e.g. unstable simulations there)
    def cut(theta):
        return jnp.where(theta[:, 0] > 2.5, -jnp.inf, logp(theta))

    vg = central_difference(cut)
    x0 = start(64).at[:8, 0].set(3.0)
    for alg in (
        svgd(vg, learning_rate=0.05),
        sgld(vg, step_size=0.02),
        sghmc(vg, step_size=0.02),
        make_sampler("mh", logdensity_fn=cut, proposal_scale=0.3),
    ):
        r = run(alg, 0, x0, 50, progress=False, trace_every=None)
        assert np.all(np.isfinite(r.final_positions)), alg.name
        assert np.all(
            np.isfinite(np.asarray(r.final_state.logdensity))
            | (np.asarray(r.final_state.logdensity) == -np.inf)
        )
        assert np.isfinite(r.diagnostics["mean_logdensity"]).all(), alg.name


def test_stein_direction_matches_closed_form():
    x = jax.random.normal(jax.random.key(0), (30, 3))
    g = -x
    h = 0.7
    xn, gn = np.asarray(x, np.float64), np.asarray(g, np.float64)
    diff = xn[:, None, :] - xn[None, :, :]  # x_i - x_j
    k = np.exp(-np.sum(diff**2, -1) / h)
    # phi_i = 1/n sum_j k(x_j, x_i) g_j + d/dx_j k(x_j, x_i) = ... + 2/h (x_i - x_j) k
    ref = (k @ gn + 2.0 / h * np.einsum("ij,ijd->id", k, diff)) / 30
    np.testing.assert_allclose(stein_direction(x, g, h), ref, rtol=1e-4, atol=1e-5)


def test_svgd_bandwidth_is_median_heuristic_of_current_particles():
    x0 = start(40)
    alg = svgd(VG, learning_rate=0.05)
    state = alg.init(None, x0)
    _, info = alg.step(None, state)  # first step already uses the heuristic (not h = 1)
    expected = np.median(pdist(np.asarray(x0, np.float64))) ** 2 / np.log(40)
    assert float(info.bandwidth) == pytest.approx(expected, rel=1e-4)
    # fixed length scale and plain SGD: x += lr * phi
    alg = svgd(VG, optimizer=optax.sgd(0.1), length_scale=0.5)
    state = alg.init(None, x0)
    new, info = alg.step(None, state)
    phi = stein_direction(x0, state.logdensity_grad, 0.5)
    np.testing.assert_allclose(new.position, x0 + 0.1 * phi, rtol=1e-5, atol=1e-6)
    assert float(info.bandwidth) == 0.5


def test_sgld_schedule_and_temperature_zero():
    schedule = optax.exponential_decay(0.05, transition_steps=10, decay_rate=0.5)
    r = run(sgld(VG, step_size=schedule), 0, start(16), 20, progress=False)
    np.testing.assert_allclose(
        r.diagnostics["step_size"], [schedule(i) for i in range(20)], rtol=1e-6
    )
    # T = 0 is noiseless gradient ascent: converges to the mode
    r = run(sgld(VG, step_size=0.05, temperature=0.0), 0, start(16), 400, progress=False)
    np.testing.assert_allclose(r.final_positions, np.tile(MU, (16, 1)), atol=1e-2)
    # the Adam-guided variant runs and stays finite
    r = run(sgld(VG, step_size=0.01, optimizer=optax.adam(0.01)), 0, start(16), 50, progress=False)
    assert np.all(np.isfinite(r.final_positions))


def test_sghmc_noise_guard():
    with pytest.raises(ConfigError, match="beta"):
        sghmc(VG, step_size=0.1, alpha=1.0, beta=30.0)
    with pytest.raises(ConfigError, match="alpha"):
        sghmc(VG, step_size=0.5, alpha=3.0)
    # a schedule that would make the noise imaginary is clipped, not NaN
    alg = sghmc(VG, step_size=lambda t: 0.01 + 0.01 * t, alpha=1.0, beta=50.0)
    r = run(alg, 0, start(16), 10, progress=False)
    assert np.all(np.isfinite(r.final_positions))


def test_run_outputs_and_settings():
    kwargs, _, _ = CONFIGS["mh"]
    r = run(
        make_sampler("mh", **kwargs), 5, start(20), 23, progress=False, trace_every=5, chunk_size=10
    )
    np.testing.assert_array_equal(r.trace_iterations, [0, 5, 10, 15, 20])
    assert r.trace_positions.shape == (5, 20, 2) and r.trace_logdensity.shape == (5, 20)
    np.testing.assert_array_equal(r.trace_positions[0], start(20))
    np.testing.assert_allclose(
        r.trace_logdensity[-1], logp(jnp.asarray(r.trace_positions[-1])), rtol=1e-5
    )
    s = r.settings
    assert s["sampler"] == "mh" and s["seed"] == 5 and s["n_iterations"] == 23
    assert s["hyperparameters"] == {"proposal_scale": [0.8, 0.4]}
    assert json.loads(json.dumps(s)) == s  # plain JSON-able record
    assert 0.1 < r.diagnostics["mean_acceptance_rate"].mean() < 0.9
    with pytest.raises(ConfigError):
        run(make_sampler("mh", **kwargs), 0, None, 10, progress=False)
    with pytest.raises(ConfigError):
        run(make_sampler("mh", **kwargs), 0, start(4), 10, progress=False, start_iteration=3)
    with pytest.raises(ConfigError):
        run(
            make_sampler("mh", **kwargs),
            0,
            start(4),
            10,
            progress=False,
            callback=print,
            callback_every=15,
            chunk_size=10,
        )


def test_make_sampler_errors():
    with pytest.raises(ConfigError, match="unknown sampler"):
        make_sampler("hmc", value_and_grad_fn=VG)
    with pytest.raises(ConfigError, match="needs logdensity_fn"):
        make_sampler("mh", proposal_scale=0.1)
    with pytest.raises(ConfigError, match="needs value_and_grad_fn"):
        make_sampler("svgd")
    with pytest.raises(ConfigError, match="svgd"):
        make_sampler("svgd", value_and_grad_fn=VG, step_size=0.1)
    with pytest.raises(ConfigError):
        make_sampler("sgld", value_and_grad_fn=VG, step_size=-1.0)
    with pytest.raises(ConfigError):
        make_sampler("mh", logdensity_fn=logp, proposal_scale=[0.1, 0.0])
    assert make_sampler("nnsvgd", value_and_grad_fn=VG).name == "nnsvgd"
