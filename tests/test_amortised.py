"""Amortised posteriors (issue 31 §2, treeinfer.amortised): the flow recovers an analytic
posterior, a trained model saves and loads to the same density, it is refused for another tree
or layout, a recording outside its training range sends the run to the simulator-based path,
the checked answer becomes a run-layer posterior, and ``infer --amortised`` writes a run folder
that loads (slow: the fallback's simulator-based run).

A tiny model (1 joint, 2 pulls of 0.3 s, 256 simulations, a few epochs) keeps the file at
about 30 s on a 2-core CPU; its answers are not meant to be good, only its plumbing."""

from __future__ import annotations

import contextlib
import io
import math

import numpy as np
import pytest

pytest.importorskip("flowjax")

from treeinfer.amortised import check, estimator, network  # noqa: E402
from treeinfer.amortised.config import AmortiseConfig, PullLayout, TrainConfig  # noqa: E402
from treeinfer.data.trajectories import Trajectory  # noqa: E402
from treeinfer.errors import ConfigError  # noqa: E402
from treeinfer.tree.generators import chain  # noqa: E402

LAYOUT = PullLayout(n_pulls=2, duration=0.3, dt=0.01, peak_range=(1.0, 2.0))
TRAIN = TrainConfig(
    simulations=256,
    chunk=128,
    epochs=4,
    flow_layers=2,
    width=16,
    embedding=4,
    batch_size=64,
    sigma_x_range=(1e-3, 3e-3),
)


def _tree(length=0.7):
    return chain(1, lengths=length, radii=0.03, name="c1")


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    am = estimator.train(_tree(), AmortiseConfig(LAYOUT, TRAIN))
    path = tmp_path_factory.mktemp("amortised") / "m"
    estimator.save(am, path)
    return am, path


def _recording(am, scale=1.0, seed=0):
    """Two pulls on the model's grid, simulated from the training distribution; ``scale``
    multiplies the forces and displacements (10: ten times outside the training range)."""
    from treeinfer.amortised.simulations import draw_profiles

    rng = np.random.default_rng(seed)
    lay = am.config.layout
    t = np.arange(lay.n_steps) * lay.dt
    clean = draw_profiles(rng, lay, lay.n_pulls) * scale
    force = clean + 0.02 * scale * rng.normal(size=clean.shape)
    disp = 0.01 * clean / 2.0 + 2e-3 * rng.normal(size=clean.shape)
    return [Trajectory(t, f, x, None, f"p{i}") for i, (f, x) in enumerate(zip(force, disp))]


def test_flow_recovers_a_linear_gaussian_posterior():
    """theta ~ N(0, I_2), x = theta + N(0, 0.3^2): the posterior is N(x / 1.09, 0.09 / 1.09)
    (closed form); the flow, trained on draws of (theta, x), must match its mean and std."""
    import jax

    rng = np.random.default_rng(0)
    n = 2000
    theta = rng.normal(size=(n, 2)).astype(np.float32)
    x = theta[:, None, :] + 0.3 * rng.normal(size=(n, 1, 2)).astype(np.float32)
    feats = np.concatenate([x, np.zeros_like(x)], axis=-1)  # one "pull" of 4 features
    m = network.build(jax.random.key(0), 2, 4, 3, 32, 8)
    m, _ = network.fit(m, theta, feats, jax.random.key(1), 25, 128, 3e-3, 10)
    draw = network.sampler(m, 4000)
    sd = math.sqrt(0.09 / 1.09)
    for i in range(3):
        z = np.asarray(draw(jax.random.key(i), feats[i])[0])
        np.testing.assert_allclose(z.mean(0), x[i, 0] / 1.09, atol=0.25 * sd + 0.03)
        np.testing.assert_allclose(z.std(0), sd, rtol=0.25)


def test_the_training_loop_is_flowjaxs_fit_to_data_and_stops_at_its_deadline():
    """network.fit is flowjax's fit_to_data step for step (the same weights, an independent
    reference: the library's own loop), plus a deadline after which no epoch starts."""
    import equinox as eqx
    import jax
    import optax
    import paramax
    from flowjax.train import fit_to_data

    rng = np.random.default_rng(0)
    theta = rng.normal(size=(300, 2)).astype(np.float32)
    feats = rng.normal(size=(300, 2, 3)).astype(np.float32)
    m0 = network.build(jax.random.key(0), 2, 3, 2, 16, 4)
    ours, losses = network.fit(m0, theta, feats, jax.random.key(1), 3, 64, 3e-3, 10)

    def loss(params, static, z, f, key=None):
        return -paramax.unwrap(eqx.combine(params, static)).log_prob(z, f).mean()

    sched = optax.cosine_decay_schedule(3e-3, 3 * (int(0.9 * 300) // 64), alpha=0.05)
    theirs, ref = fit_to_data(
        jax.random.key(1), m0, (theta, feats), loss_fn=loss, optimizer=optax.adam(sched),
        max_epochs=3, max_patience=10, batch_size=30, show_progress=False,
    )  # fmt: skip
    assert losses["train"] == ref["train"] and losses["val"] == ref["val"]
    for a, b in zip(jax.tree.leaves(eqx.filter(ours, eqx.is_inexact_array)),
                    jax.tree.leaves(eqx.filter(theirs, eqx.is_inexact_array))):  # fmt: skip
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert not losses["stopped_at_deadline"]
    _, cut = network.fit(m0, theta, feats, jax.random.key(1), 50, 64, 3e-3, 100, deadline=0.0)
    assert len(cut["train"]) == 1 and cut["stopped_at_deadline"]
    lines = []
    network.fit(m0, theta, feats, jax.random.key(1), 2, 64, 3e-3, 10, True, None, lines.append)
    assert lines and lines[0].startswith("epoch 1/2: loss ")


def test_a_trained_model_saves_and_loads_to_the_same_density(model):
    am, path = model
    loaded = estimator.load(path)
    assert loaded.meta["tree_fingerprint"] == am.meta["tree_fingerprint"]
    assert loaded.meta["layout"]["n_pulls"] == 2 and loaded.meta["treeinfer_version"]
    assert loaded.labels == ["Kp[branch0]", "Kd[branch0]", "sigma_x"]
    trajs = _recording(am)
    force, disp = loaded.check_recordings(trajs)
    feats = loaded.features(force, disp)
    theta, lq = am.draw(force, disp, 64, seed=3)
    # the flow's random permutations are stored too: the same density, not just the weights
    np.testing.assert_allclose(loaded.log_q(theta, feats), lq, rtol=1e-4, atol=1e-3)
    np.testing.assert_allclose(loaded.draw(force, disp, 64, seed=3)[0], theta, rtol=1e-5)


def test_a_folder_that_is_not_a_model_is_refused(model, tmp_path):
    _, path = model
    with pytest.raises(ConfigError, match="not an amortised model folder"):
        estimator.load(tmp_path)
    bad = tmp_path / "m"
    bad.mkdir()
    (bad / "model.json").write_text((path / "model.json").read_text())
    (bad / "model.msgpack").write_bytes((path / "model.msgpack").read_bytes()[:-8] + b"x" * 8)
    with pytest.raises(ConfigError, match="sha256"):
        estimator.load(bad)


def test_another_tree_is_refused_naming_the_difference(model):
    am, _ = model
    am.check_tree(_tree())
    with pytest.raises(ConfigError, match=r"another tree.*branches\[0\]\.length"):
        am.check_tree(_tree(length=0.8))


def test_another_layout_is_refused(model):
    am, _ = model
    trajs = _recording(am)
    with pytest.raises(ConfigError, match="1 pulls \\(trained for 2\\)"):
        am.check_recordings(trajs[:1])
    with pytest.raises(ConfigError, match="grasp fraction 0.5"):
        am.check_recordings(trajs, grasp_fraction=0.5)
    short = [
        t._replace(time=t.time[:20], force=t.force[:20], displacement=t.displacement[:20])
        for t in trajs
    ]
    with pytest.raises(ConfigError, match="20 samples per pull"):
        am.check_recordings(short)


def test_a_recording_outside_the_training_range_falls_back(model):
    """Forces ten times the trained peaks: the domain check fails, the start gives no
    posterior (the run takes the simulator-based path) and the report says why."""
    am, _ = model
    force, disp = am.check_recordings(_recording(am, scale=10.0))
    start, report = check.amortised_start(am, force, disp, n_draws=64)
    assert start(None, {"options": {"particles": 8, "seed": 0}}, print) is None
    assert report["check"] == "domain" and "largest |force|" in report["reason"]
    assert not report["used"] and report["latency_ms"] < 1000
    # inside the range: no domain reason
    force, disp = am.check_recordings(_recording(am))
    assert check.domain_reasons(am, am.features(force, disp)) == []


class _Problem:
    """A problem whose posterior is the flow itself (so the weights are flat): the start must
    accept it and return a run-layer posterior of the resampled draws."""

    def __init__(self, am, feats):
        self.am, self.feats = am, feats
        self.model, self.labels, self.settings = None, tuple(am.labels), {}
        self.sim = type("S", (), {"n_joints": 1})()

    def log_density(self, theta):
        return self.am.log_q(np.asarray(theta, float), self.feats) + 7.0


def test_a_checked_answer_becomes_the_runs_posterior(model):
    am, _ = model
    force, disp = am.check_recordings(_recording(am))
    start, report = check.amortised_start(am, force, disp, n_draws=512)
    post = start(
        _Problem(am, am.features(force, disp)), {"options": {"particles": 16, "seed": 1}}, print
    )
    assert post is not None and report["used"] and report["khat"] < 0.7
    assert post.theta.shape == (16, 3) and post.run.settings["method"] == "amortised"
    assert "amortised" in post.run.stop_reason


@pytest.mark.slow  # the fallback's simulator-based run: 30-60 s on a 2-core CPU
def test_infer_amortised_writes_a_run_folder_that_loads(model, tmp_path):
    from treeinfer.cli import main
    from treeinfer.data.trajectories import write_trajectory
    from treeinfer.runs import load_run
    from treeinfer.tree.description import dump_tree

    am, path = model
    tree_file, data = tmp_path / "tree.yaml", tmp_path / "data"
    dump_tree(_tree(), tree_file)
    data.mkdir()
    for i, t in enumerate(_recording(am)):
        write_trajectory(data / f"traj_{i:03d}.csv", t)
    out, err = io.StringIO(), io.StringIO()
    common = ["infer", "--tree", tree_file, "--data", data, "--amortised", path, "--no-progress"]
    argv = common + ["--out", tmp_path / "run", "--particles", "16", "--allow-poor-fit"]
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main([str(a) for a in argv])
    assert rc == 0, err.getvalue()
    assert "amortised posterior" in err.getvalue()
    run = load_run(tmp_path / "run")
    assert run.summary["amortised"]["fallback"] == (not run.summary["amortised"]["used"])
    # another tree: refused before anything runs, exit 2
    dump_tree(_tree(length=0.9), tree_file)
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main([str(a) for a in common + ["--out", tmp_path / "run2"]])
    assert rc == 2 and "another tree" in err.getvalue()
    # other sensors in the data folder: refused before anything runs, exit 2
    dump_tree(_tree(), tree_file)
    (data / "channels.yaml").write_text("channels: []\n")
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main([str(a) for a in common + ["--out", tmp_path / "run3"]])
    assert rc == 2 and "channels.yaml declares" in err.getvalue()


class _GaussianProblem:
    """A posterior known in closed form: N(mu, diag(sd^2)) over (log Kp, log Kd, log sigma_x),
    far narrower than a tiny flow and off its centre, as a recording's real posterior is."""

    def __init__(self, mu, sd):
        self.mu, self.sd = np.asarray(mu, float), np.asarray(sd, float)

    def log_density(self, theta):
        z = (np.asarray(theta, float) - self.mu) / self.sd
        return -0.5 * np.sum(z**2, axis=-1)


def test_refinement_reaches_a_posterior_far_narrower_than_the_flow(model):
    """The flow's draws alone degenerate (k_hat >> 0.7); the refinement rounds must end with
    passing weights whose mean and std are the Gaussian's (closed form)."""
    am, _ = model
    force, disp = am.check_recordings(_recording(am))
    feats = am.features(force, disp)
    draws, log_q = am.draw(force, disp, 1024)
    # centred half a flow-std off the flow's mean, 100 times narrower
    mu = draws.mean(0) + 0.5 * draws.std(0)
    sd = draws.std(0) / 100
    problem = _GaussianProblem(mu, sd)
    imp, _ = check.refine(am, problem, feats, draws, log_q, 64, seed=0)
    assert imp.rounds > 1 and imp.ok and imp.khat <= 0.7 and imp.ess >= 64
    w = np.exp(imp.log_weights)
    mean = w @ imp.draws
    std = np.sqrt(w @ (imp.draws - mean) ** 2)
    np.testing.assert_allclose(mean, mu, atol=0.3 * sd.max())
    np.testing.assert_allclose(std, sd, rtol=0.25)


def test_a_clean_force_is_inside_the_training_domain(model):
    """A noise-free recorded force (`treeinfer simulate` without --noise-force, rounded to a
    CSV's digits) summarises as the clean training sets do: no domain reason."""
    am, _ = model
    from treeinfer.amortised.simulations import draw_profiles

    trajs = _recording(am)
    rng = np.random.default_rng(5)
    f = draw_profiles(rng, am.config.layout, 2)
    clean = [t._replace(force=np.round(fi, 6)) for t, fi in zip(trajs, f)]
    force, disp = am.check_recordings(clean)
    assert check.domain_reasons(am, am.features(force, disp)) == []


def test_the_predictive_check_compares_sigma_x_with_the_recordings_noise(model):
    am, _ = model
    force, disp = am.check_recordings(_recording(am))  # displacement noise 2 mm
    feats = am.features(force, disp)
    assert check.predictive_reasons(am, feats, np.log([2e-3] * 8)) == []
    bad = check.predictive_reasons(am, feats, np.log([2e-2] * 8))
    assert bad and "times the recording's own noise estimate" in bad[0]


def test_the_clean_force_share_is_validated():
    with pytest.raises(ConfigError, match="clean_force_share"):
        TrainConfig(clean_force_share=1.5)


@pytest.mark.parametrize("name", ["channels.yaml", "pulls.yaml"])
def test_other_sensors_or_pulls_are_refused(tmp_path, name):
    """A data folder with observation channels or per-recording pulls: exit 2 before the
    model is even loaded (its summary holds the grasp point's force and displacement only)."""
    from treeinfer.cli.amortise import _refuse_other_sensors

    _refuse_other_sensors(tmp_path)  # a plain folder: nothing to refuse
    (tmp_path / name).write_text("{}\n")
    with pytest.raises(ConfigError, match=f"{name} declares"):
        _refuse_other_sensors(tmp_path)
