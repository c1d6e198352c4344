"""``treeinfer infer --likelihood gaussian / --kT auto`` and the predictive band in ``predict`` and
``evaluate`` (issue 11), in-process, on the ``demo --quick`` data with 2 mm displacement noise."""

from __future__ import annotations

import contextlib
import io
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from treeinfer.cli import main
from treeinfer.data.trajectories import add_noise, read_trajectory_dir, write_trajectory

ROOT = Path(__file__).resolve().parents[1]
TWO = ROOT / "treeinfer" / "examples" / "two_branch.yaml"
QUICK = [
    "--particles",
    "8",
    "--iterations",
    "3",
    "--checkpoint-every",
    "0",
    "--no-progress",
    "--allow-poor-fit",
]
SIGMA = 0.002


def _main(*argv):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main([str(a) for a in argv])
    return rc, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def noisy_data(tmp_path_factory, demo_quick):
    base = tmp_path_factory.mktemp("noise")
    # noise-free pulls of the session's demo (the paper's loss; the demo's default adds 2 mm
    # itself): tests/conftest.py
    demo = demo_quick[0]
    rng = np.random.default_rng(0)
    for sub in ("train", "test"):
        (base / sub).mkdir()
        for t in read_trajectory_dir(demo / "data" / sub):
            noisy = add_noise(t._replace(velocity=None), 0.0, SIGMA, rng)
            write_trajectory(base / sub / t.source, noisy._replace(source=t.source))
    shutil.copy(demo / "data" / "train" / "true_params.json", base / "train")
    return base


@pytest.fixture(scope="module")
def gaussian_run(noisy_data):
    out = noisy_data / "run_gauss"
    rc, stdout, err = _main(
        "infer",
        "--tree",
        TWO,
        "--data",
        noisy_data / "train",
        "--out",
        out,
        "--likelihood",
        "gaussian",
        *QUICK,
    )
    assert rc == 0, err
    return out, stdout + err


def test_infer_gaussian_run_folder(gaussian_run):
    out, text = gaussian_run
    assert "likelihood: Gaussian displacement noise, sigma_x inferred" in text
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["options"]["likelihood"] == "gaussian" and cfg["problem"]["noise_inferred"]
    with np.load(out / "trace.npz") as z:
        assert z["labels"].tolist()[-1] == "sigma_x" and z["theta"].shape == (8, 5)
    s = json.loads((out / "summary.json").read_text())
    assert s["posterior"]["sigma_x"]["unit"] == "m"
    assert set(s["truth"]) == {"Kp[child]", "Kp[parent]", "Kd[child]", "Kd[parent]"}
    assert s["training_metrics"]["band"] == "predictive"


def test_predict_and_evaluate_write_both_bands(gaussian_run, noisy_data, tmp_path):
    out, _ = gaussian_run
    test_csv = sorted((noisy_data / "test").glob("*.csv"))[0]
    rc, stdout, err = _main("predict", "--run", out, "--force", test_csv, "--out", tmp_path / "p")
    assert rc == 0, err
    lines = (tmp_path / "p" / "prediction.csv").read_text().splitlines()
    # header first (issue 13); the column names say which band is which
    cols = lines[0].split(",")
    assert cols == [
        "time",
        "force",
        "recorded",
        "mean",
        "lower",
        "upper",
        "predictive_lower",
        "predictive_upper",
    ]
    a = np.array([[float(c) if c else np.nan for c in r.split(",")] for r in lines[1:]])
    width_par, width_pred = a[:, 5] - a[:, 4], a[:, 7] - a[:, 6]
    assert np.all(width_pred >= width_par - 1e-9) and width_pred[0] > 0.001  # t = 0: the noise

    rc, stdout, err = _main(
        "evaluate", "--run", out, "--data", noisy_data / "test", "--out", tmp_path / "e"
    )
    assert rc == 0, err
    m = json.loads((tmp_path / "e" / "metrics.json").read_text())["metrics"]
    assert m["band"] == "predictive" and m["n_degenerate_points"] == 0
    assert math.isfinite(m["predictive_nll_per_point"])
    assert m["parameter_band"]["pct_outside"] > m["pct_outside"]


def test_infer_kT_auto(noisy_data, tmp_path):
    rc, stdout, err = _main(
        "infer",
        "--tree",
        TWO,
        "--data",
        noisy_data / "train",
        "--out",
        tmp_path / "r",
        "--kT",
        "auto",
        "--likelihood",
        "boltzmann",
        *QUICK,
    )
    assert rc == 0, err
    assert "kT auto = " in stdout + err and "sigma / sqrt(T)" in stdout + err
    cfg = json.loads((tmp_path / "r" / "config.json").read_text())
    assert cfg["options"]["kT"] == "auto" and cfg["problem"]["kT_auto"]
    assert cfg["problem"]["noise_displacement"] == pytest.approx(SIGMA, rel=0.3)
    assert cfg["problem"]["kT"] < 0.01


@pytest.mark.parametrize(
    "extra, fragment",
    [
        (["--likelihood", "gaussian", "--noise-displacement", "-0.002"], "--noise-displacement"),
        (["--likelihood", "gaussian", "--noise-displacement", "nan"], "--noise-displacement"),
        (["--likelihood", "gaussian", "--noise-displacement", "5"], "noise_displacement"),
        (["--kT", "warm"], "--kT"),
    ],
)
def test_bad_noise_options(noisy_data, tmp_path, extra, fragment):
    rc, _, err = _main(
        "infer",
        "--tree",
        TWO,
        "--data",
        noisy_data / "train",
        "--out",
        tmp_path / "bad",
        *extra,
        *QUICK,
    )
    assert rc == 2 and fragment in err and "Traceback" not in err, err
