"""config.json is the RunConfig; a new run's tree and data are read once (issue 10)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from treeinfer.errors import ConfigError
from treeinfer.io.provenance import config_hash
from treeinfer.runs import RunConfig, infer_config, load_run_inputs, run_inference

FIXTURE = Path(__file__).resolve().parent / "fixtures" / "run_main_2026-11-22"
DATA = FIXTURE / "data"
TREE = DATA / "tree.yaml"
OPTIONS = dict(
    sampler="svgd",
    particles=4,
    iterations=2,
    kT=0.05,
    seed=0,
    eta=10.0,
    grasp_fraction=None,
    max_unstable_share=0.5,
    checkpoint_every=0,
)


@pytest.mark.parametrize("folder", ["run", "interrupted.partial"])
def test_old_config_json_round_trips_unchanged(folder):
    """A config.json written by main before RunConfig covered the whole file reads back and
    writes out key for key, so its resume hash is the one recorded."""
    recorded = json.loads((FIXTURE / folder / "config.json").read_text())
    cfg = RunConfig.from_json(recorded)
    assert cfg.to_json() == recorded
    assert config_hash(cfg.to_json()) == recorded["config_hash"]
    # typed access to the options and the record
    assert cfg.particles == recorded["options"]["particles"]
    assert cfg.likelihood == "boltzmann"  # not in the old options: the default
    assert "likelihood" not in cfg.to_json()["options"]  # ... and not written back
    assert cfg.problem == recorded["problem"] and cfg.tree_dict == recorded["tree_dict"]


def test_new_config_round_trips_and_refuses_bad_fields(tmp_path):
    inputs = load_run_inputs(TREE, DATA)
    cfg = infer_config(TREE, DATA, tmp_path / "run", inputs=inputs, **OPTIONS)
    assert cfg["options"]["particles"] == 4 and cfg["seed"] == 0
    assert [f["name"] for f in cfg["data"]["files"]] == ["traj_000.csv", "traj_001.csv"]
    again = RunConfig.from_json(json.loads(json.dumps(cfg)))
    assert again.to_json() == cfg
    with pytest.raises(ConfigError, match="unknown field"):
        RunConfig.from_json({**cfg, "options": {**cfg["options"], "partciles": 3}})
    with pytest.raises(ConfigError, match="--particles"):
        RunConfig.from_json({**cfg, "options": {**cfg["options"], "particles": 1}})
    with pytest.raises(ConfigError, match="missing"):
        RunConfig.from_json({**cfg, "options": {"sampler": "svgd"}})


def test_inputs_read_once_are_passed_through_and_checked(tmp_path):
    """infer_config and run_inference share one RunInputs; inputs that are not the config's
    (another tree) are refused before anything is built."""
    inputs = load_run_inputs(TREE, DATA)
    assert len(inputs.trajectories) == 2 and inputs.truth is not None
    cfg = infer_config(TREE, DATA, tmp_path / "run", inputs=inputs, **OPTIONS)
    other = load_run_inputs(FIXTURE / "run" / "tree.yaml", DATA)
    other = other._replace(tree=dataclasses.replace(other.tree, name="x"))
    with pytest.raises(ConfigError, match="inputs' tree"):
        run_inference(cfg, inputs=other, progress=False)


def test_shape_buckets_option_is_validated_and_written_only_when_not_default():
    base = dict(tree="t.yaml", data="d", out="o")
    with pytest.raises(ConfigError, match="--shape-buckets"):
        RunConfig(**base, shape_buckets="maybe")
    assert "shape_buckets" not in RunConfig(**base).options_json()  # old run hashes unchanged
    assert RunConfig(**base, shape_buckets="off").options_json()["shape_buckets"] == "off"
