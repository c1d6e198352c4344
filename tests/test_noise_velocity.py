"""``--noise-velocity``: the velocity term of a generative likelihood with its own sigma (issue
11, section 1: "the velocity term optional (off by default ...) or with its own sigma"), from
``make_problem`` and the command line, checked against scipy."""

from __future__ import annotations

import contextlib
import io
import json

import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats
from test_crb import KD, KP, two_branch_pulls

from treeinfer.cli import main
from treeinfer.data.trajectories import Trajectory, write_trajectory
from treeinfer.errors import ConfigError
from treeinfer.examples import example_path
from treeinfer.inference.problem import make_problem
from treeinfer.runs.config import RunConfig
from treeinfer.sim import simulate

SX, SV = 0.002, 0.05  # m, m/s


@pytest.fixture(scope="module")
def setup():
    """The two pulls of ``test_crb.two_branch_pulls`` with white displacement and velocity
    noise: ``(tree, sim, trajectories)``."""
    tree, sim, t, forces, roll = two_branch_pulls()
    rng = np.random.default_rng(3)
    trajs = []
    for b in range(2):
        x = np.asarray(roll.tau[0, b], float) + SX * rng.standard_normal(t.size)
        v = np.asarray(roll.tau_dot[0, b], float) + SV * rng.standard_normal(t.size)
        trajs.append(Trajectory(t, forces[b], x, v, f"p{b}.csv"))
    return tree, sim, trajs


def _problem(setup, **kw):
    tree, sim, trajs = setup
    return make_problem(
        tree, trajs, sim=sim, nn_prior=False, likelihood="gaussian", noise_displacement=SX, **kw
    )


def test_velocity_term_adds_the_scipy_velocity_density(setup):
    _, sim, trajs = setup
    off, on = _problem(setup), _problem(setup, noise_velocity=SV)
    assert off.settings["noise_velocity"] is None and on.settings["noise_velocity"] == SV
    theta = np.log(np.array([[*KP, *KD], [*(KP * 1.3), *(KD * 0.7)]]))
    diff = np.asarray(on.log_density(jnp.asarray(theta))) - np.asarray(
        off.log_density(jnp.asarray(theta))
    )
    forces = jnp.asarray(np.stack([t.force for t in trajs]))
    roll = simulate(sim, jnp.exp(theta[:, :2]), jnp.exp(theta[:, 2:]), forces)
    v_obs = np.stack([t.velocity for t in trajs])
    want = stats.norm.logpdf(v_obs[None] - np.asarray(roll.tau_dot), 0.0, SV).sum(axis=(1, 2))
    np.testing.assert_allclose(diff, want, rtol=1e-4, atol=1e-2)
    # and the term has a gradient: the velocity residual moves the damping
    g_on = np.asarray(on.value_and_grad(jnp.asarray(theta))[1])
    g_off = np.asarray(off.value_and_grad(jnp.asarray(theta))[1])
    assert np.all(np.isfinite(g_on)) and not np.allclose(g_on, g_off)


@pytest.mark.parametrize(
    "kw, fragment",
    [
        ({"noise_velocity": -0.1}, "noise_velocity"),
        ({"noise_velocity": float("nan")}, "noise_velocity"),
        ({"noise_velocity": 1e6}, "larger than the whole range"),
        ({"noise_velocity": SV, "likelihood": "boltzmann"}, "--noise-velocity"),
    ],
)
def test_bad_values_name_the_option(setup, kw, fragment):
    tree, sim, trajs = setup
    kw = {"likelihood": "gaussian", **kw}
    with pytest.raises(ConfigError, match=fragment):
        make_problem(tree, trajs, sim=sim, nn_prior=False, **kw)


def test_run_config_validates_and_round_trips():
    base = dict(tree="t", data="d", out="o")
    with pytest.raises(ConfigError, match="--noise-velocity"):
        RunConfig(**base, likelihood="boltzmann", noise_velocity=0.05)
    with pytest.raises(ConfigError, match="--noise-velocity"):
        RunConfig(**base, likelihood="gaussian", noise_velocity=0.0)
    with pytest.raises(ConfigError, match="--noise-velocity"):
        RunConfig(**base, likelihood="gaussian", noise_force="2%", noise_velocity=0.05)
    cfg = RunConfig(**base, likelihood="gaussian", noise_velocity=0.05)
    assert cfg.options_json()["noise_velocity"] == 0.05
    assert RunConfig.from_json(cfg.to_json()).noise_velocity == 0.05
    # off: config.json keeps the layout it had before the option existed
    assert "noise_velocity" not in RunConfig(**base, likelihood="gaussian").options_json()


def _main(*argv):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main([str(a) for a in argv])
    return rc, out.getvalue() + err.getvalue()


def test_cli_run_records_the_velocity_term(setup, tmp_path):
    _, _, trajs = setup
    data = tmp_path / "data"
    data.mkdir()
    for t in trajs:
        write_trajectory(data / t.source, t)
    common = ["infer", "--tree", example_path("two_branch"), "--data", data]
    quick = ["--particles", "4", "--iterations", "2", "--checkpoint-every", "0", "--no-progress"]
    rc, text = _main(
        *common, "--out", tmp_path / "bad", "--likelihood", "boltzmann", "--noise-velocity", "0.05",
        *quick,
    )  # fmt: skip
    assert rc == 2 and "--noise-velocity" in text and "Traceback" not in text, text
    rc, text = _main(
        *common,
        "--out",
        tmp_path / "run",
        "--likelihood",
        "gaussian",
        "--noise-velocity",
        "0.05",
        "--allow-poor-fit",
        *quick,
    )
    assert rc == 0, text
    assert "velocity noise 0.05 m/s" in text
    cfg = json.loads((tmp_path / "run" / "config.json").read_text())
    assert cfg["options"]["noise_velocity"] == 0.05 and cfg["problem"]["noise_velocity"] == 0.05
