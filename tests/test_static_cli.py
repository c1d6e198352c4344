"""The static model and stiffness-only inference wired through make_problem, the run layer and the
CLI: quasi-static pushes at three heights -> import-csv -> ``infer --model-kind static`` (two
heights) -> ``evaluate`` (the third)."""

from __future__ import annotations

import dataclasses
import json
from types import SimpleNamespace

import numpy as np
import pytest

from treeinfer.data.import_csv import import_csv
from treeinfer.data.pulls import load_data_pulls, stack_resolved
from treeinfer.tree.description import Branch, dump_tree, load_tree, make_tree
from treeinfer.tree.stem import Stem, branch_at_height, stem_tree, write_stem_logs

HELD_OUT = 0.24  # m


@pytest.fixture(scope="module")
def stem_data(tmp_path_factory):
    """Raw logger CSVs (gf, mm, wrapping ms counter, offsets, noise) imported per height into
    train/ (0.12, 0.36 m) and test/ (0.24 m), each with its pulls.yaml (branch, distance,
    horizontal)."""
    root = tmp_path_factory.mktemp("stem")
    tree = dataclasses.replace(stem_tree(Stem()), pull_direction="horizontal")
    dump_tree(tree, root / "stem.yaml")
    for path, push in write_stem_logs(root / "raw", Stem(), seed=3):
        branch, dist = branch_at_height(tree, push.height)
        import_csv(
            [path],
            root / ("test" if push.height == HELD_OUT else "train"),
            time="millis",
            force="load_g",
            displacement="pos_mm",
            units="time=ms,force=gf,displacement=mm",
            dt=0.5,
            tare=True,
            zero_displacement="contact",
            trim=True,
            grasp_branch=branch,
            grasp_distance=dist,
            direction="horizontal",
            tree=tree,
        )
    return root


@pytest.mark.slow
def test_cli_static_infer_then_evaluate_held_out_height(stem_data, capsys):
    from treeinfer.cli.main import main
    from treeinfer.data.trajectories import read_trajectory_dir
    from treeinfer.inference.static import static_rollout
    from treeinfer.runs import load_run

    root = stem_data
    run = root / "run"
    rc = main(
        [
            "infer",
            "--tree",
            str(root / "stem.yaml"),
            "--data",
            str(root / "train"),
            "--out",
            str(run),
            "--model-kind",
            "static",
            "--sampler",
            "svgd",
            "--particles",
            "4",
            "--iterations",
            "4",
            "--likelihood",
            "boltzmann",
            "--kT",
            "0.002",
            "--no-progress",
            "--checkpoint-every",
            "0",
            "--allow-poor-fit",
        ]
    )
    out = capsys.readouterr()
    assert rc == 0, out.err
    assert "damping (Kd): not identified" in out.out
    assert "quasi-static" not in out.err  # the notice is for the dynamic model only
    config = json.loads((run / "config.json").read_text())
    assert config["options"]["model_kind"] == "static"
    assert config["problem"]["model_kind"] == "static"
    assert config["problem"]["parameters"] == ["kp"]
    assert load_tree(run / "tree.yaml").parameters == ("kp",)
    summary = json.loads((run / "summary.json").read_text())
    assert sorted(summary["posterior"]) == sorted(f"Kp[{n}]" for n in ("link0", "link1", "link2"))
    assert "not identified" in summary["damping"]

    ev = root / "eval"
    assert (
        main(["evaluate", "--run", str(run), "--data", str(root / "test"), "--out", str(ev)]) == 0
    )
    capsys.readouterr()
    metrics = json.loads((ev / "metrics.json").read_text())["metrics"]
    assert metrics["per_trajectory"][0]["name"].endswith("push_240mm.csv")
    csv = np.genfromtxt(ev / "push_240mm_prediction.csv", delimiter=",", names=True)

    # the prediction is the static model's at the held-out recording's own pull (pulls.yaml:
    # its branch, height and horizontal direction), not at the tree's grasp point
    loaded = load_run(run)
    tree = loaded.tree
    traj = read_trajectory_dir(root / "test")[0]
    br, fr, di = stack_resolved(load_data_pulls(root / "test", tree, [traj.source]), tree)
    kp = np.exp(np.asarray(loaded.theta, float))
    own = static_rollout(loaded.sim, kp, traj.force[None], fr, di, br, tree)
    np.testing.assert_allclose(csv["mean"], np.asarray(own.tau)[:, 0].mean(0), atol=2e-6)
    at_tip = static_rollout(loaded.sim, kp, traj.force[None], None, di[0], None, tree)
    assert np.max(np.abs(csv["mean"] - np.asarray(at_tip.tau)[:, 0].mean(0))) > 1e-4
    np.testing.assert_allclose(csv["recorded"], traj.displacement, atol=1e-12)

    # predict on the same recording: its own pull too, compared with the recording
    assert (
        main(
            [
                "predict",
                "--run",
                str(run),
                "--force-csv",
                str(root / "test" / traj.source),
                "--out",
                str(root / "pred"),
            ]
        )
        == 0
    )
    assert "NOT compared" not in capsys.readouterr().err
    pred = np.genfromtxt(root / "pred" / "prediction.csv", delimiter=",", names=True)
    np.testing.assert_allclose(pred["mean"], csv["mean"], atol=1e-9)
    np.testing.assert_allclose(pred["recorded"], traj.displacement, atol=1e-12)

    # k-fold with the run's settings on the two training heights: each fold predicts its
    # held-out height at that recording's own pull
    assert (
        main(
            [
                "evaluate",
                "--run",
                str(run),
                "--data",
                str(root / "train"),
                "--kfold",
                "2",
                "--out",
                str(root / "kfold"),
                "--no-progress",
            ]
        )
        == 0
    )
    capsys.readouterr()
    folds = json.loads((root / "kfold" / "metrics.json").read_text())["folds"]
    assert sorted(f["test"][0] for f in folds) == ["push_120mm.csv", "push_360mm.csv"]


@pytest.mark.slow
def test_cli_static_noise_force_band_flag_in_predict_evaluate_and_kfold(stem_data, capsys):
    """``infer --model-kind static --likelihood gaussian --noise-force auto``: the load-cell
    term enters the predictive bands of ``predict``, ``evaluate`` and ``evaluate --kfold`` (the
    same ``band_includes_force_noise`` flag as dynamic runs), and widens them."""
    from treeinfer.cli.main import main

    root = stem_data
    run = root / "run_fn"
    quick = ["--particles", "4", "--iterations", "4", "--no-progress", "--checkpoint-every", "0"]
    argv = ["infer", "--tree", str(root / "stem.yaml"), "--data", str(root / "train")]
    argv += ["--model-kind", "static", "--likelihood", "gaussian", "--sampler", "svgd"]
    rc = main(argv + ["--out", str(run), "--noise-force", "auto", *quick, "--allow-poor-fit"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    config = json.loads((run / "config.json").read_text())
    assert config["problem"]["force_noise"] > 0
    summary = json.loads((run / "summary.json").read_text())
    assert summary["training_metrics"]["band_includes_force_noise"] is True
    test_csv = str(root / "test" / "push_240mm.csv")
    assert (
        main(["predict", "--run", str(run), "--force-csv", test_csv, "--out", str(root / "pf")])
        == 0
    )
    capsys.readouterr()
    pc = json.loads((root / "pf" / "config.json").read_text())
    assert pc["band_includes_force_noise"] is True and "force-noise term" in pc["band"]
    ev = root / "eval_fn"
    assert (
        main(["evaluate", "--run", str(run), "--data", str(root / "test"), "--out", str(ev)]) == 0
    )
    m = json.loads((ev / "metrics.json").read_text())["metrics"]
    assert m["band"] == "predictive" and m["band_includes_force_noise"] is True
    kf = root / "kfold_fn"
    argv = ["evaluate", "--run", str(run), "--data", str(root / "train"), "--kfold", "2"]
    assert main(argv + ["--out", str(kf), "--no-progress"]) == 0
    capsys.readouterr()
    folds = json.loads((kf / "metrics.json").read_text())["folds"]
    assert all(f["metrics"]["band_includes_force_noise"] is True for f in folds)
    # the same particles without the term: a narrower band than with it
    from treeinfer.data.trajectories import read_trajectory_dir
    from treeinfer.evaluation.predictive import evaluate_trajectories, force_noise_for, noise_for
    from treeinfer.inference.static import model_with_pulls
    from treeinfer.runs import load_run

    loaded = load_run(run)
    trajs = read_trajectory_dir(root / "test")
    model, grasp = model_with_pulls(
        loaded.model, root / "test", [t.source for t in trajs], tree=loaded.tree
    )
    sigma, kind = noise_for(loaded.theta, loaded.sim.n_joints, loaded.config["problem"])
    args = (loaded.sim, loaded.theta, list(loaded.labels), trajs, loaded.kT, grasp)
    kw = dict(noise_sigma=sigma, noise_kind=kind, model=model)
    with_term, _, _ = evaluate_trajectories(
        *args, **kw, force_noise=force_noise_for(loaded.config["problem"])
    )
    without, _, _ = evaluate_trajectories(*args, **kw)
    assert (
        with_term["ci_width"] > without["ci_width"] and "band_includes_force_noise" not in without
    )


def _one_joint_tree(**kw):
    return make_tree(
        [Branch("b", None, 0.5, 0.01, kd=0.3)], grasp_branch="b", grasp_fraction=1.0, **kw
    )


def test_stiffness_only_problem_holds_damping_at_the_trees_value():
    """inference: {parameters: [kp]} with the dynamic model: theta = [log Kp], the likelihood
    is the full model's at the tree's own Kd (an independent evaluation of the 2R target)."""
    from treeinfer.data.trajectories import Trajectory
    from treeinfer.inference.problem import make_problem
    from treeinfer.model.likelihood import boltzmann_log_likelihood

    tree = dataclasses.replace(_one_joint_tree(), parameters=("kp",))
    dt, n = 0.02, 25
    t = dt * np.arange(n)
    force = np.clip(t / 0.2, 0, 1) * 2.0
    x = 0.01 * np.clip(t / 0.2, 0, 1)
    traj = Trajectory(t, force, x, np.gradient(x, dt), "syn.csv")
    problem = make_problem(tree, [traj], nn_prior=False, backend="fused", likelihood="boltzmann")
    assert problem.labels == ("Kp[b]",) and problem.dim == 1
    assert problem.settings["fixed_kd"] == [0.3]
    full = boltzmann_log_likelihood(problem.sim, problem.obs, problem.kT)
    theta = np.log([[5.0], [20.0]])
    got = np.asarray(problem.log_likelihood(theta))
    ref = np.asarray(full(np.concatenate([theta, np.log(0.3) * np.ones((2, 1))], axis=1)))
    np.testing.assert_allclose(got, ref, rtol=1e-5)
    assert got[0] != pytest.approx(got[1])  # the data do depend on Kp


def test_static_and_stiffness_only_take_generative_likelihoods_and_kT_auto():
    """The noise likelihoods work with the static model and with stiffness only (theta = the
    model's gains + log sigma_x; values checked in test_model_likelihoods.py); Boltzmann with
    kT="auto" uses the same kT rule as the dynamic model on the same data."""
    from treeinfer.data.trajectories import Trajectory
    from treeinfer.inference.problem import make_problem

    dt, n = 0.02, 25
    t = dt * np.arange(n)
    force = np.clip(t / 0.2, 0, 1) * 2.0
    x = 0.01 * np.clip(t / 0.2, 0, 1) + 1e-4 * np.sin(37 * t)
    traj = Trajectory(t, force, x, np.gradient(x, dt), "syn.csv")
    kp_only = dataclasses.replace(_one_joint_tree(), parameters=("kp",))
    for tree, kind in ((kp_only, "dynamic"), (_one_joint_tree(), "static")):
        p = make_problem(
            tree, [traj], nn_prior=False, backend="fused", model_kind=kind, likelihood="gaussian"
        )
        assert p.labels == ("Kp[b]", "sigma_x")
        assert p.settings["likelihood"] == "gaussian" and p.settings["model_kind"] == kind
    auto = make_problem(
        kp_only, [traj], kT="auto", nn_prior=False, backend="fused", likelihood="boltzmann"
    )
    full = make_problem(
        _one_joint_tree(),
        [traj],
        kT="auto",
        nn_prior=False,
        backend="fused",
        likelihood="boltzmann",
    )
    assert auto.dim == 1 and auto.kT == pytest.approx(full.kT)
    assert np.isfinite(np.asarray(auto.log_likelihood(np.log([[10.0]])))).all()


def test_quasi_static_notice_logged_for_the_dynamic_model_only():
    from treeinfer.runs.service import _quasi_static_check
    from treeinfer.sim import make_simulator

    tree = stem_tree(Stem())
    # the check reads the model (masses, joints) only: the stability step spares the accuracy
    # probes of the default step (seconds of 2,000-substep rollouts)
    sim = make_simulator(tree, obs_dt=0.5, backend="fused", accuracy="coarse")
    problem = SimpleNamespace(tree=tree, sim=sim, obs=SimpleNamespace(dt=0.5))
    said = []
    _quasi_static_check(problem, {"options": {}}, said.append)
    assert len(said) == 1 and "--model-kind static" in said[0]
    said.clear()
    _quasi_static_check(problem, {"options": {"model_kind": "static"}}, said.append)
    assert said == []
