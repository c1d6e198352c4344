"""``treeinfer demo / infer / predict / evaluate`` in-process through ``main(argv)``.

One tiny problem for everything (the 2-branch example; ``demo --quick``: 2 training + 2 test
pulls of 40 steps at 0.02 s, 8 particles, 3 iterations), so that every rollout has one of two
shapes and the jitted predictions are compiled once per shape. ``demo --quick`` runs first and
its data feed ``infer`` (same settings: its particles must equal the demo's), ``predict``,
``evaluate`` and ``evaluate --kfold 2`` (on all 4 pulls). MJX tracing and compiling dominate the
time (about a minute per inference on a loaded 2-core CPU).
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from treeinfer import runs
from treeinfer.cli import COMMANDS, INFER_DEFAULTS, main
from treeinfer.data.trajectories import (
    Trajectory,
    read_force_profile,
    read_trajectory,
    read_trajectory_dir,
    write_trajectory,
)
from treeinfer.errors import TrajectoryFileError
from treeinfer.tree.description import load_tree

ROOT = Path(__file__).resolve().parents[1]
TWO = ROOT / "treeinfer" / "examples" / "two_branch.yaml"
QUICK = ["--particles", "8", "--iterations", "3", "--checkpoint-every", "0", "--no-progress"]
# settings under which the sampler runs its iterations (the defaults before issue 27's start
# pipeline, whose importance posterior usually needs none)
SAMPLER_RUN = ["--likelihood", "boltzmann", "--init", "laplace"]


def run(capsys, *argv):
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def assert_user_error(rc, err, *fragments):
    assert rc == 2, err
    assert "error:" in err and "Traceback" not in err, err
    for f in fragments:
        assert f in err, (f, err)


@pytest.fixture(scope="module")
def demo(demo_quick):
    """``treeinfer demo --quick`` with SAMPLER_RUN: (folder, its stdout); the session's run
    (tests/conftest.py), shared with the noise tests that read its pulls."""
    return demo_quick


@pytest.fixture(scope="module")
def run_dir(demo):
    """``treeinfer infer`` on the demo's training data with the demo's settings."""
    out = demo[0].parent / "run"
    buf, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(err):
        rc = main(
            [
                "infer",
                "--tree",
                str(TWO),
                "--data",
                str(demo[0] / "data" / "train"),
                "--out",
                str(out),
                "--seed",
                "0",
                *SAMPLER_RUN,  # the demo fixture's
                "--reinit-stragglers",
                "0",  # as the demo's --quick
                *QUICK,
                "--formats",  # every figure also as SVG (issue 29; not part of the results)
                "png,svg",
            ]
        )
    assert rc == 0, err.getvalue()
    # its console output, stdout and stderr (the tests look for lines in it)
    return out, buf.getvalue() + err.getvalue()


# ---- help ------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "name, options",
    [
        (
            "infer",
            [
                "--tree",
                "--data",
                "--out",
                "--sampler",
                "--particles",
                "--iterations",
                "--kT",
                "--seed",
                "--eta",
                "--grasp-fraction",
                "--max-unstable-share",
                "--checkpoint-every",
                "--resume",
                "--force",
                "--no-progress",
            ],
        ),
        (
            "predict",
            [
                "--run",
                "--force-csv",
                "--profile",
                "--duration",
                "--grasp-fraction",
                "--out",
                "--force",
            ],
        ),
        ("evaluate", ["--run", "--data", "--out", "--kfold", "--grasp-fraction"]),
        ("demo", ["--out", "--quick", "--seed"]),
    ],
)
def test_help(capsys, name, options):
    assert name in COMMANDS
    rc, out, _ = run(capsys, name, "--help")
    assert rc == 0 and "examples:" in out and f"treeinfer {name}" in out
    for opt in options:
        assert opt in out, opt


def test_infer_defaults_match_the_library():
    from treeinfer.inference.problem import DEFAULT_ETA
    from treeinfer.model.likelihood import DEFAULT_KT

    assert INFER_DEFAULTS["kT"] == DEFAULT_KT and INFER_DEFAULTS["eta"] == DEFAULT_ETA


# ---- demo ------------------------------------------------------------------------------------
def test_demo_quick(demo):
    out, stdout = demo
    assert (
        len(read_trajectory_dir(out / "data" / "train")) == 2
        and len(read_trajectory_dir(out / "data" / "test")) == 2
    )
    for f in (
        "run/config.json",
        "run/posterior.nc",
        "run/plots/bands_train.png",
        "evaluation/metrics.json",
        "evaluation/bands.png",
        "demo.json",
    ):
        assert (out / f).is_file(), f
    assert not runs.partial_dir(out / "run").exists()
    d = json.loads((out / "demo.json").read_text())
    m = d["unseen_test_metrics"]
    assert d["sizes"]["quick"] and 0 <= m["pct_outside"] <= 100 and m["ci_width"] > 0
    # the fixture's start and likelihood (SAMPLER_RUN) are recorded; the demo's defaults are
    # the start pipeline and the Gaussian model (test_demo_quick_gaussian_likelihood...)
    assert d["sizes"]["init"] == "laplace" and d["sizes"]["likelihood"] == "boltzmann"
    options = json.loads((out / "run" / "config.json").read_text())["options"]
    assert options["init"] == "laplace" and options["likelihood"] == "boltzmann"
    assert set(m["parameters"]) == {"Kp[child]", "Kp[parent]", "Kd[child]", "Kd[parent]"}
    truth = json.loads((out / "data" / "train" / "true_params.json").read_text())
    for lab, p in m["parameters"].items():  # truth recorded in log space, as the true_params say
        kind, joint = lab[:2].lower(), lab[3:-1]
        assert math.isclose(p["truth"], math.log(truth[kind][joint]), rel_tol=1e-12)
    for text in (
        "true parameters",
        "Kp[child]",
        "95% band",
        "outside",
        "inside their 95% interval",
    ):
        assert text in stdout, text


def test_demo_quick_gaussian_likelihood_on_noisy_pulls(tmp_path, capsys):
    """``demo --likelihood gaussian``: 2 mm noise on the pulls, sigma_x inferred, the headline
    band predictive; the noise column has no truth and is left out of the parameter check."""
    out = tmp_path / "demo_g"
    rc = main(["demo", "--quick", "--likelihood", "gaussian", "--out", str(out), "--no-progress"])
    assert rc == 0
    d = json.loads((out / "demo.json").read_text())
    assert d["sizes"]["likelihood"] == "gaussian"
    assert d["sizes"]["noise_displacement_data_m"] == 0.002
    m = d["unseen_test_metrics"]
    assert m["band"] == "predictive" and m["ci_width"] > 0.002  # at least the noise's width
    assert set(m["parameters"]) == {"Kp[child]", "Kp[parent]", "Kd[child]", "Kd[parent]"}
    assert "sigma_x" in d["posterior"]
    assert "added white displacement noise of 2 mm" in capsys.readouterr().err


def test_demo_rejects_bad_noise(tmp_path, capsys):
    rc = main(["demo", "--quick", "--noise-displacement", "-1", "--out", str(tmp_path / "d")])
    assert rc == 2
    assert "noise-displacement" in capsys.readouterr().err


# ---- infer -----------------------------------------------------------------------------------
def test_infer_run_folder(run_dir, demo):
    from treeinfer.inference.diagnostics.arviz_compat import read_netcdf

    out, stdout = run_dir
    names = {p.name for p in out.iterdir()}
    assert {
        "config.json",
        "tree.yaml",
        "posterior.nc",
        "particles.csv",
        "trace.npz",
        "summary.json",
        "plots",
    } <= names
    for png in ("trace.png", "pairs.png", "bands_train.png"):
        assert (out / "plots" / png).read_bytes()[:4] == b"\x89PNG"
    assert not runs.partial_dir(out).exists()
    assert not [p for p in out.parent.iterdir() if "staging" in p.name]

    cfg = json.loads((out / "config.json").read_text())
    data = demo[0] / "data" / "train"
    assert (
        cfg["seed"] == 0
        and cfg["options"]["particles"] == 8
        and cfg["options"]["sampler"] == "nnsvgd"
    )
    # the Laplace start (SAMPLER_RUN) said so, and the default gradient is recorded in the
    # problem, not among the options (as test_mapfit's slow CLI test checks)
    assert "Laplace start" in stdout and cfg["options"]["init"] == "laplace"
    assert "gradients" not in cfg["options"] and cfg["problem"]["gradient"] == "fd"
    assert {"treeinfer", "jax", "mujoco"} <= set(cfg["versions"])
    assert [f["name"] for f in cfg["data"]["files"]] == sorted(p.name for p in data.glob("*.csv"))
    for f in cfg["data"]["files"]:
        assert f["sha256"] == runs.file_sha256(data / f["name"])
    assert (
        cfg["problem"]["obs_dt"] == pytest.approx(0.02)
        and cfg["problem"]["kT"] == INFER_DEFAULTS["kT"]
    )
    assert cfg["posterior_settings"]["n_iterations"] == 3
    # the simulator backend is recorded (requested and resolved) and honoured when the run is loaded
    assert cfg["options"]["backend"] == "auto" and cfg["problem"]["backend"] == "fused"
    assert runs.load_run(out).sim.backend == "fused"
    mjx_cfg = json.loads(json.dumps(cfg))
    mjx_cfg["problem"]["backend"] = "mjx"
    assert (
        runs.simulator_for(
            load_tree(out / "tree.yaml"),
            mjx_cfg["problem"]["obs_dt"],
            mjx_cfg["problem"]["substeps"],
            mjx_cfg["problem"]["backend"],
        ).backend
        == "mjx"
    )

    with np.load(out / "trace.npz") as z:
        theta, labels, it = z["theta"], z["labels"].tolist(), z["iterations"]
        assert z["positions"].shape == (4, 8, 4) and it.tolist() == [0, 1, 2, 3]
        np.testing.assert_array_equal(z["positions"][-1], theta)
    assert labels == ["Kp[child]", "Kp[parent]", "Kd[child]", "Kd[parent]"]

    rows = [ln for ln in (out / "particles.csv").read_text().splitlines() if not ln.startswith("#")]
    assert rows[0].split(",") == ["particle", *labels, "log_density", "stable"]
    table = np.array([[float(c) for c in r.split(",")[1:5]] for r in rows[1:]])
    np.testing.assert_allclose(table, np.exp(theta.astype(float)), rtol=1e-12)  # natural units

    s = json.loads((out / "summary.json").read_text())
    assert {
        "diagnostics",
        "convergence_warnings",
        "n_unstable",
        "posterior",
        "training_metrics",
        "truth",
    } <= set(s)
    assert {"ci_width", "pct_outside", "predictive_nll", "posterior_nll"} <= set(
        s["training_metrics"]
    )
    stable = np.ones(len(theta), bool)
    stable[s["unstable_particles"]] = False
    for lab in labels:  # the printed table: mean of the stable particles' gains, and an interval
        p = s["posterior"][lab]
        k = np.exp(theta[stable, labels.index(lab)].astype(float))
        assert p["mean"] == pytest.approx(k.mean(), rel=1e-6) and p["lower"] <= p["upper"]
        assert lab in stdout
    assert "wrote" in stdout and "convergence" in stdout
    # posterior.nc: natural units with units and the prior box; the log-parameters beside them
    idata = read_netcdf(out / "posterior.nc")
    logs = idata.log_posterior["theta"]
    assert list(logs.coords["param"].values) == labels and logs.shape == (1, stable.sum(), 4)
    np.testing.assert_allclose(logs.values[0], theta[stable], rtol=0, atol=0)
    kp = idata.posterior["Kp"]
    assert kp.attrs["units"] == "N m/rad" and list(kp.coords["joint"].values) == ["child", "parent"]
    np.testing.assert_allclose(kp.values[0], np.exp(theta[stable][:, :2].astype(float)))
    np.testing.assert_allclose(kp.attrs["prior_lower"], [5.0, 5.0])  # two_branch.yaml's box
    assert idata.posterior.attrs["likelihood"] == "boltzmann"
    # the same folder through the API: the numbers summary.json reports
    import treeinfer

    post = treeinfer.load_posterior(out)
    for lab in labels:
        assert post.mean[lab] == pytest.approx(s["posterior"][lab]["mean"], rel=1e-9)
        assert post.interval().loc[lab, "lower"] == pytest.approx(s["posterior"][lab]["lower"])
    assert post.sample(100, rng=0)["Kp[child]"].shape == (100,)
    assert {p.name for p in (out / "plots").iterdir()} == {  # the fixture's --formats png,svg
        f"{stem}.{ext}" for stem in ("trace", "pairs", "bands_train") for ext in ("png", "svg")
    }  # fmt: skip
    for stem in ("trace", "pairs", "bands_train"):
        assert b"<svg" in (out / "plots" / f"{stem}.svg").read_bytes()[:2000]
    # same data, settings and seed as the demo's run: the same particles
    with np.load(demo[0] / "run" / "trace.npz") as z:
        assert np.array_equal(z["theta"], theta)


def test_infer_convergence_options(demo, tmp_path, capsys):
    """Issue 11: stragglers and prior-edge mass reported, warm-up re-init, drop, early stop,
    --prior-tail; MCMC summaries from every chain's post-warm-up draws."""
    data = demo[0] / "data" / "train"
    base = [
        "infer",
        "--tree",
        TWO,
        "--data",
        data,
        "--checkpoint-every",
        "0",
        "--no-progress",
        "--allow-poor-fit",
        "--likelihood",
        "boltzmann",
        "--init",
        "uniform",  # the sampler options under test act on a sampler run from the box
    ]
    rc, out, err = run(
        capsys,
        *base,
        "--out",
        tmp_path / "svgd",
        "--sampler",
        "svgd",
        "--particles",
        "8",
        "--iterations",
        "6",
        "--reinit-stragglers",
        "3",
        "--drop-stragglers",
        "--stop-when-converged",
        "--prior-tail",
        "0.05",
    )
    assert rc == 0, err
    s = json.loads((tmp_path / "svgd" / "summary.json").read_text())
    assert {"n_stragglers", "particles", "n_low_density", "n_outside_box", "warnings"} <= set(
        s["stragglers"]
    )
    assert set(s["prior_edge"]["parameters"]) == set(s["posterior"])
    assert s["stop_reason"] == "max_iterations" and s["n_iterations_done"] == 6
    cfg = json.loads((tmp_path / "svgd" / "config.json").read_text())
    assert cfg["options"]["prior_tail"] == 0.05 and cfg["problem"]["prior_sigma"] == 0.05
    assert cfg["options"]["reinit_stragglers"] == 3 and cfg["options"]["drop_stragglers"]

    rc, out, err = run(
        capsys,
        *base,
        "--out",
        tmp_path / "mh",
        "--sampler",
        "mh",
        "--particles",
        "4",
        "--iterations",
        "10",
        "--mcmc-warmup",
        "0.5",
        "--mcmc-thin",
        "1",
    )
    assert rc == 0, err
    s = json.loads((tmp_path / "mh" / "summary.json").read_text())
    d = s["posterior_draws"]["mcmc_draws"]
    with np.load(tmp_path / "mh" / "trace.npz") as z:
        pos = z["positions"]
    assert pos.shape[:2] == (11, 4) and d["warmup"] == 5 and d["thin"] == 1
    assert d["n_draws"] == int(np.all(np.isfinite(pos[5:]), axis=2).sum())
    rows = [
        ln
        for ln in (tmp_path / "mh" / "particles.csv").read_text().splitlines()
        if not ln.startswith("#")
    ]
    assert len(rows) - 1 == d["n_draws"]
    rc, out, err = run(capsys, "infer", "--resume", tmp_path / "mh", "--drop-stragglers")
    assert_user_error(rc, err, "--drop-stragglers")  # --resume takes every option from the run


def test_infer_refuses_existing_run(run_dir, demo, capsys):
    out = run_dir[0]
    before = (out / "config.json").read_text()
    rc, _, err = run(
        capsys, "infer", "--tree", TWO, "--data", demo[0] / "data" / "train", "--out", out, *QUICK
    )
    assert_user_error(rc, err, str(out), "--force")
    assert (out / "config.json").read_text() == before


@pytest.mark.parametrize(
    "extra, fragment",
    [
        (["--particles", "1"], "--particles"),
        (["--iterations", "0"], "--iterations"),
        (["--kT", "-1"], "--kT"),
        (["--kT", "nan"], "--kT"),
        (["--grasp-fraction", "1.5"], "--grasp-fraction"),
        (["--max-unstable-share", "2"], "--max-unstable-share"),
        (["--checkpoint-every", "-1"], "--checkpoint-every"),
    ],
)
def test_infer_bad_options(tmp_path, capsys, extra, fragment):
    data = tmp_path / "data"
    _write_pulls(data, 0.02, 2)
    out = tmp_path / "run"
    rc, _, err = run(capsys, "infer", "--tree", TWO, "--data", data, "--out", out, *extra)
    assert_user_error(rc, err, fragment)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]


def test_infer_bad_inputs(tmp_path, capsys):
    data = tmp_path / "data"
    _write_pulls(data, 0.02, 2)
    rc, _, err = run(
        capsys, "infer", "--tree", TWO, "--data", data, "--out", tmp_path / "r", "--sampler", "nuts"
    )
    assert rc == 2 and "invalid choice" in err and "nnsvgd" in err
    rc, _, err = run(
        capsys, "infer", "--tree", TWO, "--data", tmp_path / "none", "--out", tmp_path / "r"
    )
    assert_user_error(rc, err, "none")
    rc, _, err = run(capsys, "infer", "--data", data, "--out", tmp_path / "r")
    assert_user_error(rc, err, "--tree")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]


# ---- predict ---------------------------------------------------------------------------------
def _prediction(d: Path) -> tuple[list[str], np.ndarray]:
    lines = (d / "prediction.csv").read_text().splitlines()
    assert lines[0].startswith("time,")  # header first: pandas/csv readers parse it as is
    return lines[0].split(","), np.array(
        [[float(c) if c else np.nan for c in ln.split(",")] for ln in lines[1:]]
    )


def test_predict_trajectory_and_force_only_csv(run_dir, demo, tmp_path, capsys):
    from treeinfer.sim.reference import simulate_reference

    out = run_dir[0]
    test_csv = demo[0] / "data" / "test" / "traj_002.csv"
    rc, stdout, err = run(
        capsys, "predict", "--run", out, "--force-csv", test_csv, "--out", tmp_path / "p1"
    )
    assert rc == 0, err
    cols, a = _prediction(tmp_path / "p1")
    assert cols == ["time", "force", "recorded", "mean", "lower", "upper"]
    a = a[
        :, [0, 1, 3, 4, 5, 2]
    ]  # the old column order: time, force, mean, lower, upper, displacement
    tr = read_trajectory(test_csv)
    np.testing.assert_array_equal(a[:, 0], tr.time)
    np.testing.assert_array_equal(a[:, 1], tr.force)
    np.testing.assert_array_equal(a[:, 5], tr.displacement)
    assert np.all(a[:, 3] <= a[:, 2] + 1e-12) and np.all(a[:, 2] <= a[:, 4] + 1e-12)
    assert (tmp_path / "p1" / "prediction.png").is_file() and "outside the band" in stdout
    cfg = json.loads((tmp_path / "p1" / "config.json").read_text())
    assert cfg["command"] == "predict" and cfg["n_particles"] == 8

    # independent reference: the band's mean is the particles' mean rollout in plain MuJoCo (C,
    # float64)
    loaded = runs.load_run(out)
    ok = loaded.stable
    refs = [
        simulate_reference(loaded.sim, np.exp(th[:2]), np.exp(th[2:]), tr.force)[0]
        for th in loaded.theta.astype(float)[ok]
    ]
    np.testing.assert_allclose(
        a[:, 2], np.mean(refs, axis=0), atol=2e-4 + 2e-3 * np.abs(a[:, 2]).max()
    )

    # a time,force file with the same force gives the same band, without ground truth
    ff = tmp_path / "force.csv"
    ff.write_text(
        "# a force profile\ntime,force\n"
        + "".join(f"{float(t)!r},{float(f)!r}\n" for t, f in zip(tr.time, tr.force))
    )
    # (the old spelling `--force FILE` still works, with a deprecation warning)
    rc, _, err = run(capsys, "predict", "--run", out, "--force", ff, "--out", tmp_path / "p2")
    assert rc == 0, err
    assert "deprecated" in err and "--force-csv" in err
    cols2, b = _prediction(tmp_path / "p2")
    assert cols2 == cols and np.all(np.isnan(b[:, 2]))  # no recording: 'recorded' empty
    np.testing.assert_array_equal(b[:, [0, 1, 3, 4, 5]], a[:, :5])
    # --force alone means overwrite, as everywhere
    rc, _, err = run(capsys, "predict", "--run", out, "--force-csv", ff, "--out", tmp_path / "p2")
    assert_user_error(rc, err, "--force")
    rc, _, err = run(
        capsys, "predict", "--run", out, "--force-csv", ff, "--out", tmp_path / "p2", "--force"
    )
    assert rc == 0, err

    # a profile spec with the run's step
    rc, _, err = run(
        capsys,
        "predict",
        "--run",
        out,
        "--profile",
        "ramp:peak=5,ramp=0.4",
        "--duration",
        "0.8",
        "--out",
        tmp_path / "p3",
    )
    assert rc == 0, err
    _, c = _prediction(tmp_path / "p3")
    assert c.shape == (40, 6) and c[-1, 1] == 5.0


def test_predict_and_evaluate_write_every_format_asked(run_dir, demo, tmp_path, capsys):
    """--formats (issue 29): each figure in every format listed, and only those."""
    test = demo[0] / "data" / "test"
    rc, stdout, err = run(
        capsys, "predict", "--run", run_dir[0], "--force-csv", test / "traj_002.csv",
        "--out", tmp_path / "p", "--formats", "pdf",
    )  # fmt: skip
    assert rc == 0, err
    assert (tmp_path / "p" / "prediction.pdf").read_bytes()[:5] == b"%PDF-"
    assert not (tmp_path / "p" / "prediction.png").exists()
    assert "prediction.pdf" in stdout
    rc, stdout, err = run(
        capsys, "evaluate", "--run", run_dir[0], "--data", test, "--out", tmp_path / "e",
        "--formats", "png,svg,pdf",
    )  # fmt: skip
    assert rc == 0, err
    for ext in ("png", "svg", "pdf"):
        assert (tmp_path / "e" / f"bands.{ext}").stat().st_size > 0
    assert "bands.{png,svg,pdf}" in stdout
    rc, _, err = run(capsys, "evaluate", "--run", run_dir[0], "--data", test, "--out",
                     tmp_path / "e2", "--formats", "jpg")  # fmt: skip
    assert rc == 2 and "--formats" in err and "png,pdf,svg" in err
    assert not (tmp_path / "e2").exists()


def test_predict_errors(run_dir, tmp_path, capsys):
    out = run_dir[0]
    ff = tmp_path / "f.csv"
    ff.write_text("time,force\n" + "".join(f"{0.01 * i!r},{0.1 * i!r}\n" for i in range(30)))
    rc, _, err = run(capsys, "predict", "--run", out, "--force-csv", ff, "--out", tmp_path / "p")
    assert_user_error(rc, err, "time step", "0.02")
    rc, _, err = run(
        capsys, "predict", "--run", tmp_path / "missing", "--force-csv", ff, "--out", tmp_path / "p"
    )
    assert_user_error(rc, err, "missing", "no such run folder")
    (tmp_path / "norun").mkdir()
    rc, _, err = run(
        capsys, "predict", "--run", tmp_path / "norun", "--force-csv", ff, "--out", tmp_path / "p"
    )
    assert_user_error(rc, err, "no config.json")
    rc, _, err = run(
        capsys,
        "predict",
        "--run",
        out,
        "--profile",
        "ramp:peak=5,ramp=0.4",
        "--out",
        tmp_path / "p",
    )
    assert_user_error(rc, err, "--duration")
    assert not (tmp_path / "p").exists()


def test_read_force_profile_errors(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("time,newtons\n0,1\n")
    with pytest.raises(TrajectoryFileError, match="line 1.*expected 'time,force'"):
        read_force_profile(bad)
    bad.write_text("time,force\n0,1\n0.01,x\n")
    with pytest.raises(TrajectoryFileError, match="line 3"):
        read_force_profile(bad)
    bad.write_text("time,force\n0,1\n0.01,2\n0.03,3\n")
    with pytest.raises(TrajectoryFileError, match="uneven time step"):
        read_force_profile(bad)


# ---- evaluate --------------------------------------------------------------------------------
def test_evaluate_held_out(run_dir, demo, tmp_path, capsys):
    out = run_dir[0]
    test = demo[0] / "data" / "test"
    rc, stdout, err = run(capsys, "evaluate", "--run", out, "--data", test, "--out", tmp_path / "e")
    assert rc == 0, err
    for f in ("metrics.json", "metrics.md", "bands.png", "config.json"):
        assert (tmp_path / "e" / f).is_file(), f
    m = json.loads((tmp_path / "e" / "metrics.json").read_text())["metrics"]
    assert {
        "ci_width",
        "pct_outside",
        "predictive_nll",
        "posterior_nll",
        "parameters",
        "per_trajectory",
    } <= set(m)
    per = m["per_trajectory"]
    assert [p["name"] for p in per] == ["traj_002.csv", "traj_003.csv"]
    # equal-length trajectories: the pooled metrics are the per-trajectory means
    assert m["ci_width"] == pytest.approx(np.mean([p["ci_width"] for p in per]), rel=1e-5)
    assert m["pct_outside"] == pytest.approx(np.mean([p["pct_outside"] for p in per]), abs=1e-6)
    assert m["n_points"] + m["n_degenerate_points"] == 80
    # the demo evaluated the same particles on the same data
    dm = json.loads((demo[0] / "evaluation" / "metrics.json").read_text())["metrics"]
    for k in ("ci_width", "pct_outside", "predictive_nll", "posterior_nll"):
        assert m[k] == pytest.approx(dm[k], rel=1e-6), k
    assert "| 95% band width |" in (tmp_path / "e" / "metrics.md").read_text()
    assert "held-out metrics" in stdout
    # per recording: a CSV any reader parses (header first), the band around the mean
    import csv

    with open(tmp_path / "e" / "traj_002_prediction.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == ["time", "force", "recorded", "mean", "lower", "upper"]
    tr = read_trajectory(test / "traj_002.csv")
    np.testing.assert_array_equal([float(r["recorded"]) for r in rows], tr.displacement)
    assert all(
        float(r["lower"]) <= float(r["mean"]) + 1e-12 <= float(r["upper"]) + 2e-12 for r in rows
    )


def test_evaluate_and_predict_use_each_recordings_grasp_point(run_dir, demo, tmp_path, capsys):
    import shutil

    from treeinfer.data.pulls import PullSpec, write_pulls

    out = run_dir[0]
    data = tmp_path / "d"
    shutil.copytree(demo[0] / "data" / "test", data)
    write_pulls(data / "pulls.yaml", {"traj_002.csv": PullSpec(fraction=0.5)})
    rc, _, err = run(capsys, "evaluate", "--run", out, "--data", data, "--out", tmp_path / "e")
    assert rc == 0, err
    cfg = json.loads((tmp_path / "e" / "config.json").read_text())
    g = load_tree(TWO).grasp_fraction
    assert cfg["grasp_fraction"] == [0.5, g]  # traj_003 keeps the tree's grasp point
    rc, _, err = run(
        capsys,
        "evaluate",
        "--run",
        out,
        "--data",
        data,
        "--out",
        tmp_path / "e2",
        "--grasp-fraction",
        "1.0",
    )
    assert_user_error(rc, err, f"pulls.yaml records these pulls at 0.5, {g:g}")
    # predict: at its own point the recording is compared; at another, a loud warning and no
    # comparison ('recorded' empty)
    rec = data / "traj_002.csv"
    rc, stdout, err = run(
        capsys, "predict", "--run", out, "--force-csv", rec, "--out", tmp_path / "p"
    )
    assert rc == 0, err
    assert "outside the band" in stdout and "WARNING" not in err
    assert json.loads((tmp_path / "p" / "config.json").read_text())["grasp_fraction"] == 0.5
    rc, stdout, err = run(
        capsys,
        "predict",
        "--run",
        out,
        "--force-csv",
        rec,
        "--out",
        tmp_path / "q",
        "--grasp-fraction",
        "1.0",
    )
    assert rc == 0, err
    assert (
        "WARNING" in err and "fraction 1 instead of 0.5" in err and "outside the band" not in stdout
    )
    cols, a = _prediction(tmp_path / "q")
    assert np.all(np.isnan(a[:, cols.index("recorded")]))


def test_evaluate_kfold(run_dir, demo, tmp_path, capsys):
    both = tmp_path / "all"
    both.mkdir()
    for sub in ("train", "test"):
        for f in (demo[0] / "data" / sub).glob("*.csv"):
            shutil.copy(f, both / f.name)
    shutil.copy(demo[0] / "data" / "train" / "true_params.json", both)
    rc, _, err = run(
        capsys,
        "evaluate",
        "--run",
        run_dir[0],
        "--data",
        both,
        "--kfold",
        "5",
        "--out",
        tmp_path / "k",
    )
    assert_user_error(rc, err, "--kfold 5", "found 4")
    assert not (tmp_path / "k").exists()

    rc, stdout, err = run(
        capsys,
        "evaluate",
        "--run",
        run_dir[0],
        "--data",
        both,
        "--kfold",
        "2",
        "--out",
        tmp_path / "k",
        "--no-progress",
    )
    assert rc == 0, err
    res = json.loads((tmp_path / "k" / "metrics.json").read_text())
    assert res["kfold"] == 2 and len(res["folds"]) == 2
    assert [f["test"] for f in res["folds"]] == [
        ["traj_000.csv", "traj_001.csv"],
        ["traj_002.csv", "traj_003.csv"],
    ]
    for f in res["folds"]:
        assert set(f["train"]).isdisjoint(f["test"]) and len(f["train"]) == 2
        assert {"ci_width", "pct_outside", "predictive_nll", "posterior_nll", "parameters"} <= set(
            f["metrics"]
        )
    for k in ("ci_width", "pct_outside", "predictive_nll_per_point", "posterior_nll"):
        assert res["mean"][k] == pytest.approx(
            np.mean([f["metrics"][k] for f in res["folds"]]), rel=1e-12
        )
    assert (tmp_path / "k" / "fold_2_particles.csv").is_file() and (
        tmp_path / "k" / "bands.png"
    ).is_file()
    assert "mean over 2 folds" in stdout


def test_evaluate_errors(run_dir, tmp_path, capsys):
    out = run_dir[0]
    d01 = tmp_path / "dt01"
    _write_pulls(d01, 0.01, 2)
    rc, _, err = run(capsys, "evaluate", "--run", out, "--data", d01, "--out", tmp_path / "e")
    assert_user_error(rc, err, "dt=0.01", "0.02")
    rc, _, err = run(
        capsys, "evaluate", "--run", tmp_path / "nope", "--data", d01, "--out", tmp_path / "e"
    )
    assert_user_error(rc, err, "nope")
    d02 = tmp_path / "dt02"
    _write_pulls(d02, 0.02, 2)
    rc, _, err = run(
        capsys, "evaluate", "--run", out, "--data", d02, "--kfold", "1", "--out", tmp_path / "e"
    )
    assert_user_error(rc, err, "K must be an integer >= 2")
    assert not (tmp_path / "e").exists()


def _write_pulls(d: Path, dt: float, n: int) -> None:
    t = np.arange(40) * dt
    for i in range(n):
        f = (3.0 + i) * np.clip(t / 0.3, 0, 1)
        write_trajectory(d / f"p{i}.csv", Trajectory(t, f, 0.01 * f, None, f"p{i}.csv"))


def test_infer_too_many_unstable_keeps_the_sampler_state(demo, tmp_path, monkeypatch, capsys):
    """More unstable final particles than --max-unstable-share: exit 2, no run folder, and the
    sampler state kept for `--resume --max-unstable-share`. Sampling and the training rollout are
    replaced by stand-ins (this is about the bookkeeping, not the simulator)."""
    import jax.numpy as jnp
    import optax

    from treeinfer.inference import problem as inference
    from treeinfer.inference.samplers import RunResult, SVGDState

    theta = np.tile(np.log([50.0, 100.0, 1.0, 1.0]), (8, 1)).astype(np.float32)
    ld = np.full(8, -1.0, np.float32)

    def fake_infer(
        problem,
        sampler,
        n_particles,
        n_iterations,
        seed,
        progress,
        callback,
        callback_every,
        initial_state,
        start_iteration,
        **options,  # cache, warm-up ...: not used by the stand-in
    ):
        calls.append((initial_state is not None, start_iteration))
        state = SVGDState(
            jnp.asarray(theta),
            jnp.asarray(ld),
            jnp.zeros_like(jnp.asarray(theta)),
            optax.adam(0.05).init(jnp.asarray(theta)),
        )  # NNSVGD's state structure
        result = RunResult(
            theta, state, theta[None], ld[None], np.array([0]), {}, {"start_iteration": 0}, 0.0
        )
        return inference.Posterior(
            theta, np.exp(theta[:, :2]), np.exp(theta[:, 2:]), ld, problem.labels, result, {}
        )

    calls = []
    stable = np.array([True, True, True, False, False, False, False, False])
    monkeypatch.setattr(inference, "infer", fake_infer)
    monkeypatch.setattr(
        runs.service,
        "_training_fit",
        lambda *a: {"stable": stable, "prediction": None, "metrics": None},
    )
    out = tmp_path / "run"
    rc, _, err = run(
        capsys, "infer", "--tree", TWO, "--data", demo[0] / "data" / "train", "--out", out, *QUICK,
        "--likelihood", "boltzmann", "--init", "uniform",  # the (faked) sampler runs
    )  # fmt: skip
    assert_user_error(rc, err, "62% of", "--max-unstable-share", f"--resume {out}")
    assert not out.exists()
    partial = runs.partial_dir(out)
    assert runs.read_checkpoint_info(partial / runs.CHECKPOINT_FILE)["iteration"] == 3
    # a larger limit on --resume writes the run from the kept state, without sampling again
    rc, stdout, err = run(
        capsys, "infer", "--resume", out, "--max-unstable-share", "0.7", "--no-progress"
    )
    assert rc == 0, err
    assert calls == [(False, 0), (True, 3)] and not partial.exists()
    s = json.loads((out / "summary.json").read_text())
    assert s["n_unstable"] == 5 and s["unstable_particles"] == [3, 4, 5, 6, 7]
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["options"]["max_unstable_share"] == 0.7
    assert "5 unstable" in stdout
