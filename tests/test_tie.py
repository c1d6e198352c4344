"""Stiffness tied along a stem's taper (``inference: {tie: taper, tie_scale: TAU}``, ``--tie``,
``--tie-scale``): parsing and validation, the Hencky taper shape, the hard and soft layouts and
their prior, and a tiny end-to-end CLI run (static model, Gaussian noise, soft tie)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from scipy import stats

from treeinfer.errors import ConfigError, TreeFileError
from treeinfer.inference.static import model_for, taper_shape, with_tie
from treeinfer.tree.description import Branch, load_tree, make_tree, tree_from_dict, tree_to_dict
from treeinfer.tree.stem import Stem, stem_tree


def _chain_dict(**inference):
    return {
        "branches": [
            {"name": "a", "parent": None, "length": 0.2, "radius": 0.006},
            {"name": "b", "parent": "a", "length": 0.2, "radius": 0.005},
            {"name": "c", "parent": "b", "length": 0.1, "radius": 0.004},
        ],
        "grasp": {"branch": "c", "fraction": 1.0},
        "inference": {"levels": 3, "parameters": ["kp"], **inference},
    }


def test_tree_file_tie_round_trips_and_bad_values_name_the_field():
    t = tree_from_dict(_chain_dict(tie="taper", tie_scale=0.2), "t.yaml")
    assert (t.tie, t.tie_scale) == ("taper", 0.2)
    back = tree_from_dict(tree_to_dict(t))
    assert (back.tie, back.tie_scale) == ("taper", 0.2)
    assert "tie" not in tree_to_dict(tree_from_dict(_chain_dict()))["inference"]
    for bad, match in (
        (dict(tie="cone"), r"t\.yaml: inference\.tie: unknown tie 'cone'"),
        (dict(tie="taper", tie_scale=-1), r"inference\.tie_scale: expected a positive"),
        (dict(tie="taper", tie_scale="wide"), r"inference\.tie_scale: expected a positive"),
        (dict(tie_scale=0.1), r"inference\.tie_scale: given without a tie"),
    ):
        with pytest.raises(TreeFileError, match=match):
            tree_from_dict(_chain_dict(**bad), "t.yaml")


def test_tie_refused_where_it_means_nothing():
    one = _chain_dict(tie="taper")
    one["inference"]["levels"] = 1
    with pytest.raises(TreeFileError, match=r"inference\.tie: 'taper' ties .* two or more"):
        tree_from_dict(one, "t.yaml")
    fork = _chain_dict(tie="taper", joints=["b", "c", "d"])
    fork["branches"].append({"name": "d", "parent": "a", "length": 0.1, "radius": 0.004})
    with pytest.raises(TreeFileError, match=r"'b' and 'd' are on different branches|'c' and 'd'"):
        tree_from_dict(fork, "t.yaml")
    # damping inferred: the tie is on stiffness only
    kd = _chain_dict(tie="taper")
    del kd["inference"]["parameters"]
    tree = tree_from_dict(kd, "t.yaml")
    with pytest.raises(ConfigError, match=r"ties stiffness only.*parameters: \[kp\]"):
        model_for(tree, "dynamic")
    assert model_for(tree, "static").layout.dim == 1  # the static model infers kp only


def test_cli_flags_over_the_tree_file():
    plain = tree_from_dict(_chain_dict())
    tied = with_tie(plain, "taper", None)
    assert (tied.tie, tied.tie_scale) == ("taper", None)
    soft = with_tie(tied, None, 0.3)  # --tie-scale alone softens the file's tie
    assert (soft.tie, soft.tie_scale) == ("taper", 0.3)
    assert with_tie(soft, "taper", None).tie_scale == 0.3  # the file's scale is kept
    assert with_tie(soft, "none", None).tie is None
    with pytest.raises(ConfigError, match=r"--tie: unknown tie 'cone'"):
        with_tie(plain, "cone", None)
    with pytest.raises(ConfigError, match=r"--tie-scale: given without a tie"):
        with_tie(plain, None, 0.1)
    with pytest.raises(ConfigError, match=r"--tie-scale: expected a positive"):
        with_tie(plain, "taper", 0.0)
    with pytest.raises(ConfigError, match=r"--tie taper: .*two or more"):
        with_tie(dataclasses.replace(plain, inferred=("c",)), "taper", None)
    from treeinfer.runs.config import RunConfig

    with pytest.raises(ConfigError, match="--tie: unknown tie"):
        RunConfig(tree="", data="", out="", tie="cone")
    cfg = RunConfig(tree="", data="", out="", tie="taper", tie_scale=0.2)
    assert cfg.options_json()["tie"] == "taper" and cfg.options_json()["tie_scale"] == 0.2
    assert "tie" not in RunConfig(tree="", data="", out="").options_json()


def test_taper_shape_is_hencky_lumping_of_the_half_bars():
    """By hand: hinge a (root) carries half of a; b carries half of a and half of b; c (the
    free end) half of b and all of c; K = 1 / sum(l / r^4)."""
    t = tree_from_dict(_chain_dict(tie="taper"))
    flex = {
        "a": 0.1 / 0.006**4,
        "b": 0.1 / 0.006**4 + 0.1 / 0.005**4,
        "c": 0.1 / 0.005**4 + 0.1 / 0.004**4,
    }
    k = np.array([1.0 / flex[n] for n in t.inferred])
    np.testing.assert_allclose(taper_shape(t), k / k.max(), rtol=1e-12)
    # a uniform stem cut at midpoints (stub at the clamp, half-length top): every hinge E I / l
    uni = stem_tree(Stem(tip_diameter=0.010), n_links=5, hinges="midpoints", tie="taper")
    np.testing.assert_allclose(taper_shape(uni), 1.0, rtol=1e-12)


def test_hard_and_soft_layouts_and_the_soft_prior():
    tree = tree_from_dict(_chain_dict(tie="taper", tie_scale=0.25))
    shape = taper_shape(tree)
    lay = model_for(tree, "static").layout
    assert lay.dim == 4 and lay.labels[0] == "Kp_scale"
    mid = 0.5 * (lay.lower[0] + lay.upper[0])  # two scales inside the scale's box
    theta = np.array([[mid + 0.3, 0.1, -0.2, 0.05], [mid - 0.4, 0.0, 0.3, -0.1]])
    kp, kd = lay.gains(theta)
    np.testing.assert_allclose(kp, np.exp(theta[:, :1]) * shape * np.exp(theta[:, 1:]), 1e-6)
    back = lay.theta(np.asarray(kp))  # the scale is the geometric mean; round trip
    np.testing.assert_allclose(np.asarray(lay.gains(back)[0]), kp, rtol=1e-5)
    np.testing.assert_allclose(back[:, 1:].sum(1), 0.0, atol=1e-6)
    # inside the scale's box the prior is Normal(0, tau) on the deviations (scipy), up to a
    # constant
    lp = np.asarray(lay.log_prior(0.05)(theta))
    ref = stats.norm(0, 0.25).logpdf(theta[:, 1:]).sum(1)
    np.testing.assert_allclose(lp - lp[0], ref - ref[0], atol=1e-5)
    # the scale box covers every joint's own Kp box
    lo, hi = tree.bounds_array()
    assert np.all(np.exp(lay.lower[0]) * shape <= lo[:3] * (1 + 1e-9))
    assert np.all(np.exp(lay.upper[0]) * shape >= hi[:3] * (1 - 1e-9))
    hard = model_for(dataclasses.replace(tree, tie_scale=None), "static").layout
    assert hard.dim == 1
    np.testing.assert_allclose(hard.gains(theta[:, :1])[0], np.exp(theta[:, :1]) * shape, 1e-6)


def test_tied_problem_has_no_inequality_prior_and_records_the_tie():
    from treeinfer.data.trajectories import Trajectory
    from treeinfer.inference.problem import make_problem

    tree = make_tree(
        [
            Branch("a", None, 0.2, 0.006),
            Branch("b", "a", 0.2, 0.005),
        ],
        grasp_branch="b",
        levels=2,
        parameters=("kp",),
        tie="taper",
        tie_scale=0.1,
        pull_direction="horizontal",
    )
    t = np.arange(30) * 0.5
    traj = Trajectory(t, 0.01 * np.arange(30), 1e-4 * np.arange(30), source="x.csv")
    p = make_problem(tree, [traj], nn_prior=True, likelihood="gaussian", model_kind="static")
    assert p.labels[:3] == ("Kp_scale", "Kp_taper_ratio[b]", "Kp_taper_ratio[a]")
    assert not p.nn_prior and p.settings["tie"] == "taper" and p.settings["tie_scale"] == 0.1
    assert np.all(np.isfinite(np.asarray(p.log_density(np.zeros((2, p.dim))))))


@pytest.mark.slow
def test_cli_soft_tie_infer_then_evaluate(tmp_path, capsys):
    """import-csv -> infer --model-kind static --likelihood gaussian --tie taper --tie-scale ->
    evaluate at the held-out height, MH from ``--init laplace``: the tie is recorded (options,
    tree.yaml, problem) and the prediction is the static model's at the tied gains (recomputed
    here by hand)."""
    from treeinfer.cli.main import main
    from treeinfer.data.import_csv import import_csv
    from treeinfer.data.pulls import load_data_pulls, stack_resolved
    from treeinfer.data.trajectories import read_trajectory_dir
    from treeinfer.inference.static import static_rollout
    from treeinfer.runs import load_run
    from treeinfer.tree.description import dump_tree
    from treeinfer.tree.stem import branch_at_height, write_stem_logs

    tree = dataclasses.replace(
        stem_tree(Stem(), n_links=4, hinges="midpoints", kp_bounds=(0.05, 50.0)),
        pull_direction="horizontal",
    )
    dump_tree(tree, tmp_path / "stem.yaml")
    for path, push in write_stem_logs(tmp_path / "raw", Stem(), seed=1):
        branch, dist = branch_at_height(tree, push.height)
        import_csv(
            [path],
            tmp_path / ("test" if push.height == 0.24 else "train"),
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
    run = tmp_path / "run"
    args = ["infer", "--tree", str(tmp_path / "stem.yaml"), "--data", str(tmp_path / "train")]
    args += ["--out", str(run), "--model-kind", "static", "--likelihood", "gaussian"]
    args += ["--tie", "taper", "--tie-scale", "0.1", "--sampler", "mh", "--particles", "6"]
    args += ["--init", "laplace"]
    args += ["--iterations", "4", "--no-progress", "--checkpoint-every", "0", "--allow-poor-fit"]
    rc = main(args)
    err = capsys.readouterr().err
    assert rc == 0, err
    assert "Laplace start: MAP of the log-density" in err  # --init laplace, any model
    config = json.loads((run / "config.json").read_text())
    prop = np.asarray(config["sampler"]["options"]["proposal_scale"])  # MH shaped by the start
    assert prop.shape == (6, 6) and np.allclose(prop, np.tril(prop))
    assert config["options"]["tie"] == "taper" and config["options"]["tie_scale"] == 0.1
    assert config["problem"]["tie"] == "taper" and config["problem"]["tie_scale"] == 0.1
    saved = load_tree(run / "tree.yaml")
    assert (saved.tie, saved.tie_scale) == ("taper", 0.1)
    ev = tmp_path / "eval"
    assert (
        main(["evaluate", "--run", str(run), "--data", str(tmp_path / "test")] + ["--out", str(ev)])
        == 0
    )
    capsys.readouterr()
    csv = np.genfromtxt(ev / "push_240mm_prediction.csv", delimiter=",", names=True)
    loaded = load_run(run)
    th = np.asarray(loaded.theta, float)
    kp = np.exp(th[:, :1]) * taper_shape(saved) * np.exp(th[:, 1:5])
    traj = read_trajectory_dir(tmp_path / "test")[0]
    br, fr, di = stack_resolved(load_data_pulls(tmp_path / "test", saved, [traj.source]), saved)
    own = static_rollout(loaded.sim, kp, traj.force[None], fr, di, br, saved)
    np.testing.assert_allclose(csv["mean"], np.asarray(own.tau)[:, 0].mean(0), atol=2e-6)
