"""The posterior without sampler iterations (treeinfer.inference.fast,
treeinfer.inference.importance).

References: a closed-form Gaussian target for the importance weights; ``problem.log_density``
(the likelihood's own code path) for the batched evaluator; quadrature of the exact posterior on
a grid for a one-joint tree (D = 2), against which the importance-sampled mean and std are
checked.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from treeinfer.data.trajectories import Trajectory
from treeinfer.errors import ConfigError
from treeinfer.inference.fast import (
    BatchEvaluator,
    fast_posterior,
    importance_for_run,
    posterior_from_fast,
)
from treeinfer.inference.importance import (
    importance_posterior,
    importance_resample,
    psis,
    systematic_resample,
)
from treeinfer.inference.problem import make_problem
from treeinfer.sim import make_simulator
from treeinfer.sim.reference import simulate_reference
from treeinfer.tree.generators import chain


def test_importance_weights_recover_a_gaussian_target():
    rng = np.random.default_rng(0)
    q = stats.norm(0.0, 1.5)
    x = q.rvs(size=20000, random_state=rng)
    log_p = stats.norm(0.7, 0.5).logpdf(x)
    idx, lw, khat, ess, ok, reason = importance_resample(x[:, None], log_p, q.logpdf(x), 4000)
    w = np.exp(lw)
    assert ok and reason == "" and khat < 0.7 and 2000 < ess < 20000
    mean = w @ x
    assert abs(mean - 0.7) < 0.02 and abs(np.sqrt(w @ (x - mean) ** 2) - 0.5) < 0.02
    assert abs(x[idx].mean() - 0.7) < 0.03
    # a proposal much narrower than the target: heavy-tailed weights, flagged
    q = stats.norm(0.0, 0.3)
    x = q.rvs(size=4000, random_state=rng)
    _, _, khat, _, ok, reason = importance_resample(
        x[:, None], stats.norm(0.0, 1.0).logpdf(x), q.logpdf(x), 100
    )
    assert not ok and khat > 0.7 and "k_hat" in reason
    # unstable draws (-inf) get no weight
    log_p = np.where(np.arange(4000) % 2 == 0, -np.inf, 0.0)
    idx, lw, *_ = importance_resample(x[:, None], log_p, np.zeros(4000), 50)
    assert np.all(idx % 2 == 1) and np.all(np.isneginf(lw[::2]))


@pytest.mark.parametrize("scale", [0.3, 1.0, 2.5])
def test_psis_equals_arviz(scale):
    from treeinfer.inference.diagnostics.arviz_compat import psis_log_weights

    rng = np.random.default_rng(4)
    # log-normal weights: heavier tails with the scale; M = 3600, whose tail length (3 sqrt(M))
    # both ArviZ series agree on (tests/test_arviz_compat.py)
    lw = scale * rng.normal(size=3600)
    ours, k = psis(lw)
    ref, k_ref = psis_log_weights(lw)
    np.testing.assert_allclose(ours, ref, rtol=1e-10, atol=1e-12)
    assert k == pytest.approx(float(k_ref), rel=1e-10)
    assert (k > 0.7) == (scale > 2)  # heavier tails, larger k_hat


def test_systematic_resample_counts():
    w = np.array([0.5, 0.25, 0.125, 0.125])
    idx = systematic_resample(np.random.default_rng(3), np.log(w), 8)
    np.testing.assert_array_equal(np.bincount(idx, minlength=4), [4, 2, 1, 1])


@pytest.fixture(scope="module")
def one_joint():
    tree = chain(1, lengths=0.7, radii=0.03, angles_deg=0.0, base_position=(0.0, 0.0, 1.5),
                 base_pitch_deg=20.0, levels=1, name="c1")  # fmt: skip
    sim = make_simulator(tree, obs_dt=0.01, substeps=2)
    kp, kd = np.array([40.0]), np.array([0.6])
    t = np.arange(60) * 0.01
    rng = np.random.default_rng(2)
    trajs = []
    for i, peak in enumerate((6.0, 3.0)):
        f = peak * np.clip(t / (0.1 + 0.1 * i), 0.0, 1.0) * (t < 0.35)
        tau, _ = simulate_reference(sim, kp, kd, f)
        trajs.append(Trajectory(t, f, tau + 2e-3 * rng.normal(size=tau.shape), None, f"p{i}"))
    problem = make_problem(tree, trajs, sim=sim, nn_prior=False, kT=0.05, likelihood="boltzmann")
    return problem, np.log(np.concatenate([kp, kd]))


def test_batch_evaluator_equals_problem_log_density(one_joint):
    problem, truth = one_joint
    ev = BatchEvaluator(problem, chunk=5)
    theta = truth + np.random.default_rng(0).normal(size=(7, 2)) * [[0.3, 1.0]]
    theta[3] = [30.0, 0.0]  # Kp = e^30: an unstable rollout, -inf
    got = ev.log_density(theta)
    want = np.asarray(jax.jit(problem.log_density)(jnp.asarray(theta, jnp.float32)))
    assert np.isneginf(got[3]) and np.isneginf(want[3])
    fin = np.isfinite(want)
    np.testing.assert_allclose(got[fin], want[fin], rtol=1e-5, atol=1e-3)
    assert ev.calls == 2  # 7 sets in chunks of 5: one program, two runs


def test_fast_posterior_matches_grid_quadrature(one_joint):
    problem, truth = one_joint
    res = fast_posterior(problem, n_particles=256, n_starts=3, n_draws=4000, seed=1)
    assert res.ok, res.reason
    assert res.theta.shape == (256, 2) and np.all(np.isfinite(res.log_density))
    assert res.settings["program_calls"] == res.calls
    # the exact posterior by quadrature on a grid of +-7 proposal stds around the MAP point
    sd = np.sqrt(np.diag(res.importance.cov))
    axes = [np.linspace(m - 7 * s, m + 7 * s, 121) for m, s in zip(res.fit.theta, sd)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 2)
    lp = np.asarray(jax.jit(problem.log_density)(jnp.asarray(grid, jnp.float32)), float)
    w = np.exp(lp - lp[np.isfinite(lp)].max())
    w = np.where(np.isfinite(w), w, 0.0)
    w /= w.sum()
    g_mean = w @ grid
    g_sd = np.sqrt(w @ (grid - g_mean) ** 2)
    wi = np.exp(res.importance.log_weights)
    i_mean = wi @ res.importance.draws
    i_sd = np.sqrt(wi @ (res.importance.draws - i_mean) ** 2)
    se = g_sd / math.sqrt(res.importance.ess)
    assert np.all(np.abs(i_mean - g_mean) < 5 * se + 1e-3 * g_sd), (i_mean, g_mean, se)
    np.testing.assert_allclose(i_sd, g_sd, rtol=0.15)
    # the resampled particles carry the same distribution
    assert np.all(np.abs(res.theta.mean(0) - g_mean) < 0.3 * g_sd)
    # and the data identify Kp: the truth lies within the posterior's bulk
    assert abs(g_mean[0] - truth[0]) < 4 * g_sd[0]
    # the same through problem.log_density (importance_posterior) and a Student-t proposal
    other = importance_posterior(problem, res.fit, 256, n_draws=4000, seed=2, df=8.0)
    wo = np.exp(other.log_weights)
    o_mean = wo @ other.draws
    assert other.ok and np.all(
        np.abs(o_mean - g_mean) < 5 * g_sd / math.sqrt(other.ess) + 1e-3 * g_sd
    )
    # as a Posterior for the run layer: zero iterations, the diagnostics recorded
    post = posterior_from_fast(problem, res, seed=1)
    np.testing.assert_allclose(post.kp[:, 0], np.exp(res.theta[:, 0]), rtol=1e-6)
    assert post.run.settings["n_iterations_done"] == 0 and "k_hat" in post.run.stop_reason
    assert post.valid.all() and post.run.final_state.logdensity.shape == (256,)


def test_importance_for_run_logs_and_decides(one_joint):
    problem, _ = one_joint
    lines = []
    # (k_hat from a few hundred draws is noisy: 256 draws gave k_hat 1-2 with ESS 235 here)
    post, theta0 = importance_for_run(
        problem, 64, seed=3, log=lines.append, n_starts=3, n_draws=2000
    )
    assert len(lines) == 1 and "k_hat" in lines[0] and theta0.shape == (64, 2)
    assert post is not None and "no sampler iterations" in lines[0]
    np.testing.assert_array_equal(post.theta, theta0.astype(np.float32))
    good = post.theta.astype(float)
    # too few draws for the effective sample size asked: not trusted, particles still returned
    lines.clear()
    post, theta0 = importance_for_run(
        problem, 64, seed=3, log=lines.append, n_starts=3, n_draws=40, max_rounds=1,
        resample=False,
    )  # fmt: skip
    assert post is None and "not trusted" in lines[0] and theta0.shape == (64, 2)
    assert "the sampler runs from these particles" in lines[0]
    # by default resample-move refines them on the same program: the trusted posterior again
    lines.clear()
    post, theta0 = importance_for_run(
        problem, 64, seed=3, log=lines.append, n_starts=3, n_draws=40, max_rounds=1
    )
    assert len(lines) == 2 and lines[1].startswith("resample-move:"), lines
    assert post is not None and "resample-move" in post.run.stop_reason
    sd = good.std(0)
    assert np.all(np.abs(post.theta.mean(0) - good.mean(0)) < 0.5 * sd)
    assert np.all(np.abs(post.theta.std(0) / sd - 1) < 0.35)
    assert post.run.settings["resample_move"]["ok"]


def test_fast_posterior_refuses_other_models(one_joint):
    """Every likelihood of the paper's dynamic model runs on the rollout program (issue 27:
    tests/test_start_pipeline.py checks its weights); another model (here the static one) goes
    through treeinfer.inference.start_pipeline instead and is refused here."""
    problem, _ = one_joint
    static = make_problem(
        problem.tree, problem.obs, nn_prior=False, likelihood="gaussian", noise_force=None,
        noise_displacement=2e-3, model_kind="static",
    )  # fmt: skip
    with pytest.raises(ConfigError, match="dynamic model"):
        fast_posterior(static)
    with pytest.raises(ConfigError, match="n_starts"):
        fast_posterior(problem, n_starts=0)


def _cli(capsys, *argv):
    from treeinfer.cli import main

    rc = main([str(a) for a in argv])
    return rc, capsys.readouterr().err


@pytest.mark.slow  # a whole `treeinfer infer` run: 2 min on the loaded 2-core box
def test_cli_infer_init_importance(tmp_path, capsys, monkeypatch):
    """``infer --init importance``: the importance draws are the run's posterior (zero
    iterations, the stop reason with k_hat and the ESS) and predict/evaluate read the folder;
    when the weights are not trusted the sampler runs from the draws; a static model and a
    --resume of the finished run are refused with a user error."""
    import json

    import treeinfer.inference.fast as fp
    from treeinfer.data.trajectories import write_trajectory
    from treeinfer.tree.description import dump_tree

    tree = chain(1, lengths=0.7, radii=0.03, angles_deg=0.0, base_position=(0.0, 0.0, 1.5),
                 base_pitch_deg=20.0, levels=1, name="c1")  # fmt: skip
    tree_file = tmp_path / "tree.yaml"
    dump_tree(tree, tree_file)
    sim = make_simulator(tree, obs_dt=0.01, substeps=2)
    t = np.arange(60) * 0.01
    rng = np.random.default_rng(2)
    data = tmp_path / "data"
    data.mkdir()
    for i, peak in enumerate((6.0, 3.0)):  # the one_joint fixture's data
        f = peak * np.clip(t / (0.1 + 0.1 * i), 0.0, 1.0) * (t < 0.35)
        tau, _ = simulate_reference(sim, [40.0], [0.6], f)
        noisy = tau + 2e-3 * rng.normal(size=tau.shape)
        write_trajectory(data / f"p{i}.csv", Trajectory(t, f, noisy, None, f"p{i}"))
    real = fp.importance_for_run
    calls = []

    def trusted(problem, n_particles, seed, log, **kw):  # enough draws for a reliable k_hat
        # the run layer hands its ProgramCache down (the command's programs are shared)
        assert type(kw.get("programs")).__name__ == "ProgramCache"
        calls.append((n_particles, seed))
        return real(problem, n_particles, seed, log, n_starts=3, n_draws=2000, **kw)

    monkeypatch.setattr(fp, "importance_for_run", trusted)
    out = tmp_path / "run"
    common = ["--tree", tree_file, "--data", data, "--particles", 6, "--iterations", 3,
              "--checkpoint-every", 0, "--no-progress", "--init", "importance",
              "--likelihood", "boltzmann"]  # fmt: skip
    rc, err = _cli(capsys, "infer", *common, "--out", out)
    assert rc == 0, err
    assert calls == [(6, 0)] and "importance posterior" in err and "k_hat" in err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["n_iterations_done"] == 0, err
    assert "importance sampling" in summary["stop_reason"] and "k_hat" in summary["stop_reason"]
    assert "effective sample size" in summary["stop_reason"]
    assert summary["diagnostics_kind"] == "importance" and summary["diagnostics"]["khat"] <= 0.7
    assert summary["diagnostics"]["ess"] >= 6 / 4
    assert not any("diagnostics unavailable" in w for w in summary["convergence_warnings"])
    config = json.loads((out / "config.json").read_text())
    assert config["options"]["init"] == "importance"
    assert config["posterior_settings"]["n_iterations"] == 0
    assert config["posterior_settings"]["sampler"] == "importance"
    assert config["sampler"]["options"]["warmup"] == 10  # as --init laplace (svgd)
    assert not (tmp_path / "run.partial").exists()
    # predict and evaluate read the folder
    rc, err = _cli(capsys, "predict", "--run", out, "--force-csv", data / "p0.csv", "--out",
                   tmp_path / "pred")  # fmt: skip
    assert rc == 0, err
    rc, err = _cli(capsys, "evaluate", "--run", out, "--data", data, "--out", tmp_path / "ev")
    assert rc == 0, err
    # --resume of the finished run: a user error, no traceback
    rc, err = _cli(capsys, "infer", "--resume", out)
    assert rc == 2 and "already complete" in err and "Traceback" not in err, err

    # weights not trusted: the sampler runs its iterations from the importance particles
    def untrusted(problem, n_particles, seed, log, **kw):
        _, theta0 = real(
            problem, n_particles, seed, log, n_starts=3, n_draws=40, max_rounds=1,
            coarse_substeps=None, **kw,  # one round of 40 draws of the fit's own proposal
        )  # fmt: skip
        calls.append(theta0)
        return None, theta0

    monkeypatch.setattr(fp, "importance_for_run", untrusted)
    rc, err = _cli(capsys, "infer", *common, "--out", tmp_path / "run2")
    assert rc == 0, err
    assert "not trusted" in err
    summary = json.loads((tmp_path / "run2" / "summary.json").read_text())
    assert summary["n_iterations_done"] == 3 and "importance" not in summary["stop_reason"]
    trace = np.load(tmp_path / "run2" / "trace.npz")
    np.testing.assert_allclose(trace["positions"][0], calls[-1], rtol=1e-6)

    # the static model: every --init works with every model (issue 27), through its own
    # log-density (treeinfer.inference.start_pipeline), not the rollout program
    rc, err = _cli(capsys, "infer", *common, "--out", tmp_path / "run3", "--model-kind", "static")
    assert rc in (0, 4) and "importance posterior" in err and "Traceback" not in err, err
    assert (tmp_path / "run3" / "summary.json").is_file()


def test_fast_posterior_ok_needs_a_stable_band_and_enough_ess(one_joint, monkeypatch):
    """``ok`` is False when the even and odd draws' bands disagree (band_split) or when the
    effective sample size stays below 2 P; adaptive rounds run while it is below."""
    import treeinfer.inference.importance as imp_mod

    problem, _ = one_joint
    res = fast_posterior(problem, 32, n_starts=3, n_draws=2000, seed=3)
    assert res.ok and res.importance.ess >= 64 and res.settings["band_split"] <= 0.2
    assert res.settings["importance_rounds"] == res.importance.rounds >= 1
    monkeypatch.setattr(imp_mod, "band_split", lambda pred, lw: (0.010, 0.013, 0.26))
    bad = fast_posterior(problem, 32, n_starts=3, n_draws=2000, seed=3)
    assert not bad.ok and "halves" in bad.reason and "26%" in bad.reason
    monkeypatch.undo()
    few = fast_posterior(problem, 200, n_starts=3, n_draws=100, seed=2, max_rounds=1)
    assert not few.ok and "effective sample size" in few.reason


def test_default_chunk_fills_an_accelerator_with_one_round(monkeypatch):
    from treeinfer.inference import fast_evaluator as fp

    monkeypatch.setattr(fp.jax, "default_backend", lambda: "cpu")
    assert fp.default_chunk(104, 832) == 104  # the LM's batch: padding costs its share here
    monkeypatch.setattr(fp.jax, "default_backend", lambda: "gpu")
    assert fp.default_chunk(104, 832) == 832  # one program run per importance round
    assert fp.default_chunk(39, 512) == 14 * 39  # the next multiple of the LM batch (546)


def test_fast_posterior_is_the_same_with_a_larger_batch(one_joint):
    """The accelerator's batch (every call padded to the importance round's draws) changes how
    many program runs there are, not the posterior."""
    problem, _ = one_joint
    opts = dict(n_particles=64, n_starts=2, n_draws=400, seed=3, max_rounds=1)
    small = fast_posterior(problem, **opts)
    big = fast_posterior(problem, evaluator=BatchEvaluator(problem, chunk=400), **opts)
    assert big.calls < small.calls
    np.testing.assert_allclose(big.fit.theta, small.fit.theta, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(big.theta, small.theta, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(big.importance.ess, small.importance.ess, rtol=1e-4)


def test_finite_psd_drops_nonfinite_curvature_without_failing_the_batch():
    """One NaN curvature (an AR(1) density overflowing at a trial point on noise-free data) made
    the batched eigen-decomposition raise for every point, and the start pipeline fell back to
    uniform starts; now that point is zeroed and flagged, the others projected as before."""
    from treeinfer.inference.start_steps import _psd, finite_psd

    rng = np.random.default_rng(0)
    a = rng.normal(size=(3, 4, 4))
    h = a @ np.swapaxes(a, 1, 2) - 0.5 * np.eye(4)  # symmetric, some negative eigenvalues
    bad = h.copy()
    bad[1, 2, 3] = np.nan
    with pytest.raises(np.linalg.LinAlgError):
        _psd(bad)
    out, finite = finite_psd(bad)
    assert finite.tolist() == [True, False, True]
    assert np.all(out[1] == 0.0)
    np.testing.assert_allclose(out[[0, 2]], _psd(h[[0, 2]]))
    assert np.all(np.linalg.eigvalsh(out[0]) >= -1e-12)
