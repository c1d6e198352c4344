"""Observation channels end to end on the command line (issue 30): simulate --channel, infer
(reads channels.yaml, infers each channel's noise), evaluate (a band per channel), suggest
--sensors. One short pull; about a minute on two cores."""

import json

import pytest

import treeinfer as ti
from treeinfer.cli import main


@pytest.mark.slow
def test_simulate_infer_evaluate_suggest_with_a_marker(tmp_path, capsys):
    tree = str(ti.example_path("two_branch"))
    common = ["--tree", tree, "--n-traj", "1", "--duration", "1.5", "--dt", "0.02", "--params",
              "40,80,0.3,0.8", "--noise-displacement", "2mm", "--channel",
              "position:child:0.5:xz:0.001"]  # fmt: skip
    assert main(["simulate", *common, "--out", str(tmp_path / "train")]) == 0
    assert main(["simulate", *common, "--seed", "5", "--out", str(tmp_path / "test")]) == 0
    assert (tmp_path / "train" / "channels.yaml").is_file()
    run = tmp_path / "run"
    rc = main(["infer", "--tree", tree, "--data", str(tmp_path / "train"), "--out", str(run)])
    assert rc == 0
    summary = json.loads((run / "summary.json").read_text())
    labels = (
        [row["label"] for row in summary["posterior"]]
        if isinstance(summary["posterior"], list)
        else list(summary["posterior"])
    )
    assert "sigma[position_child_0.5]" in str(labels)  # one noise scale for the sensor
    # the fit verdict checks the channel too (coverage, standardised residuals, lag-1)
    checked = summary["fit"]["measures"]["channels"]["position_child_0.5"]
    assert checked["band"] == "predictive" and checked["fraction_outside"] < 0.2
    assert abs(checked["ppc"]["lag1"]) < 0.5
    assert (run / "plots" / "channels_train.png").is_file()
    # predict: the recording's own channel (its folder's channels.yaml), then a new force
    pred = tmp_path / "pred"
    assert main(["predict", "--run", str(run), "--force-csv",
                 str(tmp_path / "test" / "traj_000.csv"), "--out", str(pred)]) == 0  # fmt: skip
    cfg = json.loads((pred / "config.json").read_text())
    (pc,) = cfg["channels"].values()
    assert pc["band"] == "predictive" and pc["pct_outside"] < 20.0
    assert (pred / "channels.png").is_file()
    prof = tmp_path / "prof"
    assert main(["predict", "--run", str(run), "--profile", "ramp:peak=3,ramp=0.5",
                 "--duration", "1", "--out", str(prof)]) == 0  # fmt: skip
    cfg = json.loads((prof / "config.json").read_text())
    assert cfg["channels"]["position_child_0.5"]["pct_outside"] is None  # nothing recorded
    text = (prof / "channels" / "position_child_0.5_prediction.csv").read_text().splitlines()
    assert text[0].startswith("time,x_recorded,x_mean,x_lower,x_upper,x_predictive_lower")
    assert len(text) == 1 + 50
    out = tmp_path / "eval"
    assert main(["evaluate", "--run", str(run), "--data", str(tmp_path / "test"), "--out",
                 str(out)]) == 0  # fmt: skip
    metrics = json.loads((out / "metrics.json").read_text())
    (cm,) = metrics["channels"].values()
    assert cm["band"] == "predictive" and cm["pct_outside"] < 20.0
    assert (out / "channels.png").is_file()
    assert (out / "channel_position_child_0.5_000_prediction.csv").is_file()
    assert main(["suggest", "--run", str(run), "--sensors", "--top", "3"]) == 0
    assert "best: " in capsys.readouterr().out
