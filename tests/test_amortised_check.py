"""The amortised posterior's check against the real simulator-based posterior (issue 31 §2):
on recordings drawn from the training distribution the checked answer is used (no fallback),
and is the simulator's posterior (its mean against the truth); on recordings outside it (a
force ten times the trained peaks, a displacement that lags the force by a logger's delay)
the start gives no posterior and the run falls back, saying why.

A small model (1 joint, 2 pulls of 0.5 s, 1024 simulations) and real problems
(``make_problem``: the run's likelihood with the force-noise term, priors); about a minute on
a 2-core CPU (slow)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("flowjax")

from treeinfer.amortised import check, estimator  # noqa: E402
from treeinfer.amortised.config import AmortiseConfig, PullLayout, TrainConfig  # noqa: E402
from treeinfer.amortised.simulations import draw_profiles  # noqa: E402
from treeinfer.data.trajectories import Trajectory  # noqa: E402
from treeinfer.tree.generators import chain  # noqa: E402

pytestmark = pytest.mark.slow

LAYOUT = PullLayout(n_pulls=2, duration=0.5, dt=0.01)
TRAIN = TrainConfig(
    simulations=1024,
    chunk=256,
    epochs=30,
    flow_layers=3,
    width=32,
    embedding=8,
    batch_size=128,
    sigma_x_range=(1e-3, 3e-3),
)
TREE = chain(1, lengths=0.7, radii=0.03, name="c1")


@pytest.fixture(scope="module")
def model():
    return estimator.train(TREE, AmortiseConfig(LAYOUT, TRAIN))


def _recording(kp, kd, seed, sigma_x=2e-3, sigma_f=0.0, scale=1.0, delay=0):
    """Pulls of the layout's family at gains ``kp``, ``kd`` (the run's simulator), displacement
    noise ``sigma_x``, force noise ``sigma_f``; ``scale`` multiplies the forces (and so the
    sag); ``delay`` samples of lag of the displacement behind the force (a logger's)."""
    from treeinfer.sim.synthetic import simulate_batch

    rng = np.random.default_rng(seed)
    forces = draw_profiles(rng, LAYOUT, LAYOUT.n_pulls) * scale
    roll, _ = simulate_batch(TREE, np.array([kp]), np.array([kd]), forces, LAYOUT.dt)
    tau = np.asarray(roll.tau[0], float)
    if delay:
        tau = np.concatenate([np.zeros((len(tau), delay)), tau[:, :-delay]], axis=1)
    t = np.arange(LAYOUT.n_steps) * LAYOUT.dt
    out = []
    for i, (f, x) in enumerate(zip(forces, tau)):
        f = f + sigma_f * rng.normal(size=f.shape)
        out.append(Trajectory(t, f, x + sigma_x * rng.normal(size=x.shape), None, f"p{i}"))
    return out


def _start(am, trajs, particles=32):
    import treeinfer as ti

    force, disp = am.check_recordings(trajs)
    start, report = check.amortised_start(am, force, disp, n_draws=1024)
    problem = ti.make_problem(TREE, trajs)
    logs = []
    post = start(problem, {"options": {"particles": particles, "seed": 0}}, logs.append)
    return post, report


@pytest.mark.parametrize(
    "kp, kd, sigma_f, seed", [(60.0, 0.4, 0.0, 1), (150.0, 1.0, 0.05, 2)], ids=["clean", "noisy"]
)
def test_an_in_distribution_recording_is_answered_without_fallback(model, kp, kd, sigma_f, seed):
    """A clean force (as `treeinfer simulate` writes) and a noisy one: the check passes
    (possibly after refinement rounds) and the answer brackets the truth."""
    post, report = _start(model, _recording(kp, kd, seed, sigma_f=sigma_f))
    assert post is not None, report.get("reason")
    assert report["used"] and report["check"] == "importance" and report["khat"] <= 0.7
    assert report["ess"] >= 8 and post.run.settings["method"] == "amortised"
    theta = np.asarray(post.theta, float)
    truth = np.log([kp, kd, 2e-3])
    sd = theta.std(0) + 1e-9
    # the truth within 4 posterior standard deviations of the mean (each column)
    assert np.all(np.abs(theta.mean(0) - truth) < 4 * sd + 0.02), (theta.mean(0), truth, sd)


def test_a_force_ten_times_the_trained_peaks_falls_back(model):
    post, report = _start(model, _recording(60.0, 0.4, 3, scale=10.0))
    assert post is None and not report["used"]
    assert report["check"] == "domain" and "largest |force|" in report["reason"]


def test_a_delayed_displacement_falls_back(model):
    """Displacement 80 ms behind the force: inside the training ranges (amplitudes, noise),
    but the simulator cannot fit it; the checked posterior's sigma_x soaks up the misfit and
    the predictive check (or the weights) refuse the fast answer."""
    post, report = _start(model, _recording(60.0, 0.4, 4, delay=8))
    assert post is None and not report["used"], report
    assert report["check"] in ("predictive", "importance"), report
    assert report["reason"]


def test_a_second_recording_of_the_same_shape_is_checked_without_compiling(model):
    """Issue 31: the check's programs (rollouts, log-prior, noise density with the force-noise
    term, the LM's Gauss-Newton terms) take the recording as arguments and live with the
    model: the second recording of one shape compiles nothing (counted, not timed)."""
    import dataclasses

    import treeinfer as ti
    from treeinfer.sim.compile_stats import compile_stats
    from treeinfer.sim.program_cache import ProgramCache

    am = dataclasses.replace(model, programs=ProgramCache(16))  # none from the other tests
    stats = compile_stats()
    seen = []
    for kp, kd, seed in ((120.0, 0.8, 5), (90.0, 0.6, 6)):
        trajs = _recording(kp, kd, seed, sigma_f=0.05)
        force, disp = am.check_recordings(trajs)
        start, report = check.amortised_start(am, force, disp, n_draws=1024)
        problem = ti.make_problem(TREE, trajs)
        assert problem.noise.force_noise is not None  # the force-noise term's programs too
        mark = stats.mark()
        start(problem, {"options": {"particles": 32, "seed": 0}}, lambda m: None)
        seen.append((report, stats.since(mark)))
    (first, c1), (second, c2) = seen
    assert first["check"] == second["check"] == "importance", seen
    # the LM round ran in both (its Gauss-Newton program is one of the three)
    assert first["rounds"] >= 2 and second["rounds"] >= 2, seen
    assert c1["xla_compiles"] + c1["cache_hits"] >= 1, c1  # the counter counts
    assert c2["xla_compiles"] == 0 and c2["cache_hits"] == 0, c2["compiled"]
