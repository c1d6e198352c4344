"""The command line, run in-process through ``main(argv)`` (one process: the jit and the
persistent compilation cache are shared, so the simulate tests compile MJX once), plus one
subprocess test of ``python -m treeinfer``.

The simulate tests use the 2-branch example, 2 trajectories of 0.6 s at 0.01 s (one shape,
[1, 2, 60], for every run) and check the CSVs against plain MuJoCo (the simulator's C
reference path), so a mix-up of Kp/Kd or of the joint order would show.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import mujoco
import numpy as np
import pytest

from treeinfer import __version__, cli
from treeinfer.cli import COMMANDS, main
from treeinfer.data.forces import from_spec
from treeinfer.data.trajectories import read_trajectory, read_trajectory_dir
from treeinfer.sim.synthetic import default_true_params
from treeinfer.tree import generators as gen
from treeinfer.tree.description import branch_density, load_tree, tree_to_dict
from treeinfer.tree.urdf import load_model_file

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "treeinfer" / "examples"
TWO = EXAMPLES / "two_branch.yaml"
SIM_ARGS = ["--n-traj", "2", "--duration", "0.6", "--dt", "0.01"]


def run(capsys, *argv):
    """(exit code, stdout, stderr) of ``main(argv)``."""
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def assert_user_error(rc, err, *fragments):
    assert rc == 2, err
    assert err.startswith("error: ") or "error:" in err, err
    assert "Traceback" not in err
    for f in fragments:
        assert f in err, (f, err)


# ---- main, help, version ------------------------------------------------------------------------
def test_main_help_lists_commands(capsys):
    rc, out, _ = run(capsys, "--help")
    assert rc == 0
    for name in COMMANDS:
        assert name in out
    assert "--debug" in out and "--version" in out


def test_version(capsys):
    rc, out, _ = run(capsys, "--version")
    assert rc == 0 and __version__ in out


@pytest.mark.parametrize(
    "name, options",
    [
        (
            "tree",
            [
                "--out",
                "--kind",
                "--from",
                "--mjcf",
                "--urdf",
                "--depth",
                "--rule",
                "--grasp-fraction",
                "--levels",
            ],
        ),
        (
            "simulate",
            [
                "--tree",
                "--out",
                "--n-traj",
                "--seed",
                "--params",
                "--params-json",
                "--duration",
                "--dt",
                "--profile-kind",
                "--peak-range",
                "--noise-force",
                "--noise-displacement",
                "--grasp-fraction",
                "--force",
            ],
        ),
        ("import-bag", ["--out", "--force-topic", "--pose-topic", "--dt"]),
    ],
)
def test_subcommand_help(capsys, name, options):
    rc, out, _ = run(capsys, name, "--help")
    assert rc == 0
    assert "example" in out and f"treeinfer {name} " in out  # an epilog with an example
    for opt in options:
        assert opt in out, opt
    assert "--debug" in out


def test_every_command_has_help(capsys):
    for name in COMMANDS:
        rc, out, _ = run(capsys, name, "--help")
        assert rc == 0 and f"treeinfer {name}" in out


def test_usage_errors_exit_2(capsys):
    rc, _, err = run(capsys)
    assert rc == 2 and "required" in err
    rc, _, err = run(capsys, "tree", "--out", "x.yaml", "--kind", "bogus")
    assert rc == 2 and "invalid choice" in err
    rc, _, err = run(capsys, "simulate", "--tree", "t.yaml", "--out", "d", "--peak-range", "1")
    assert rc == 2 and "LO,HI" in err


def _boom(exc):
    def run_(args):
        raise exc

    return run_


def test_internal_error_exit_3_without_traceback(capsys, monkeypatch, tmp_path):
    monkeypatch.setitem(
        COMMANDS, "tree", cli.Command(cli.configure_tree, _boom(ZeroDivisionError("oops")))
    )
    rc, _, err = run(capsys, "tree", "--out", tmp_path / "t.yaml")
    assert rc == 3
    assert "internal error" in err and "oops" in err and "--debug" in err and "Traceback" not in err
    rc, _, err = run(capsys, "--debug", "tree", "--out", tmp_path / "t.yaml")
    assert rc == 3 and "Traceback" in err and "ZeroDivisionError" in err
    rc, _, err = run(
        capsys, "tree", "--out", tmp_path / "t.yaml", "--debug"
    )  # after the command too
    assert rc == 3 and "Traceback" in err


def test_interrupt_and_oserror(capsys, monkeypatch, tmp_path):
    monkeypatch.setitem(
        COMMANDS, "tree", cli.Command(cli.configure_tree, _boom(KeyboardInterrupt()))
    )
    rc, _, err = run(capsys, "tree", "--out", tmp_path / "t.yaml")
    assert rc == 130 and "interrupted" in err and "Traceback" not in err
    monkeypatch.setitem(
        COMMANDS,
        "tree",
        cli.Command(cli.configure_tree, _boom(PermissionError(13, "Permission denied", "/x/y"))),
    )
    rc, _, err = run(capsys, "tree", "--out", tmp_path / "t.yaml")
    assert_user_error(rc, err, "/x/y", "Permission denied")


def test_python_m_treeinfer_subprocess(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(ROOT), "JAX_PLATFORMS": "cpu"}
    p = subprocess.run(
        [sys.executable, "-m", "treeinfer", "--help"],
        capture_output=True,
        text=True,
        env=env,
        cwd=tmp_path,
        check=False,
    )
    assert p.returncode == 0, p.stderr
    assert "usage: treeinfer" in p.stdout and "simulate" in p.stdout
    bad = tmp_path / "bad.yaml"
    bad.write_text("branches: [\n")
    p = subprocess.run(
        [
            sys.executable,
            "-m",
            "treeinfer",
            "tree",
            "--from",
            str(bad),
            "--out",
            str(tmp_path / "x.yaml"),
        ],
        capture_output=True,
        text=True,
        env=env,
        cwd=tmp_path,
        check=False,
    )
    assert p.returncode == 2 and "invalid YAML" in p.stderr and "Traceback" not in p.stderr
    assert not (tmp_path / "x.yaml").exists()


# ---- tree ---------------------------------------------------------------------------------------
def _check_models(tree, mjcf: Path, urdf: Path):
    """Both model files load in MuJoCo with one hinge per jointed branch and the wood's mass."""
    mass = sum(branch_density(tree, b) * math.pi * b.radius**2 * b.length for b in tree.branches)
    jointed = {b.name for b in tree.branches if not b.fixed}
    for path in (mjcf, urdf):
        m = load_model_file(path)
        assert {m.joint(j).name for j in range(m.njnt)} == jointed
        assert all(m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE for j in range(m.njnt))
        np.testing.assert_allclose(m.body_mass.sum(), mass, rtol=1e-6)


@pytest.mark.parametrize(
    "kind, options, reference",
    [
        (
            "chain",
            [
                "--n",
                "3",
                "--lengths",
                "0.7,0.6,0.5",
                "--radii",
                "0.03,0.02,0.014",
                "--angles",
                "-10",
            ],
            lambda: gen.chain(3, [0.7, 0.6, 0.5], [0.03, 0.02, 0.014], -10.0),
        ),
        (
            "fractal",
            [
                "--depth",
                "1",
                "--branching",
                "3",
                "--base-pitch",
                "20",
                "--levels",
                "1",
                "--grasp-fraction",
                "0.5",
            ],
            lambda: gen.fractal(1, 3, base_pitch_deg=20.0, levels=1, grasp_fraction=0.5),
        ),
        (
            "lsystem",
            [
                "--axiom",
                "F",
                "--rule",
                "F=F[+F]F[-F]",
                "--iterations",
                "1",
                "--angle",
                "30",
                "--kp-bounds",
                "10,300",
            ],
            lambda: gen.lsystem(
                "F", {"F": "F[+F]F[-F]"}, 1, angle_deg=30.0, bounds={"kp": [10, 300]}
            ),
        ),
    ],
)
def test_tree_generators_write_loadable_tree_and_models(capsys, tmp_path, kind, options, reference):
    out, mjcf, urdf = tmp_path / f"{kind}.yaml", tmp_path / f"{kind}.xml", tmp_path / f"{kind}.urdf"
    rc, stdout, err = run(
        capsys, "tree", "--kind", kind, *options, "--out", out, "--mjcf", mjcf, "--urdf", urdf
    )
    assert rc == 0, err
    tree = load_tree(out)
    assert tree_to_dict(tree) == tree_to_dict(reference())  # the generator, called directly
    _check_models(tree, mjcf, urdf)
    for label in tree.parameter_labels():
        assert label in stdout
    assert f"{len(tree.branches)} branches" in stdout and tree.grasp_branch in stdout


def test_tree_from_converts_and_regenerates(capsys, tmp_path):
    # convert YAML -> JSON with a new grasp point
    out = tmp_path / "two.json"
    rc, _, err = run(capsys, "tree", "--from", TWO, "--grasp-fraction", "0.5", "--out", out)
    assert rc == 0, err
    a, b = load_tree(TWO), load_tree(out)
    assert b.branches == a.branches and b.inferred == a.inferred and b.grasp_fraction == 0.5
    json.loads(out.read_text())  # really JSON
    # plain conversion keeps a generated file's recipe; re-generation changes only what is given
    frac = tmp_path / "f.yaml"
    assert (
        run(
            capsys, "tree", "--kind", "fractal", "--depth", "1", "--base-pitch", "15", "--out", frac
        )[0]
        == 0
    )
    copy = tmp_path / "f.json"
    assert run(capsys, "tree", "--from", frac, "--out", copy)[0] == 0
    assert json.loads(copy.read_text())["generator"]["depth"] == 1
    deeper = tmp_path / "deeper.yaml"
    rc, _, err = run(
        capsys, "tree", "--from", frac, "--kind", "fractal", "--depth", "2", "--out", deeper
    )
    assert rc == 0, err
    assert tree_to_dict(load_tree(deeper)) == tree_to_dict(gen.fractal(2, base_pitch_deg=15.0))


def test_tree_levels_and_bounds_on_conversion(capsys, tmp_path):
    out = tmp_path / "t.yaml"
    rc, _, err = run(
        capsys,
        "tree",
        "--from",
        EXAMPLES / "three_branch.yaml",
        "--levels",
        "1",
        "--kd-bounds",
        "0.1,5",
        "--out",
        out,
    )
    assert rc == 0, err
    t = load_tree(out)
    assert t.inferred == ("branch2",) and t.bounds["branch2"].kd == (0.1, 5.0)


@pytest.mark.parametrize(
    "argv, fragments",
    [
        (["--kind", "fractal", "--axiom", "F"], ["--axiom does not apply to --kind fractal"]),
        (["--kind", "explicit"], ["--kind explicit", "--from"]),
        (
            ["--kind", "chain", "--n", "2", "--lengths", "1,2,3", "--radii", "0.01"],
            ["lengths has 3 values, expected 2"],
        ),
        (
            ["--kind", "lsystem", "--axiom", "F", "--rule", "FF", "--lsystem-iterations", "1"],
            ["--rule 'FF'"],
        ),
        (
            [
                "--kind",
                "lsystem",
                "--axiom",
                "F",
                "--rule",
                "F=F[+F]",
                "--rule",
                "F=F",
                "--iterations",
                "1",
            ],
            ["probability"],
        ),
        (["--kind", "fractal", "--grasp-branch", "nope"], ["unknown branch 'nope'"]),
        (["--from", "MISSING.yaml"], ["MISSING.yaml", "no such file"]),
        (
            ["--from", str(EXAMPLES / "two_branch.yaml"), "--kind", "fractal"],
            ["generator", "--kind explicit"],
        ),
    ],
)
def test_tree_errors(capsys, tmp_path, argv, fragments):
    out = tmp_path / "t.yaml"
    rc, _, err = run(capsys, "tree", *argv, "--out", out, "--mjcf", tmp_path / "t.xml")
    assert_user_error(rc, err, *fragments)
    assert list(tmp_path.iterdir()) == []


def test_tree_refuses_to_overwrite_without_force(capsys, tmp_path):
    out = tmp_path / "t.yaml"
    out.write_text("keep me")
    rc, _, err = run(capsys, "tree", "--kind", "fractal", "--depth", "0", "--out", out)
    assert_user_error(rc, err, str(out), "--force")
    assert out.read_text() == "keep me"
    rc, _, err = run(capsys, "tree", "--kind", "fractal", "--depth", "0", "--out", out, "--force")
    assert rc == 0 and len(load_tree(out).branches) == 1
    rc, _, err = run(capsys, "tree", "--kind", "fractal", "--out", tmp_path / "t.txt")
    assert_user_error(rc, err, ".yaml")


# ---- simulate -----------------------------------------------------------------------------------
def _check_against_reference(folder: Path, tol=1e-5):
    """Every CSV equals a plain-MuJoCo rollout with the recorded true parameters and force."""
    from treeinfer.sim import make_simulator
    from treeinfer.sim.reference import simulate_reference

    tree = load_tree(folder / "tree.yaml")
    tp = json.loads((folder / "true_params.json").read_text())
    # the simulator as `simulate` chose it (its step is accuracy-controlled on these profiles)
    recorded = json.loads((folder / "config.json").read_text())["simulation"]
    sim = make_simulator(
        tree, 0.01, substeps=recorded["substeps"], force_interp=recorded["force_interp"]
    )
    kp = [tp["kp"][n] for n in tree.inferred]
    kd = [tp["kd"][n] for n in tree.inferred]
    for tr in read_trajectory_dir(folder):
        tau, tau_dot = simulate_reference(sim, kp, kd, tr.force)
        np.testing.assert_allclose(tr.displacement, tau, atol=tol)
        if tr.velocity is not None:
            np.testing.assert_allclose(tr.velocity, tau_dot, atol=100 * tol)
        assert np.abs(tau).max() > 0.01  # the pull really moved the branch


@pytest.fixture(scope="module")
def sim_a(tmp_path_factory):
    """One simulated data set (seed 1), shared by the tests below."""
    out = tmp_path_factory.mktemp("sim") / "a"
    rc = main(["simulate", "--tree", str(TWO), "--out", str(out), "--seed", "1", *SIM_ARGS])
    assert rc == 0
    return out


def test_simulate_writes_a_complete_data_set(sim_a, capsys):
    assert sorted(p.name for p in sim_a.iterdir()) == [
        ".treeinfer-output",
        "config.json",
        "manifest.json",  # every published folder lists its files' checksums (issue 28)
        "traj_000.csv",
        "traj_001.csv",
        "tree.yaml",
        "true_params.json",
    ]
    trajs = read_trajectory_dir(sim_a)
    cfg = json.loads((sim_a / "config.json").read_text())
    assert (
        cfg["treeinfer_version"] == __version__
        and cfg["seed"] == 1
        and cfg["options"]["n_traj"] == 2
    )
    assert len(trajs) == 2
    for tr, spec in zip(trajs, cfg["profiles"]):
        assert tr.n_steps == 60 and tr.dt == pytest.approx(0.01)
        np.testing.assert_array_equal(tr.force, from_spec(spec, 0.6, 0.01))
        assert tr.velocity is not None
    tree = load_tree(sim_a / "tree.yaml")
    assert tree_to_dict(tree) == tree_to_dict(load_tree(TWO))
    # true parameters: labelled, consistent, inside the prior's middle third, parent >= child
    tp = json.loads((sim_a / "true_params.json").read_text())
    assert tp["labels"] == tree.parameter_labels()
    theta = np.array([tp["kp"][n] for n in tree.inferred] + [tp["kd"][n] for n in tree.inferred])
    np.testing.assert_allclose(np.exp(tp["theta_log"]), theta, rtol=1e-12)
    lo, hi = tree.bounds_array()
    u = np.log(theta / lo) / np.log(hi / lo)
    assert np.all((u >= 1 / 3) & (u <= 2 / 3))
    for parent, child in tree.inferred_pairs():
        r = tree.n_inferred
        assert theta[parent] >= theta[child] and theta[r + parent] >= theta[r + child]
    _check_against_reference(sim_a)


def test_simulate_same_seed_same_files_and_params_json_round_trip(sim_a, capsys, tmp_path):
    b = tmp_path / "b"
    rc, _, err = run(capsys, "simulate", "--tree", TWO, "--out", b, "--seed", "1", *SIM_ARGS)
    assert rc == 0, err
    for name in ("traj_000.csv", "traj_001.csv", "true_params.json"):
        assert (b / name).read_bytes() == (sim_a / name).read_bytes()
    # the written parameters fed back in (same seed -> same profiles), with noise on top
    c = tmp_path / "c"
    rc, _, err = run(
        capsys,
        "simulate",
        "--tree",
        sim_a / "tree.yaml",
        "--out",
        c,
        "--seed",
        "1",
        *SIM_ARGS,
        "--params-json",
        sim_a / "true_params.json",
        "--noise-force",
        "0.1",
        "--noise-displacement",
        "0.001",
    )
    assert rc == 0, err
    tp_a = json.loads((sim_a / "true_params.json").read_text())
    tp_c = json.loads((c / "true_params.json").read_text())
    assert tp_c["kp"] == tp_a["kp"] and tp_c["kd"] == tp_a["kd"]
    df, dx = [], []
    for name in ("traj_000.csv", "traj_001.csv"):
        clean, noisy = read_trajectory(sim_a / name), read_trajectory(c / name)
        assert noisy.velocity is None  # noisy displacement: readers differentiate it
        np.testing.assert_array_equal(noisy.time, clean.time)
        df.append(noisy.force - clean.force)
        dx.append(noisy.displacement - clean.displacement)
    # 120 draws each: the sample std is within 25% of sigma with overwhelming probability
    assert np.std(np.concatenate(df)) == pytest.approx(0.1, rel=0.25)
    assert np.std(np.concatenate(dx)) == pytest.approx(0.001, rel=0.25)


def test_simulate_explicit_params_and_profiles(capsys, tmp_path):
    d = tmp_path / "d"
    specs = ["hold:peak=5,ramp=0.2,hold=0.1,release=0.1", "step:peak=3,rise=0.1,start=0.1"]
    rc, out, err = run(
        capsys,
        "simulate",
        "--tree",
        TWO,
        "--out",
        d,
        "--duration",
        "0.6",
        "--dt",
        "0.01",
        "--params",
        "30,90,0.4,1.5",
        "--profile",
        specs[0],
        "--profile",
        specs[1],
    )
    assert rc == 0, err
    tp = json.loads((d / "true_params.json").read_text())
    assert tp["kp"] == {"child": 30.0, "parent": 90.0} and tp["kd"] == {"child": 0.4, "parent": 1.5}
    assert json.loads((d / "config.json").read_text())["profiles"] == specs
    assert "Kp[child]=30" in out
    _check_against_reference(d)


def test_simulate_unstable_is_a_clear_error_and_writes_nothing(capsys, tmp_path):
    d = tmp_path / "blown"
    rc, _, err = run(
        capsys,
        "simulate",
        "--tree",
        TWO,
        "--out",
        d,
        "--duration",
        "0.6",
        "--dt",
        "0.01",
        "--profile",
        "ramp:peak=5000,ramp=0.1",
        "--profile",
        "step:peak=3,rise=0.1",
    )
    assert_user_error(rc, err, "blew up", "traj_000.csv", "peak=5000")
    assert "traj_001" not in err
    assert list(tmp_path.iterdir()) == []  # no folder, no staging left-overs


@pytest.fixture
def bad_tree(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text(
        "name: x\nbranches:\n  - {name: a, parent: null, length: -1, radius: 0.01}\ngrasp: "
        "{branch: a}\n"
    )
    return p


@pytest.mark.parametrize(
    "extra, fragments",
    [
        (["--tree", "MISSING.yaml"], ["MISSING.yaml", "no such file"]),
        (
            ["--params", "1,2,3"],
            ["--params", "expected 4 numbers", "Kp[child], Kp[parent], Kd[child], Kd[parent]"],
        ),
        (["--params", "1,2,-3,4"], ["--params", "Kd[child]", "positive"]),
        (["--params", "1,2,0,4"], ["Kd[child]", "positive"]),
        (["--n-traj", "0"], ["--n-traj"]),
        (["--dt", "0"], ["--dt"]),
        (["--dt", "0.3"], ["--duration", "at least 3"]),
        (["--grasp-fraction", "1.5"], ["--grasp-fraction", "(0, 1]"]),
        (["--noise-force", "-1"], ["--noise-force"]),
        (["--peak-range", "5,1"], ["--peak-range"]),
        (["--profile", "ramp:peak=3"], ["missing key(s) ramp"]),
        (["--profile", "ramp:peak=3,ramp=1", "--n-traj", "2"], ["--n-traj 2", "1 --profile"]),
    ],
)
def test_simulate_bad_inputs(capsys, tmp_path, extra, fragments):
    out = tmp_path / "out"
    argv = ["simulate", "--out", out, "--duration", "0.6"]
    if "--tree" not in extra:
        argv += ["--tree", TWO]
    rc, _, err = run(capsys, *argv, *extra)
    assert_user_error(rc, err, *fragments)
    assert not out.exists()


def test_simulate_malformed_tree(capsys, tmp_path, bad_tree):
    rc, _, err = run(capsys, "simulate", "--tree", bad_tree, "--out", tmp_path / "out")
    assert_user_error(rc, err, str(bad_tree), "length")
    assert not (tmp_path / "out").exists()


def test_simulate_params_json_errors(capsys, tmp_path):
    p = tmp_path / "p.json"
    for content, fragment in [
        ("{", "invalid JSON"),
        ('{"kp": {"child": 1}, "kd": {"child": 1, "parent": 2}}', "missing ['parent']"),
        ('{"theta_log": [1, 2]}', "theta_log"),
        ('{"something": 1}', "'kp' and 'kd'"),
    ]:
        p.write_text(content)
        rc, _, err = run(
            capsys, "simulate", "--tree", TWO, "--out", tmp_path / "out", "--params-json", p
        )
        assert_user_error(rc, err, str(p), fragment)
    assert not (tmp_path / "out").exists()


def test_simulate_refuses_non_empty_out(capsys, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "old.csv").write_text("keep")
    rc, _, err = run(capsys, "simulate", "--tree", TWO, "--out", out, *SIM_ARGS)
    assert_user_error(rc, err, str(out), "--force")
    assert [p.name for p in out.iterdir()] == ["old.csv"] and (
        out / "old.csv"
    ).read_text() == "keep"


def test_default_true_params_order_and_window():
    """The default draw on a 3-joint chain, with a different prior box per joint: each value sits
    in the middle third of its own log box, and the fraction of the box decreases from the root
    to the tip (so with shared boxes parent >= child)."""
    from dataclasses import replace

    from treeinfer.tree.description import Bounds

    boxes = {
        "branch2": Bounds((1.0, 100.0), (0.1, 1.0)),
        "branch1": Bounds((2.0, 400.0), (0.05, 5.0)),
        "branch0": Bounds((5.0, 500.0), (0.2, 20.0)),
    }
    tree = replace(gen.chain(3, 0.5, 0.02), bounds=boxes)
    assert tree.inferred == ("branch2", "branch1", "branch0")  # tip first
    lo, hi = tree.bounds_array()
    for seed in range(5):
        kp, kd = default_true_params(tree, np.random.default_rng(seed))
        u = np.log(np.concatenate([kp, kd]) / lo) / np.log(hi / lo)
        assert np.all((u >= 1 / 3 - 1e-12) & (u <= 2 / 3 + 1e-12))
        assert np.all(np.diff(u[:3]) >= 0) and np.all(np.diff(u[3:]) >= 0)
    a = default_true_params(tree, np.random.default_rng(0))
    b = default_true_params(tree, np.random.default_rng(0))
    np.testing.assert_array_equal(np.concatenate(a), np.concatenate(b))
