"""Sampler programs that take the data as an argument (issue 15 item 4): the padded, masked
target equals the unpadded one, and a second data set of one shape bucket reuses the compiled
sampler program."""

from __future__ import annotations

import logging

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from treeinfer.data.trajectories import Trajectory, stack_trajectories
from treeinfer.inference.problem import infer, make_problem
from treeinfer.sim import make_simulator
from treeinfer.sim.program_cache import ProgramCache
from treeinfer.tree.generators import chain


def _tree():
    return chain(1, lengths=0.7, radii=0.03, angles_deg=0.0, base_position=(0.0, 0.0, 1.5),
                 base_pitch_deg=20.0, levels=1, name="c1")  # fmt: skip


def _obs(lengths, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for i, n in enumerate(lengths):  # ragged: stacking masks the shorter rows already
        t = np.arange(n) * 0.01
        f = (5.0 + i) * np.clip(t / 0.1, 0, 1) * (t < 0.3)
        x = 0.01 * f / 5.0 + 1e-3 * rng.normal(size=n)
        out.append(Trajectory(t, f, x, None, f"p{i}"))
    return stack_trajectories(out)


THETA = np.log([[40.0, 0.6], [25.0, 1.5], [70.0, 0.2]])


@pytest.mark.parametrize(
    "case",
    [
        {"likelihood": "boltzmann", "kT": 0.05},
        {"likelihood": "boltzmann", "kT": 0.05, "grasp_fraction": [0.8, 0.9]},
        {"likelihood": "gaussian", "noise_displacement": 1e-3},
        {"likelihood": "gaussian", "noise_displacement": None},  # sigma_x inferred: 3 columns
        {"likelihood": "student_t", "noise_displacement": 1e-3},
        {"likelihood": "boltzmann", "kT": 0.05, "gradient": "jvp"},
    ],
    ids=[
        "boltzmann",
        "boltzmann-grasp-per-pull",
        "gaussian",
        "gaussian-sigma-inferred",
        "student-t",
        "boltzmann-jvp",
    ],  # fmt: skip
)
def test_padded_data_argument_equals_unpadded_target(case):
    """The sampler's target on the padded data, passed as a jitted program's argument, equals
    the unpadded problem's (built with constants, the path of ``--shape-buckets off``)."""
    tree, obs = _tree(), _obs((50, 57))
    sim = make_simulator(tree, obs_dt=0.01, substeps=2)
    kw = {"sim": sim, "nn_prior": False, **case}
    plain = make_problem(tree, obs, **kw)
    bucketed = make_problem(tree, obs, shape_bucket=(3, 80), **kw)  # a padded row and 23 steps
    assert plain.data_target is None and "shape_bucket" not in plain.settings
    dt = bucketed.data_target
    assert dt.shape == (3, 80) and bucketed.settings["shape_bucket"] == [3, 80]
    assert np.shape(dt.data["force"]) == (3, 80) and int(np.sum(dt.data["mask"])) == 107
    theta = np.asarray(THETA, np.float32)
    if plain.dim == 3:  # the log sigma_x column
        theta = np.concatenate([theta, np.log([[8e-4], [1e-3], [2e-3]])], 1).astype(np.float32)
    theta = jnp.asarray(theta)

    @jax.jit
    def padded(theta, data):  # the data are an argument here, not constants
        vg, ld = dt.target(data)
        return vg(theta), ld(theta)

    (v, g), ld = padded(theta, dt.data)
    v0, g0 = jax.jit(plain.value_and_grad)(theta)
    ld0 = jax.jit(plain.log_density)(theta)
    # Boltzmann: the simulated velocity at the longest row's last real sample moves by ~2e-6
    # relative once a next step exists (tests/test_startup.py); Gaussian: float32 rounding
    rtol = 1e-5 if case["likelihood"] == "boltzmann" else 2e-6
    np.testing.assert_allclose(np.asarray(v), np.asarray(v0), rtol=rtol)
    np.testing.assert_allclose(np.asarray(ld), np.asarray(ld0), rtol=rtol)
    # the likelihood is not flat here: the comparison below can fail
    assert np.ptp(np.asarray(v0)) > 1.0 and np.all(np.isfinite(np.asarray(g0)))
    # central differences of a float32 log density: rounding noise ~ eps * |log p| / h
    atol = 1e-3 * float(np.max(np.abs(np.asarray(v0)))) + 1e-3
    np.testing.assert_allclose(np.asarray(g), np.asarray(g0), rtol=1e-3, atol=atol)


@pytest.mark.parametrize("term", ["velocity", "force_noise"])
def test_velocity_and_force_noise_terms_padded_equal_unpadded(term):
    """The generative likelihood with the velocity term on (``sigma_v``, only through
    ``likelihood_terms``) and with the force-noise term (its basis, computed on the padded
    pulls, is data too); the force Jacobian's reference is given (no MAP fit: a fast test)."""
    from treeinfer.model.likelihood import likelihood_terms

    tree, obs = _tree(), _obs((50, 57))
    sim = make_simulator(tree, obs_dt=0.01, substeps=2)
    if term == "velocity":
        kw = {"sigma_v": 0.05}
    else:
        kw = {"noise_force": 0.3, "force_noise_reference": np.log([40.0, 0.6])}
    terms = likelihood_terms(sim, obs, "gaussian", sigma_x=1e-3, **kw)
    theta = jnp.asarray(THETA, jnp.float32)
    data = terms.data_of(obs, (3, 80))
    if term == "force_noise":
        assert np.shape(data["force_basis"].values) == (3, 80)
    v = jax.jit(lambda th, d: terms.loglik_of(d)(th))(theta, data)
    v0 = jax.jit(terms.log_likelihood)(theta)
    without = jax.jit(likelihood_terms(sim, obs, "gaussian", sigma_x=1e-3).log_likelihood)(theta)
    assert np.all(np.abs(np.asarray(v0) - np.asarray(without)) > 1.0)  # the term counts
    rtol = 2e-6 if term == "velocity" else 1e-5  # an eigenbasis of T' = 80 instead of 57
    np.testing.assert_allclose(np.asarray(v), np.asarray(v0), rtol=rtol)
    g = jax.jit(jax.grad(lambda th, d: jnp.sum(terms.loglik_of(d)(th))))(theta, data)
    g0 = jax.jit(jax.grad(lambda th: jnp.sum(terms.log_likelihood(th))))(theta)
    np.testing.assert_allclose(np.asarray(g), np.asarray(g0), rtol=1e-3, atol=1e-3 * np.ptp(v0))


class _Compiles(logging.Handler):
    """Counts XLA compilations of the sampler chunk (``jax_log_compiles``)."""

    def __init__(self):
        super().__init__(logging.DEBUG)
        self.names = []

    def emit(self, record):
        msg = record.getMessage()
        if "Finished XLA compilation of" in msg:
            self.names.append(msg.split("Finished XLA compilation of ")[1].split(" ")[0])


def test_two_data_sets_of_one_bucket_compile_the_sampler_once():
    """(b) two data sets of one bucket: one compile of the sampler's chunk, the second run a
    ProgramCache hit; (c) a data set of another bucket compiles again. Each run still samples
    its own data: the same seed gives other particles on other data."""
    tree = _tree()
    sim = make_simulator(tree, obs_dt=0.01, substeps=2)
    programs = ProgramCache()
    handler = _Compiles()
    logger = logging.getLogger("jax")
    logger.addHandler(handler)
    old_level = logger.level
    logger.setLevel(logging.DEBUG)
    jax.config.update("jax_log_compiles", True)
    finals = []
    try:
        for lengths, bucket in (((50, 57), (2, 64)), ((60, 44), (2, 64)), ((50, 70), (2, 80))):
            problem = make_problem(
                tree, _obs(lengths), sim=sim, kT=0.05, shape_bucket=bucket, likelihood="boltzmann"
            )
            post = infer(problem, "nnsvgd", n_particles=4, n_iterations=2, seed=0,
                         progress=False, trace_every=None, cache=programs)  # fmt: skip
            finals.append(post.theta)
    finally:
        jax.config.update("jax_log_compiles", False)
        logger.removeHandler(handler)
        logger.setLevel(old_level)
    chunks = [n for n in handler.names if n == "jit(chunk)"]
    assert len(chunks) == 2, handler.names  # the first bucket once, the second once
    keys = [k for k in programs._programs if k[0] == "sampler chunk, data argument"]
    assert len(keys) == 2
    assert not np.allclose(finals[0], finals[1])  # the second run sampled its own data


@pytest.mark.parametrize("sampler", ["sgld", "mh"])
def test_mcmc_samplers_on_the_data_argument_match_the_constant_path(sampler):
    """SGLD (Adam-preconditioned) and MH (its proposal scale is a host array recorded in the
    settings) built on the data argument: the same chains as with the data as constants, to
    float rounding (a padded row of 7 steps here)."""
    from treeinfer.inference.samplers import DataSamplingAlgorithm

    tree, obs = _tree(), _obs((50, 57))
    sim = make_simulator(tree, obs_dt=0.01, substeps=2)
    kw = {"sim": sim, "kT": 0.05, "nn_prior": False, "likelihood": "boltzmann"}
    a = make_problem(tree, obs, shape_bucket=(2, 64), **kw)
    b = make_problem(tree, obs, **kw)
    assert isinstance(a.data_sampler(sampler), DataSamplingAlgorithm)
    assert b.data_sampler(sampler) is None
    run = {"n_particles": 4, "n_iterations": 3, "progress": False, "trace_every": None}
    pa, pb = infer(a, sampler, **run), infer(b, sampler, **run)
    assert pa.settings["sampler_options"] == pb.settings["sampler_options"]
    np.testing.assert_allclose(pa.theta, pb.theta, atol=1e-5)
    np.testing.assert_allclose(pa.log_density, pb.log_density, rtol=1e-5)
