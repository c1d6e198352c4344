"""The user's posterior object (issue 29): draws and summaries in natural units, ArviZ data with
units and the prior box, diagnostics only where they apply, figures with units, the prior box and
the truth, refusals of failed runs and of predictions outside what a run supports.

Arrays are built here (no sampler runs) except in the last tests, which load the small run folder
of tests/fixtures (written by an older treeinfer: posterior.nc in log units) and predict with it.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import matplotlib
import numpy as np
import pytest
from matplotlib.patches import Rectangle
from scipy import stats

import treeinfer
from treeinfer.errors import ConfigError, PosteriorError
from treeinfer.inference.posterior import Posterior, PosteriorContext

matplotlib.use("Agg")

LABELS = ("Kp[a]", "Kp[b]", "Kd[a]", "Kd[b]")
BOX = (np.log([5.0, 5.0, 0.05, 0.05]), np.log([500.0, 500.0, 10.0, 10.0]))
FIXTURE = Path(__file__).resolve().parent / "fixtures" / "run_main_2026-11-22"


def _posterior(theta, sampler="nnsvgd", settings=None, **context):
    theta = np.asarray(theta, float)
    ctx = PosteriorContext(lower=BOX[0], upper=BOX[1], **context)
    return Posterior(
        theta,
        np.exp(theta[:, :2]),
        np.exp(theta[:, 2:4]),
        np.zeros(len(theta)),
        LABELS,
        None,
        {"sampler": sampler, **(settings or {})},
        ctx,
    )


@pytest.fixture(scope="module")
def gauss():
    """4000 particles of a known log-normal posterior: ln K ~ N(mu, sd^2)."""
    mu = np.log([40.0, 100.0, 0.4, 1.0])
    sd = np.array([0.1, 0.05, 0.5, 0.2])
    theta = mu + sd * np.random.default_rng(0).standard_normal((4000, 4))
    return mu, sd, theta


def test_draws_and_summaries_in_natural_units(gauss):
    mu, sd, theta = gauss
    post = _posterior(theta)
    d = post.sample(20000, rng=1)
    assert list(d) == list(LABELS) and all(v.shape == (20000,) for v in d.values())
    # log-normal moments (closed form) of the particles' distribution
    for j, lab in enumerate(LABELS):
        assert np.mean(d[lab]) == pytest.approx(np.exp(mu[j] + sd[j] ** 2 / 2), rel=0.03)
        assert np.median(d[lab]) == pytest.approx(np.exp(mu[j]), rel=0.03)
    np.testing.assert_allclose(post.mean.to_numpy(), np.exp(theta).mean(0), rtol=1e-12)
    np.testing.assert_allclose(post.std.to_numpy(), np.exp(theta).std(0, ddof=1), rtol=1e-12)
    assert post.mean.attrs["units"]["Kd[b]"] == "N m s/rad"
    iv = post.interval(0.9)
    assert list(iv.columns) == ["lower", "upper"] and iv.attrs["units"]["Kp[a]"] == "N m/rad"
    # the KDE interval of ln K: the normal's quantiles widened by Scott's bandwidth (N^-1/5)
    z = stats.norm.ppf(0.95) * sd * np.sqrt(1 + 4000 ** (-0.4))
    np.testing.assert_allclose(iv["lower"], np.exp(mu - z), rtol=0.03)
    np.testing.assert_allclose(iv["upper"], np.exp(mu + z), rtol=0.03)
    # a seed or a Generator: reproducible; log=True gives theta's rows
    np.testing.assert_array_equal(post.sample_array(5, rng=3), post.sample_array(5, rng=3))
    rows = post.sample_array(50, rng=np.random.default_rng(2), log=True)
    assert {tuple(r) for r in rows} <= {tuple(r) for r in theta}


def test_unusable_rows_are_never_drawn():
    theta = np.log(np.tile([[40.0, 100.0, 0.4, 1.0]], (4, 1))) + np.arange(4)[:, None] * 0.1
    ld = np.array([0.0, -np.inf, 0.0, 0.0])
    post = _posterior(theta, stable=np.array([True, True, False, True]))
    post = Posterior(*[getattr(post, f) for f in ("theta", "kp", "kd")], ld, LABELS, None,
                     post.settings, post.context)  # fmt: skip
    assert post.usable.tolist() == [True, False, False, True]
    drawn = post.sample_array(200, rng=0, log=True)
    assert set(np.round(drawn[:, 0] - theta[0, 0], 6)) == {0.0, 0.3}


def test_failed_runs_and_bad_requests_are_refused(gauss):
    _, _, theta = gauss
    poor = _posterior(theta, status="poor_fit", reasons=("the band misses 40% of the data",))
    for call in (lambda: poor.sample(10), lambda: poor.mean, lambda: poor.interval()):
        with pytest.raises(PosteriorError, match="poor_fit: the band misses 40%.*allow_poor_fit"):
            call()
    ok = _posterior(theta, status="poor_fit", allow_poor_fit=True)
    assert ok.sample_array(3, rng=0).shape == (3, 4)
    dead = _posterior(theta[:3], stable=np.zeros(3, bool))
    with pytest.raises(PosteriorError, match="no usable particle"):
        dead.sample(1)
    with pytest.raises(ConfigError, match="n: must be an integer"):
        ok.sample(0)
    with pytest.raises(ConfigError, match="level"):
        ok.interval(1.5)
    with pytest.raises(PosteriorError, match="no simulator"):
        _posterior(theta).predict(np.ones(10))


def test_arviz_data_has_units_and_the_prior_box(gauss, tmp_path):
    import xarray as xr

    from treeinfer.inference.diagnostics import save_inference_data
    from treeinfer.inference.diagnostics.arviz_compat import group_names, summary_table

    _, _, theta = gauss
    post = _posterior(theta[:200], problem_settings={"likelihood": "gaussian", "kT": 0.05})
    idata = post.to_arviz()
    assert {"posterior", "log_posterior", "sample_stats"} <= set(group_names(idata))
    kp = idata.posterior["Kp"]
    assert kp.dims == ("chain", "draw", "joint") and list(kp["joint"].values) == ["a", "b"]
    assert kp.attrs["units"] == "N m/rad" and idata.posterior["Kd"].attrs["units"] == "N m s/rad"
    np.testing.assert_allclose(kp.attrs["prior_lower"], [5.0, 5.0])
    np.testing.assert_allclose(idata.posterior["Kd"].attrs["prior_upper"], [10.0, 10.0])
    np.testing.assert_allclose(kp.values[0], np.exp(theta[:200, :2]), rtol=1e-12)
    np.testing.assert_array_equal(idata.log_posterior["theta"].values[0], theta[:200])
    assert idata.posterior.attrs["likelihood"] == "gaussian"
    assert "do not apply" in idata.posterior.attrs["rhat_ess"]
    # written and read back as a user would: az.summary of the posterior group is in natural units
    save_inference_data(idata, tmp_path / "posterior.nc")
    ds = xr.open_dataset(tmp_path / "posterior.nc", group="posterior")
    table = summary_table(ds, kind="stats")
    assert list(table.index) == list(LABELS)
    assert table.loc["Kp[a]", "mean"] == pytest.approx(np.exp(theta[:200, 0]).mean(), rel=1e-3)
    assert ds["Kp"].attrs["units"] == "N m/rad"
    summary = post.summary()
    assert summary.loc["Kd[a]", "unit"] == "N m s/rad" and "r_hat" not in summary.columns


def test_mcmc_chains_and_rhat(gauss):
    """MCMC: one ArviZ chain per sampler chain after the warm-up; R-hat near 1 for chains of the
    same distribution and far above it when one chain sits elsewhere."""
    rng = np.random.default_rng(5)
    n, chains = 400, 4
    pos = np.log([40.0, 100.0, 0.4, 1.0]) + 0.1 * rng.standard_normal((n, chains, 4))
    post = _posterior(
        pos[n // 2 :].reshape(-1, 4),
        sampler="mh",
        settings={"mcmc_draws": {"warmup": n // 2, "thin": 2}},
        trace={"positions": pos, "log_density": np.zeros((n, chains)), "iterations": np.arange(n)},
    )
    assert post.method == "mcmc"
    idata = post.to_arviz()
    assert dict(idata.posterior.sizes) == {"chain": chains, "draw": n // 4, "joint": 2}
    np.testing.assert_allclose(idata.posterior["Kp"].values[1, 3], np.exp(pos[n // 2 + 6, 1, :2]))
    d = post.diagnostics()
    assert max(d["r_hat"].values()) < 1.05 and min(d["ess_bulk"].values()) > 250
    assert "r_hat" in post.summary().columns
    pos[:, 0, 0] += 1.0  # chain 0 elsewhere in Kp[a]
    bad = post.__class__(**{**post.__dict__, "context": post.context._replace(
        trace={**post.context.trace, "positions": pos})})  # fmt: skip
    assert bad.diagnostics()["r_hat"]["Kp[a]"] > 1.5
    particles = _posterior(pos[-1], sampler="svgd").diagnostics()
    assert "do not apply" in particles["note"] and "r_hat" not in particles


def _title_inside(fig):
    fig.canvas.draw()
    width = fig.bbox.width
    texts = [fig._suptitle] if fig._suptitle is not None else []
    texts += [ax.title for ax in fig.axes if ax.get_visible() and ax.get_title()]
    assert texts
    for t in texts:
        bb = t.get_window_extent()
        assert bb.x0 >= -0.5 and bb.x1 <= width + 0.5, (t.get_text(), bb, width)


def test_figures_have_units_prior_box_and_truth(gauss, tmp_path):
    from treeinfer.evaluation.plots import save_figure

    _, _, theta = gauss
    truth = np.array([40.0, 100.0, 0.4, 1.0])
    pos = np.stack([theta[:64] + 0.5 * np.exp(-k / 5) for k in range(30)])
    post = _posterior(
        theta[:64],
        truth=truth,
        trace={"positions": pos, "log_density": -np.exp(-np.arange(30) / 2)[:, None] * 1e4
               - np.random.default_rng(0).random((30, 64)), "iterations": np.arange(30)},
    )  # fmt: skip
    fig, axes = post.pair_plot()
    assert axes.shape == (4, 4)
    assert axes[3, 0].get_xlabel() == "Kp[a] [N m/rad]" and axes[3, 2].get_ylabel() == ""
    assert axes[2, 0].get_ylabel() == "Kd[a] [N m s/rad]"
    boxes = [p for p in axes[2, 0].patches if isinstance(p, Rectangle) and p.get_ls() == "--"]
    assert len(boxes) == 1
    (x0, y0), w, h = boxes[0].get_xy(), boxes[0].get_width(), boxes[0].get_height()
    np.testing.assert_allclose([x0, y0, x0 + w, y0 + h], [5.0, 0.05, 500.0, 10.0])
    assert axes[0, 0].get_xscale() == "log"
    dot = [ln for ln in axes[3, 1].lines if ln.get_marker() == "o"]
    assert (dot[0].get_xdata()[0], dot[0].get_ydata()[0]) == (100.0, 1.0)
    legend = [t.get_text() for t in fig.legends[0].get_texts()]
    assert legend == ["truth", "prior box"]
    _title_inside(fig)
    written = save_figure(fig, tmp_path / "pairs.png", formats=("png", "pdf", "svg"))
    assert [p.suffix for p in written] == [".png", ".pdf", ".svg"]
    assert all(p.stat().st_size > 1000 for p in written)
    with pytest.raises(ConfigError, match="formats"):
        save_figure(fig, tmp_path / "x.png", formats=("tiff",))

    fig, axes = post.plot_trace()
    assert len(axes) == 5 and axes[0].get_ylabel() == "log density"
    assert [ax.get_ylabel() for ax in axes[1:]] == [
        "Kp[a] [N m/rad]", "Kp[b] [N m/rad]", "Kd[a] [N m s/rad]", "Kd[b] [N m s/rad]"
    ]  # fmt: skip
    written = post.save_figures(tmp_path / "figs", formats=("png", "svg"))
    assert sorted(p.name for p in written) == ["pairs.png", "pairs.svg", "trace.png", "trace.svg"]
    lo, hi = axes[0].get_ylim()  # the plateau is shown, not flattened by the first iterations
    assert hi - lo < 100 and any("zoomed" in t.get_text() for t in axes[0].texts)
    _title_inside(fig)


def test_band_plots_name_a_recording_and_a_truth():
    from treeinfer.evaluation.posterior_bands import PredictiveBand

    t = np.linspace(0, 1, 30)
    mean = 0.01 * t
    band = PredictiveBand(
        t, t, mean, mean - 1e-3, mean + 1e-3, mean + 1e-4 * np.ones((5, 1)),
        mean - 5e-4, mean + 5e-4, 0.95, "predictive band (simulation + fitted noise)", 0.9,
    )  # fmt: skip
    for kw, name in (({"recording": mean}, "recording"), ({"truth": mean}, "truth")):
        fig, ax = band.plot(**kw)
        names = [x.get_text() for x in ax.get_legend().get_texts()]
        assert name in names and "ground truth" not in names
        assert ax.get_ylabel() == "displacement [m]" and ax.get_xlabel() == "time [s]"
        _title_inside(fig)
    with pytest.raises(PosteriorError, match="not both"):
        band.plot(recording=mean, truth=mean)


# ---- a run folder --------------------------------------------------------------------------------
def _old_run(tmp_path: Path) -> Path:
    root = tmp_path / "old"
    shutil.copytree(FIXTURE, root)
    p = root / "run" / "config.json"
    cfg = json.loads(p.read_text())
    cfg["data"]["dir"], cfg["options"]["out"] = str(root / "data"), str(root / "run")
    p.write_text(json.dumps(cfg, indent=2))
    return root


def test_old_run_folder_loads_samples_and_predicts(tmp_path):
    root = _old_run(tmp_path)
    post = treeinfer.load_posterior(root / "run")
    assert post.labels == ("Kp[child]", "Kp[parent]", "Kd[child]", "Kd[parent]")
    with np.load(root / "run" / "trace.npz") as z:
        theta = z["theta"]
    np.testing.assert_allclose(post.mean.to_numpy(), np.exp(theta.astype(float)).mean(0))
    truth = json.loads((root / "data" / "true_params.json").read_text())
    np.testing.assert_allclose(
        post.context.truth[:2], [truth["kp"]["child"], truth["kp"]["parent"]]
    )
    # the training forces' peak from the data files (older folders do not record it)
    assert post.context.force_max == pytest.approx(4.855, abs=1e-3)
    idata = post.to_arviz()
    np.testing.assert_allclose(idata.log_posterior["theta"].values[0], theta, rtol=1e-6)

    forces = np.linspace(0.0, 4.0, 20)
    band = post.predict(forces)
    assert band.mean.shape == (20,) and band.draws.shape == (4, 20) and band.grasp_fraction == 0.9
    assert np.all(band.lower <= band.mean + 1e-12) and np.all(band.mean <= band.upper + 1e-12)
    # the same simulation as treeinfer.predict of the particles (an independent call)
    ref = treeinfer.predict(post.context.sim, theta, forces[None], 0.9)
    np.testing.assert_allclose(band.draws, np.asarray(ref.tau)[:, 0], rtol=1e-5, atol=1e-9)
    fig, ax = band.plot()
    assert ax.get_ylabel() == "displacement [m]"
    with pytest.raises(PosteriorError, match="more than 1.5 x the largest force"):
        post.predict(forces * 3)
    assert post.predict(forces * 3, extrapolate=True).mean.shape == (20,)
    with pytest.raises(PosteriorError, match="outside branch 'child'"):
        post.predict(forces, grasp=0.0)
    with pytest.raises(PosteriorError, match="'parent' is not where"):
        post.predict(forces, grasp=("parent", 0.5))
    for where in ("interrupted.partial", "interrupted"):  # the checkpoint, or the run it waits for
        with pytest.raises(PosteriorError, match="an interrupted run.*--resume"):
            treeinfer.load_posterior(root / where)
    # the four lines of docs/api_posterior.md, as written, on this folder
    doc = (Path(__file__).resolve().parents[1] / "docs" / "api_posterior.md").read_text()
    code = doc.split("```python\n", 1)[1].split("```", 1)[0]
    assert len(code.strip().splitlines()) == 4
    scope = {}
    exec(code.replace('"demo/run"', repr(str(root / "run"))), scope)
    assert scope["draws"]["Kp[child]"].shape == (1000,) and scope["axes"].shape == (4, 4)
    assert any(isinstance(p, Rectangle) for p in scope["axes"][1, 0].patches)
    summary = json.loads((root / "run" / "summary.json").read_text())
    summary["fit"] = {"status": "poor_fit", "reasons": ["misses the data"]}
    summary["status"] = "poor_fit"
    (root / "run" / "summary.json").write_text(json.dumps(summary))
    failed = treeinfer.load_posterior(root / "run")
    assert failed.context.status == "poor_fit"
    fig, _ = failed.pair_plot()  # a failed run can still be looked at ...
    with pytest.raises(PosteriorError, match="misses the data"):
        failed.sample(10)  # ... but not sampled from


def test_infer_returns_the_posterior_object():
    """The API path: ``treeinfer.infer`` (MH, one chain per particle) returns the same object,
    with its chains for ArviZ and its simulator for predictions."""
    import jax.numpy as jnp

    from treeinfer.data.trajectories import Trajectory
    from treeinfer.examples import example_path
    from treeinfer.sim import make_simulator, simulate
    from treeinfer.tree.description import load_tree

    tree = load_tree(example_path("two_branch"))
    sim = make_simulator(tree, obs_dt=0.02)
    forces = np.stack([np.minimum(np.arange(40) * 0.2, p) for p in (3.0, 5.0)])
    r = simulate(sim, jnp.asarray([[40.0, 120.0]]), jnp.asarray([[0.5, 1.0]]), jnp.asarray(forces))
    t = 0.02 * np.arange(40)
    trajs = [
        Trajectory(t, forces[b], np.asarray(r.tau[0, b], float), None, f"p{b}") for b in (0, 1)
    ]
    # noise-free pulls and theta = [log Kp, log Kd] only: the paper's loss, named explicitly
    # since issue 27 made the Gaussian likelihood (an extra sigma_x column) the default
    problem = treeinfer.make_problem(
        tree, trajs, kT=0.05, likelihood="boltzmann", sim=sim, nn_prior=False
    )
    post = treeinfer.infer(problem, sampler="mh", n_particles=4, n_iterations=9, progress=False)
    assert isinstance(post, Posterior) and post.method == "mcmc"
    assert post.context.force_max == pytest.approx(5.0)
    idata = post.to_arviz()  # 10 trace entries (the start and 9 steps), the first half dropped
    assert dict(idata.posterior.sizes) == {"chain": 4, "draw": 5, "joint": 2}
    np.testing.assert_allclose(
        idata.posterior["Kd"].values[2, -1], np.exp(post.run.trace_positions[-1, 2, 2:]), rtol=1e-6
    )
    assert set(post.diagnostics()["r_hat"]) == set(post.labels)
    band = post.predict(forces[1])
    ref = treeinfer.predict(problem, post.theta, forces[1][None])  # an independent rollout
    np.testing.assert_allclose(band.draws, np.asarray(ref.tau)[:, 0], rtol=1e-5, atol=1e-9)
    with pytest.raises(PosteriorError, match="largest force of the training data"):
        post.predict(forces[1] * 2)


def test_noise_and_tied_columns_become_their_own_variables():
    from treeinfer.inference.posterior_io import build_inference_data

    rng = np.random.default_rng(7)
    labels = ["Kp[a]", "Kd[a]", "sigma_x", "rho"]
    theta = rng.normal(size=(2, 30, 4))
    idata = build_inference_data(theta, None, labels, method="mcmc", sampler="mh")
    post = idata.posterior
    assert post["sigma_x"].dims == ("chain", "draw") and post["sigma_x"].attrs["units"] == "m"
    np.testing.assert_allclose(post["sigma_x"].values, np.exp(theta[..., 2]))
    np.testing.assert_allclose(post["rho"].values, 1 / (1 + np.exp(-theta[..., 3])))  # logit
    np.testing.assert_allclose(post["Kp"].values[..., 0], np.exp(theta[..., 0]))
    tied = ["Kp_scale", "Kp_taper_ratio[a]", "Kp_taper_ratio[b]"]
    idata = build_inference_data(theta[..., :3], None, tied, method="particles", sampler="svgd")
    assert idata.posterior["Kp_taper_ratio"].dims == ("chain", "draw", "joint")
    assert idata.posterior["Kp_scale"].attrs["units"] == "N m/rad"
    with pytest.raises(ConfigError, match="chains"):
        build_inference_data(theta, None, labels[:3], method="mcmc", sampler="mh")
