"""Issue 13's end-to-end path at tiny size: raw logger CSVs of a sideways push at three heights
-> import-csv -> infer (two heights, dynamic model, Gaussian noise) -> evaluate (the third).
The calibration figures come from ``experiments/sideways_push.py`` (results committed)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from experiments.sideways_push import HEIGHTS, run_pipeline  # noqa: E402
from treeinfer.data.direction import pull_direction  # noqa: E402
from treeinfer.runs import load_run  # noqa: E402
from treeinfer.sim import simulate  # noqa: E402


# A whole experiment (import-csv, a dynamic infer with MH, evaluate): about a minute on a
# 16-core machine, more on CI's 2 cores (tests over ~20 s are slow-marked). The
# default run keeps its parts: per-pull branch and direction against MuJoCo C
# (test_pull_direction), evaluate at each recording's own pull (test_cli_infer's grasp-point test,
# test_static_cli's held-out height), import-csv (test_csv_import).
@pytest.mark.slow
def test_sideways_push_three_heights_pipeline(tmp_path):
    result = run_pipeline(tmp_path, "tiny", seed=0)
    assert 0.0 <= result["pct_inside_predictive_95"] <= 100.0
    assert "sigma_x" in result["posterior"]
    config = json.loads((tmp_path / "run" / "config.json").read_text())
    problem = config["problem"]
    # MH from the Laplace start, its proposal shaped by the start's covariance (recorded:
    # a lower-triangular factor over Kp, Kd and sigma_x)
    assert config["options"]["init"] == "laplace"
    prop = np.asarray(config["sampler"]["options"]["proposal_scale"])
    assert prop.shape == (5, 5) and np.allclose(prop, np.tril(prop)) and np.all(np.diag(prop) > 0)
    # the two training heights, each at its own branch, point and horizontal direction
    assert problem["pulls"]["grasp_branch"] == ["branch0", "branch1"]
    assert problem["grasp_fraction"] == pytest.approx([0.6, 1.0])
    run = load_run(tmp_path / "run")
    for name, d in zip(("branch0", "branch1"), problem["pulls"]["direction"]):
        np.testing.assert_allclose(d, pull_direction(run.tree, "horizontal", name), atol=1e-9)
        assert abs(d[2]) < 1e-9  # horizontal

    # evaluate predicted the held-out middle height at its own pull (pulls.yaml), not at the
    # tree's grasp: its mean equals a direct simulation of the run's particles there
    (_, branch, frac) = HEIGHTS[1]
    csv = np.genfromtxt(tmp_path / "eval" / "push_mid_0_prediction.csv", delimiter=",", names=True)
    ok = run.stable
    kp = np.exp(run.theta[ok, :2])
    kd = np.exp(run.theta[ok, 2:4])
    d = pull_direction(run.tree, "horizontal", branch)
    own = simulate(run.sim, kp, kd, csv["force"][None], frac, direction=d, grasp_branch=branch)
    np.testing.assert_allclose(np.asarray(own.tau[:, 0]).mean(0), csv["mean"], atol=2e-4)
    tip = simulate(run.sim, kp, kd, csv["force"][None])  # the tree's grasp, pulled down
    assert np.max(np.abs(np.asarray(tip.tau[:, 0]).mean(0) - csv["mean"])) > 1e-3
