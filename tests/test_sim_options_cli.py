"""The simulation options on the command line: --force-interp, --max-sim-dt, --sim-tolerance."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from treeinfer import runs
from treeinfer.cli import main
from treeinfer.errors import ConfigError

ROOT = Path(__file__).resolve().parent.parent
TWO = ROOT / "treeinfer" / "examples" / "two_branch.yaml"
COMMANDS = ("infer", "predict", "evaluate", "demo", "simulate")


def run(capsys, *argv):
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


@pytest.mark.parametrize("command", COMMANDS)
def test_every_simulating_command_has_the_options(capsys, command):
    rc, out, _ = run(capsys, command, "--help")
    assert rc == 0
    for flag in ("--force-interp", "--max-sim-dt", "--sim-tolerance"):
        assert flag in out, (command, flag)


@pytest.mark.parametrize(
    "args, flag",
    [
        (["--sim-tolerance", "-1"], "--sim-tolerance"),
        (["--max-sim-dt", "0"], "--max-sim-dt"),
    ],
)
def test_bad_values_name_the_flag(capsys, tmp_path, args, flag):
    rc, _, err = run(capsys, "simulate", "--tree", TWO, "--out", tmp_path / "d", *args)
    assert rc == 2 and flag in err and "Traceback" not in err, err
    with pytest.raises(ConfigError, match="--force-interp"):
        runs.RunConfig(tree="", data="", out="", force_interp="cubic")
    with pytest.raises(ConfigError, match="--sim-tolerance"):
        runs.RunConfig(tree="", data="", out="", sim_tolerance=0.0)


def test_simulate_records_the_step_it_chose(capsys, tmp_path):
    """The step is accuracy-controlled on the profiles; a looser tolerance takes fewer
    substeps; the chosen step, its estimate and the force convention reach config.json and
    the output."""
    common = ["simulate", "--tree", TWO, "--n-traj", "2", "--duration", "0.6", "--seed", "3"]
    sims = {}
    for tol in ("1e-3", "1e-4"):
        out = tmp_path / tol
        rc, stdout, err = run(
            capsys, *common, "--out", out, "--sim-tolerance", tol, "--force-interp", "hold"
        )
        assert rc == 0, err
        assert "estimated displacement error" in stdout + err
        sims[tol] = json.loads((out / "config.json").read_text())["simulation"]
    for tol, s in sims.items():
        assert s["force_interp"] == "hold" and s["step_method"] == "accuracy"
        assert s["sim_tolerance_m"] == float(tol) and s["estimated_error_m"] <= float(tol)
    assert sims["1e-3"]["substeps"] < sims["1e-4"]["substeps"]
