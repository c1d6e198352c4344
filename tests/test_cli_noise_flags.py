"""Bad noise settings on every command that takes them (issue 27, "Bad input"): negative,
non-finite or larger than the data's range gives exit 2 and a message naming the flag. All
refused before any sampling (a few seconds each)."""

from __future__ import annotations

import contextlib
import io

import numpy as np
import pytest

from treeinfer.cli import main
from treeinfer.data.trajectories import Trajectory, write_trajectory
from treeinfer.examples import example_path

TREE = example_path("two_branch")


def _main(*argv):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main([str(a) for a in argv])
    return rc, out.getvalue() + err.getvalue()


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """Two smooth pulls with 1 mm noise, 5 cm range, up to 4 N."""
    d = tmp_path_factory.mktemp("data")
    rng = np.random.default_rng(0)
    t = np.arange(200) * 0.01
    for b in range(2):
        f = 4.0 * np.clip(t / 0.5, 0, 1)
        x = 0.05 * (1 - np.exp(-4 * t)) + 1e-3 * rng.standard_normal(t.shape)
        x[0] = 0.0
        write_trajectory(d / f"p{b}.csv", Trajectory(t, f, x, None, None))
    return d


BAD = ["-0.001", "nan", "inf"]


@pytest.mark.parametrize(
    "flag, value",
    [(f, v) for f in ("--noise-displacement", "--noise-force", "--noise-velocity") for v in BAD]
    # above the data's range (5 cm) / the largest recorded force (4 N); a velocity's range is
    # checked only where a velocity column was recorded (this data set has none)
    + [("--noise-displacement", "0.5"), ("--noise-force", "50")],
)
def test_infer_refuses_bad_noise(tmp_path, data, flag, value):
    rc, text = _main(
        "infer", "--tree", TREE, "--data", data, "--out", tmp_path / "r",
        "--likelihood", "gaussian", flag, value, "--iterations", "1", "--particles", "2",
    )  # fmt: skip
    assert rc == 2, text
    assert flag in text, text


@pytest.mark.parametrize("value", BAD + ["5"])
@pytest.mark.parametrize("flag", ["--noise-displacement", "--noise-force"])
def test_simulate_refuses_bad_noise(tmp_path, flag, value):
    if flag == "--noise-force" and value == "5":
        value = "500"  # above the largest force of the profiles (peak range 2-8 N)
    rc, text = _main(
        "simulate", "--tree", TREE, "--out", tmp_path / "s", "--n-traj", "1",
        "--duration", "0.5", flag, value,
    )  # fmt: skip
    assert rc == 2, text
    assert flag in text, text
    if value in ("5", "500"):
        assert "larger than" in text


@pytest.mark.parametrize("value", BAD + ["10"])
def test_demo_and_calibrate_refuse_bad_noise(tmp_path, value):
    rc, text = _main(
        "demo", "--quick", "--out", tmp_path / "d", "--noise-displacement", value, "--no-progress"
    )
    assert rc == 2 and "--noise-displacement" in text, text
    rc, text = _main(
        "calibrate", "--tree", TREE, "--out", tmp_path / "c", "--datasets", "2",
        "--noise-displacement", value,
    )  # fmt: skip
    assert rc == 2 and "--noise-displacement" in text, text


def test_too_short_recording_names_the_flag(tmp_path):
    d = tmp_path / "short"
    d.mkdir()
    t = np.arange(12) * 0.01
    x = 0.01 * t + 1e-4 * np.random.default_rng(1).standard_normal(t.shape)
    x[0] = 0.0
    write_trajectory(d / "a.csv", Trajectory(t, 2.0 * np.ones_like(t), x, None, None))
    rc, text = _main(
        "infer", "--tree", TREE, "--data", d, "--out", tmp_path / "r", "--likelihood",
        "gaussian", "--noise-force", "auto", "--iterations", "1", "--particles", "2",
    )  # fmt: skip
    assert rc == 2 and "too short" in text and "--noise-force" in text, text
