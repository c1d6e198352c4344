"""The matched stem chain from a tree file (issue 13): ``inference: {tie: shape, tie_shape}``
(parsing, validation, its layout and log density), ``treeinfer tree --kind stem`` against
:func:`treeinfer.tree.stem.matched_hinges` and the study's layout, ``--push-heights-from``,
a tied run's predictive band, and a tiny import-csv -> tree -> infer -> evaluate run."""

from __future__ import annotations

import dataclasses
import json
from types import SimpleNamespace

import numpy as np
import pytest

from treeinfer.cli.main import main
from treeinfer.errors import ConfigError, TreeFileError
from treeinfer.tree import generators as gen
from treeinfer.tree.description import load_tree, tree_from_dict, tree_to_dict, world_frames
from treeinfer.tree.stem import Stem, StemProfile, matched_hinges, stem_tree

HEIGHTS = (0.12, 0.24, 0.36)
STEM_ARGS = ["--stem-height", "0.4", "--base-diameter", "0.010", "--tip-diameter", "0.006"]


def _chain(**inference):
    return {
        "branches": [
            {"name": "a", "parent": None, "length": 0.2, "radius": 0.006},
            {"name": "b", "parent": "a", "length": 0.2, "radius": 0.005},
            {"name": "c", "parent": "b", "length": 0.1, "radius": 0.004},
        ],
        "grasp": {"branch": "c", "fraction": 1.0},
        "inference": {"levels": 3, "parameters": ["kp"], **inference},
    }


def test_tie_shape_parsed_aligned_and_round_tripped():
    t = tree_from_dict(_chain(tie="shape", tie_shape=[1.0, 0.41, 0.12], tie_scale=0.1), "t.yaml")
    assert t.inferred == ("c", "b", "a")  # the list is in the order of the inferred joints
    assert (t.tie, t.tie_scale, t.tie_shape) == ("shape", 0.1, (1.0, 0.41, 0.12))
    by_name = tree_from_dict(_chain(tie="shape", tie_shape={"a": 0.12, "b": 0.41, "c": 1.0}))
    assert by_name.tie_shape == (1.0, 0.41, 0.12)
    d = tree_to_dict(t)
    assert d["inference"]["tie_shape"] == {"c": 1.0, "b": 0.41, "a": 0.12}  # written by joint
    assert tree_from_dict(d).tie_shape == t.tie_shape
    # another tie drops the shape from the file (a run's --tie taper over a shape tree)
    taper = dataclasses.replace(t, tie="taper")
    assert "tie_shape" not in tree_to_dict(taper)["inference"]
    assert tree_from_dict(tree_to_dict(taper)).tie == "taper"


@pytest.mark.parametrize(
    "inference, match",
    [
        (dict(tie="shape"), r"t\.yaml: inference\.tie_shape: 'tie: shape' needs"),
        (dict(tie="shape", tie_shape=[1, 2]), r"inference\.tie_shape: 2 value\(s\) for 3"),
        (dict(tie="shape", tie_shape=[1, -1, 2]), r"inference\.tie_shape\[1\]: expected a posi"),
        (dict(tie="shape", tie_shape=[1, "x", 2]), r"inference\.tie_shape\[1\]: expected a posi"),
        (dict(tie="shape", tie_shape=[1, 1, ".inf"]), r"inference\.tie_shape\[2\]"),
        (dict(tie="shape", tie_shape=[1, True, 1]), r"inference\.tie_shape\[1\]"),
        (dict(tie="shape", tie_shape={"a": 1, "b": 1}), r"tie_shape: needs one .*missing: \['c'\]"),
        (
            dict(tie="shape", tie_shape={"a": 1, "b": 1, "c": 1, "z": 1}),
            r"tie_shape: needs one .*not inferred: \['z'\]",
        ),
        (dict(tie="shape", tie_shape={"a": 0, "b": 1, "c": 1}), r"inference\.tie_shape\.a"),
        (dict(tie="shape", tie_shape=5), r"inference\.tie_shape: expected a list"),
        (dict(tie="taper", tie_shape=[1, 1, 1]), r"tie_shape: given with tie 'taper'"),
        (dict(tie_shape=[1, 1, 1]), r"tie_shape: given with tie None"),
    ],
)
def test_tie_shape_errors_name_the_field(inference, match):
    with pytest.raises(TreeFileError, match=match):
        tree_from_dict(_chain(**inference), "t.yaml")


def test_tie_shape_from_a_file_on_disk_names_the_file(tmp_path):
    import yaml

    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(_chain(tie="shape", tie_shape=[1.0, 0.5])))
    with pytest.raises(TreeFileError, match=r"bad\.yaml.*inference\.tie_shape: 2 value"):
        load_tree(path)


def test_shape_tie_layout_hard_and_soft_and_run_flags():
    from treeinfer.inference.static import model_for, with_tie

    shape = np.array([1.0, 0.41, 0.12])
    t = tree_from_dict(_chain(tie="shape", tie_shape=shape.tolist()))
    hard = model_for(t, "static").layout
    assert hard.dim == 1 and hard.tie == "shape"
    theta = np.array([[0.3], [1.7]])
    np.testing.assert_allclose(np.asarray(hard.gains(theta)[0]), np.exp(theta) * shape, 1e-6)
    soft = model_for(dataclasses.replace(t, tie_scale=0.2), "static").layout
    th = np.array([[1.0, 0.1, -0.2, 0.05]])
    np.testing.assert_allclose(
        np.asarray(soft.gains(th)[0]), np.exp(th[:, :1]) * shape * np.exp(th[:, 1:]), 1e-6
    )
    # the scale's box covers every joint's own Kp box
    lo, hi = t.bounds_array()
    assert np.all(np.exp(hard.lower[0]) * shape <= lo[:3] * (1 + 1e-9))
    assert np.all(np.exp(hard.upper[0]) * shape >= hi[:3] * (1 - 1e-9))
    # infer --tie shape on a tree without a shape: the error says where a shape comes from
    plain = tree_from_dict(_chain())
    with pytest.raises(ConfigError, match=r"'shape' needs inference\.tie_shape.*--kind stem"):
        with_tie(plain, "shape", None)
    assert with_tie(t, None, 0.3).tie_scale == 0.3  # --tie-scale softens the file's shape tie
    assert with_tie(t, "taper", None).tie == "taper"


def test_hard_shape_tie_log_density_is_the_free_models_at_scale_times_shape():
    """Through the static model's log density: the tied problem at log s equals the free
    (per-joint) problem at Kp_j = s * shape_j, up to the two priors' constants (both flat
    inside their boxes), for two scales whose likelihoods differ by many nats."""
    from treeinfer.data.trajectories import Trajectory
    from treeinfer.inference.problem import make_problem

    shape = np.array([1.0, 0.5, 0.25])
    d = _chain(tie="shape", tie_shape=shape.tolist())
    d["inference"]["prior"] = {"kp": [0.5, 500.0]}
    d["pull"] = {"direction": "horizontal"}
    d["base"] = {"pitch_deg": 90.0}
    tied = tree_from_dict(d)
    free = dataclasses.replace(tied, tie=None, tie_shape=None)
    t = np.arange(20) * 0.5
    traj = Trajectory(t, 0.02 * np.minimum(t, 5.0), 2e-4 * np.minimum(t, 5.0), source="x.csv")
    kw = dict(nn_prior=False, likelihood="gaussian", model_kind="static", gradient="autodiff")
    kw["noise_displacement"] = 1e-4
    p_tied = make_problem(tied, [traj], **kw)
    p_free = make_problem(free, [traj], **kw)
    assert p_tied.dim == 1 and p_free.dim == 3
    log_s = np.log([20.0, 40.0])
    ld_tied = np.asarray(p_tied.log_density(log_s[:, None]))
    ld_free = np.asarray(p_free.log_density(log_s[:, None] + np.log(shape)))
    assert abs(ld_tied[0] - ld_tied[1]) > 5.0  # the two scales are told apart by the data
    np.testing.assert_allclose(ld_tied - ld_free, (ld_tied - ld_free)[0], atol=1e-3)
    # a wrong shape is not the same model
    ld_wrong = np.asarray(p_free.log_density(log_s[:, None] + np.log(shape[::-1])))
    assert np.ptp(ld_tied - ld_wrong) > 1.0


def test_stem_generator_puts_the_hinges_and_shape_of_matched_hinges():
    stem = Stem(height=0.5, base_diameter=0.012, tip_diameter=0.005)
    hs = (0.1, 0.25, 0.45)
    tree = gen.stem(0.5, hs, 0.012, 0.005, tie_scale=None)
    z, shape = matched_hinges(stem, hs)
    frames = world_frames(tree)
    base = float(tree.base_position[2])
    joint_z = {n: float(frames[n][0][2]) - base for n in tree.inferred}
    order = sorted(tree.inferred, key=joint_z.get)  # link0, link1, link2 from the ground up
    np.testing.assert_allclose([joint_z[n] for n in order], z, atol=1e-12)
    by_name = dict(zip(tree.inferred, tree.tie_shape))
    np.testing.assert_allclose([by_name[n] for n in order], shape, rtol=1e-12)
    assert (tree.tie, tree.tie_scale, tree.parameters) == ("shape", None, ("kp",))
    assert tree.pull_direction == "horizontal" and tree.base_pitch_deg == 90.0
    # every branch points straight up; the welded stub reaches the first pivot
    assert tree.branches[0].fixed and tree.branches[0].length == pytest.approx(z[0])
    for n in tree.names:
        np.testing.assert_allclose(frames[n][1][:, 0], [0, 0, 1], atol=1e-12)
    # radii: the taper's diameter at each piece's middle
    cuts = [0.0, *z, 0.5]
    for b, a, c in zip(tree.branches, cuts[:-1], cuts[1:]):
        assert b.radius == pytest.approx(float(stem.diameter(0.5 * (a + c))) / 2)
    # grasped at the top push height; each push height on its own link
    g = tree.branch(tree.grasp_branch)
    top = joint_z[tree.grasp_branch] + tree.grasp_fraction * g.length
    assert top == pytest.approx(hs[-1])
    pts = gen.stem_push_points(tree, hs)
    assert [p[1] for p in pts] == order
    np.testing.assert_allclose([p[2] for p in pts], np.asarray(hs) - z, atol=1e-12)


def test_stem_generator_diameter_per_height_and_bad_settings():
    # one diameter at every push height of a uniform stem: the uniform beam's shape
    uni = Stem(height=0.4, base_diameter=0.008, tip_diameter=0.008)
    tree = gen.stem(0.4, HEIGHTS, diameters=[0.008] * 3)
    _, shape = matched_hinges(uni, HEIGHTS)
    np.testing.assert_allclose(sorted(tree.tie_shape), sorted(shape), rtol=1e-9)
    prof = StemProfile(0.4, (0.0, 0.12, 0.24, 0.36), (0.011, 0.010, 0.008, 0.007))
    tree = gen.stem(0.4, HEIGHTS, base_diameter=0.011, diameters=[0.010, 0.008, 0.007])
    np.testing.assert_allclose(
        sorted(tree.tie_shape), sorted(matched_hinges(prof, HEIGHTS)[1]), rtol=1e-9
    )
    for kwargs, match in (
        (dict(push_heights=(0.2, 0.1)), "push_heights must increase"),
        (dict(push_heights=(0.1, 0.5)), r"push_heights must lie in \(0, height"),
        (dict(tip_diameter=None), "give base_diameter and tip_diameter"),
        (dict(base_diameter=-0.01), "base_diameter"),
        (dict(diameters=[0.01, 0.01]), r"diameters \(one per push height\) has 2 values"),
        (dict(gamma=1.5), r"gamma must lie in \(0, 1\)"),
        (dict(tie_scale=0.0), "tie_scale"),
    ):
        kw = dict(height=0.4, push_heights=HEIGHTS, base_diameter=0.01, tip_diameter=0.006)
        with pytest.raises(ConfigError, match=match):
            gen.stem(**{**kw, **kwargs})


def test_cli_stem_tree_round_trips_to_the_studys_matched_layout(tmp_path, capsys):
    """``tree --kind stem`` written -> loaded -> the same branches as the study's
    ``stem_tree(hinges="matched")`` and the same tied layout as its ``matched_layout``."""
    from experiments.stem_pushes import matched_layout
    from treeinfer.inference.static import tree_tied_layout

    out = tmp_path / "stem.yaml"
    args = ["tree", "--kind", "stem", *STEM_ARGS, "--push-heights", "0.12,0.24,0.36"]
    assert main([*args, "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "0.12 m: --grasp-branch link0 --grasp-distance 0.102" in text
    tree = load_tree(out)
    study = stem_tree(Stem(), kp_bounds=(0.05, 50.0), hinges="matched", tie="taper", tie_scale=0.1)
    assert tree.branches == study.branches and tree.inferred == study.inferred
    fixed = np.full(3, 0.7)
    mine = tree_tied_layout(tree, fixed)
    ref = matched_layout(study, list(HEIGHTS), SimpleNamespace(tie_scale=0.1))
    np.testing.assert_allclose(mine.shape, ref.shape, rtol=1e-12)
    np.testing.assert_allclose(mine.lower, ref.lower, rtol=1e-12)
    np.testing.assert_allclose(mine.upper, ref.upper, rtol=1e-12)
    assert mine.tau == ref.tau == 0.1
    # re-generated from the file with one option changed; the rest is the file's
    out2 = tmp_path / "hard.yaml"
    assert (
        main(
            [
                "tree",
                "--from",
                str(out),
                "--kind",
                "stem",
                "--tie-scale",
                "none",
                "--out",
                str(out2),
            ]
        )
        == 0
    )
    hard = load_tree(out2)
    assert hard.tie_scale is None and hard.tie_shape == tree.tie_shape


def test_cli_stem_tree_errors(tmp_path, capsys):
    out = str(tmp_path / "s.yaml")
    # a folder beside the output: an output inside an input folder is refused first (issue 28)
    no_pulls = tmp_path / "no_pulls"
    no_pulls.mkdir()
    for extra, match in (
        (["--push-heights", "0.1,0.2"], "--kind stem needs --stem-height"),
        ([*STEM_ARGS], r"--kind stem needs --push-heights"),
        (
            [*STEM_ARGS, "--push-heights", "0.1", "--grasp-branch", "link0"],
            "--grasp-branch does not apply",
        ),
        ([*STEM_ARGS, "--push-heights", "0.1", "--tie-scale", "-1"], "positive number or 'none'"),
        ([*STEM_ARGS, "--push-heights-from", str(no_pulls)], r"no pulls\.yaml there"),
    ):
        assert main(["tree", "--kind", "stem", *extra, "--out", out]) != 0
        assert match.replace("\\", "") in capsys.readouterr().err.replace("\\", "")
    assert (
        main(
            [
                "tree",
                "--kind",
                "chain",
                "--n",
                "2",
                "--lengths",
                "0.1",
                "--radii",
                "0.01",
                "--push-heights",
                "0.1",
                "--out",
                out,
            ]
        )
        != 0
    )
    assert "--push-heights does not apply to --kind chain" in capsys.readouterr().err


def test_push_heights_from_a_data_folder_rewrite_its_pulls(tmp_path, capsys):
    from treeinfer.data.pulls import PullSpec, read_pulls, write_pulls

    data = tmp_path / "data"
    data.mkdir()
    specs = {
        f"push_{round(1000 * h)}mm.csv": PullSpec("stem", None, h, "horizontal") for h in HEIGHTS
    }
    write_pulls(data / "pulls.yaml", specs)
    out = tmp_path / "stem.yaml"
    assert (
        main(
            [
                "tree",
                "--kind",
                "stem",
                *STEM_ARGS,
                "--push-heights-from",
                str(data),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    capsys.readouterr()
    tree = load_tree(out)
    assert tree.branches == stem_tree(Stem(), hinges="matched").branches
    pulls = read_pulls(data / "pulls.yaml", tree)  # now valid against the chain
    want = {n: (b, d) for (h, b, d), n in zip(gen.stem_push_points(tree, HEIGHTS), specs)}
    for name, spec in pulls.pulls.items():
        assert spec.branch == want[name][0] and spec.distance == pytest.approx(want[name][1])
        assert spec.direction == "horizontal"
    assert read_pulls(data / "pulls.yaml.orig").pulls == specs  # the original is kept
    again = ["tree", "--kind", "stem", *STEM_ARGS, "--push-heights-from", str(data)]
    again += ["--out", str(out), "--force"]
    # a second pass refuses: the distances now are from the links' joints, not the ground
    assert main(again) != 0
    assert "already name a generated chain's link" in capsys.readouterr().err
    write_pulls(data / "pulls.yaml", {"a.csv": PullSpec("stem", 0.5, None, None)})
    assert main(again) != 0
    assert "no 'distance'" in capsys.readouterr().err


def test_tied_runs_predictive_band_keeps_its_noise_columns():
    """evaluation.noise_for on a tied run's draws: sigma_x is the last column (soft: after the
    scale and R deviations; hard: after the scale), not a deviation read as noise."""
    from treeinfer.evaluation.predictive import noise_for

    sig = np.array([3e-5, 8e-5])
    soft = np.column_stack([np.log([10.0, 12.0]), np.zeros((2, 3)) + 0.1, np.log(sig)])
    hard = np.column_stack([np.log([10.0, 12.0]), np.log(sig)])
    base = {"likelihood": "gaussian", "parameters": ["kp"], "kp_shape": [1.0, 0.5, 0.2]}
    for theta, tau in ((soft, 0.1), (hard, None)):
        s, kind = noise_for(theta, 3, {**base, "tie_scale": tau})
        assert kind == "gaussian"
        np.testing.assert_allclose(s, sig, rtol=1e-6)


@pytest.mark.slow
def test_cli_import_tree_infer_evaluate_with_the_stem_chain(tmp_path, capsys):
    """import-csv (gf, mm, wrapping counter) -> tree --kind stem --push-heights-from ->
    infer --model-kind static --likelihood gaussian (two heights, a few MH steps) -> evaluate
    (the third): the run records the shape tie and the held-out band is the predictive one
    (noise included), wider than the parameter band."""
    import shutil

    from treeinfer.tree.stem import write_stem_logs

    all_ = tmp_path / "all"
    for path, push in write_stem_logs(tmp_path / "raw", Stem(), seed=2):
        rc = main(
            [
                "import-csv",
                str(path),
                "--out",
                str(all_),
                "--time-column",
                "millis",
                "--force-column",
                "load_g",
                "--displacement-column",
                "pos_mm",
                "--units",
                "time=ms,force=gf,displacement=mm",
                "--dt",
                "0.5",
                "--tare",
                "--zero-displacement",
                "contact",
                "--trim",
                "--grasp-branch",
                "stem",
                "--grasp-distance",
                f"{push.height:g}",
                "--direction",
                "horizontal",
            ]
        )
        assert rc == 0
    tree = tmp_path / "stem.yaml"
    assert (
        main(
            [
                "tree",
                "--kind",
                "stem",
                *STEM_ARGS,
                "--push-heights-from",
                str(all_),
                "--out",
                str(tree),
            ]
        )
        == 0
    )
    for sub, names in (
        ("train", ["push_120mm.csv", "push_360mm.csv"]),
        ("test", ["push_240mm.csv"]),
    ):
        (tmp_path / sub).mkdir()
        for n in [*names, "pulls.yaml"]:
            shutil.copy(all_ / n, tmp_path / sub / n)
    run, ev = tmp_path / "run", tmp_path / "eval"
    rc = main(
        [
            "infer",
            "--tree",
            str(tree),
            "--data",
            str(tmp_path / "train"),
            "--out",
            str(run),
            "--model-kind",
            "static",
            "--likelihood",
            "gaussian",
            "--sampler",
            "mh",
            "--particles",
            "4",
            "--iterations",
            "6",
            "--no-progress",
            "--checkpoint-every",
            "0",
            "--allow-poor-fit",
        ]
    )
    err = capsys.readouterr().err
    assert rc == 0, err
    config = json.loads((run / "config.json").read_text())
    assert config["problem"]["tie"] == "shape" and config["problem"]["tie_scale"] == 0.1
    saved = load_tree(run / "tree.yaml")
    assert saved.tie_shape == load_tree(tree).tie_shape
    assert (
        main(["evaluate", "--run", str(run), "--data", str(tmp_path / "test"), "--out", str(ev)])
        == 0
    )
    capsys.readouterr()
    m = json.loads((ev / "metrics.json").read_text())["metrics"]
    assert m["band"] == "predictive"
    assert m["ci_width"] > m["parameter_band"]["ci_width"]
    # the per-recording CSV carries the band metrics.json scores (predictive, noise included)
    csv = np.genfromtxt(ev / "push_240mm_prediction.csv", delimiter=",", names=True)
    assert csv.dtype.names[-2:] == ("predictive_lower", "predictive_upper")
    rec = csv["recorded"]
    inside = (rec >= csv["predictive_lower"]) & (rec <= csv["predictive_upper"])
    assert 100.0 * (1.0 - inside.mean()) == pytest.approx(m["pct_outside"], abs=1e-3)
    assert np.all(csv["predictive_upper"] - csv["predictive_lower"] >= csv["upper"] - csv["lower"])
