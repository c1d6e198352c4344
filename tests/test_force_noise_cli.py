"""``treeinfer infer --likelihood gaussian --noise-force`` end to end (in-process, tiny): the
option's record in the run folder, the predictive band of ``predict``/``evaluate`` carrying the
force-noise term, and clear errors for bad values."""

from __future__ import annotations

import contextlib
import io
import json
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
def data(tmp_path_factory, demo_quick):
    """demo --quick data with 2 mm displacement and 2% (of the largest peak) force noise."""
    base = tmp_path_factory.mktemp("fnoise")
    # noise-free pulls of the session's demo (the paper's loss; the demo's default adds 2 mm
    # itself): tests/conftest.py
    demo = demo_quick[0]
    rng = np.random.default_rng(0)
    sets = {s: read_trajectory_dir(demo / "data" / s) for s in ("train", "test")}
    sf = 0.02 * max(np.abs(t.force).max() for ts in sets.values() for t in ts)
    for sub, trajs in sets.items():
        (base / sub).mkdir()
        for t in trajs:
            noisy = add_noise(t._replace(velocity=None), sf, SIGMA, rng)
            write_trajectory(base / sub / t.source, noisy._replace(source=t.source))
    shutil.copy(demo / "data" / "train" / "true_params.json", base / "train")
    return base, sf


def test_infer_predict_evaluate_with_noise_force(data, tmp_path):
    base, sf = data
    out = tmp_path / "run"
    rc, stdout, err = _main(
        "infer",
        "--tree",
        TWO,
        "--data",
        base / "train",
        "--out",
        out,
        "--likelihood",
        "gaussian",
        "--noise-force",
        "auto",
        *QUICK,
    )
    assert rc == 0, err
    assert "errors-in-variables force noise sigma_F" in stdout + err
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["options"]["noise_force"] == "auto"
    assert cfg["problem"]["noise_force"] == pytest.approx(sf, rel=0.35)
    ref = np.asarray(cfg["problem"]["noise_force_reference"])
    from treeinfer.inference.screen_points import SCREEN_TAIL_SDS
    from treeinfer.model.prior_terms import DEFAULT_PRIOR_SIGMA
    from treeinfer.tree.description import load_tree

    lo, hi = np.log(load_tree(TWO).bounds_array())
    # the MAP, inside the prior's range: the box and its smoothed tails as far as the screen looks
    tail = SCREEN_TAIL_SDS * DEFAULT_PRIOR_SIGMA * (hi - lo)
    assert ref.shape == (4,) and np.all((ref >= lo - tail) & (ref <= hi + tail))

    test_csv = sorted((base / "test").glob("*.csv"))[0]
    rc, stdout, err = _main(
        "predict", "--run", out, "--force-csv", test_csv, "--out", tmp_path / "p"
    )
    assert rc == 0, err
    pc = json.loads((tmp_path / "p" / "config.json").read_text())
    assert pc["band_includes_force_noise"] is True and "force-noise term" in pc["band"]
    rc, stdout, err = _main(
        "evaluate", "--run", out, "--data", base / "test", "--out", tmp_path / "e"
    )
    assert rc == 0, err
    m = json.loads((tmp_path / "e" / "metrics.json").read_text())["metrics"]
    assert m["band"] == "predictive" and m["band_includes_force_noise"] is True
    # the README's step 6 on a run of the default (generative) likelihood, whose particles
    # carry a noise column after the gains (it exited 2: "theta: expected [P, 4], got (P, 5)")
    rc, stdout, err = _main(
        "suggest", "--run", out, "--grasp-fractions", "1.0", "--peak-forces", "2",
        "--particles", "4", "--out", tmp_path / "s",
    )  # fmt: skip
    assert rc == 0, err
    assert (tmp_path / "s" / "suggestions.json").is_file()


@pytest.mark.parametrize(
    "extra, fragment",
    [
        (["--likelihood", "gaussian", "--noise-force", "-0.1"], "--noise-force"),
        (["--likelihood", "gaussian", "--noise-force", "nan"], "--noise-force"),
        (["--likelihood", "gaussian", "--noise-force", "150%"], "--noise-force"),
        (["--likelihood", "gaussian", "--noise-force", "500"], "noise_force"),  # above every force
        (["--likelihood", "student_t", "--noise-force", "0.1"], "--noise-force"),
        (["--likelihood", "boltzmann", "--noise-force", "0.1"], "--noise-force"),
    ],
)
def test_bad_noise_force(data, tmp_path, extra, fragment):
    base, _ = data
    rc, _, err = _main(
        "infer", "--tree", TWO, "--data", base / "train", "--out", tmp_path / "bad", *extra, *QUICK
    )
    assert rc == 2 and fragment in err and "Traceback" not in err, err
