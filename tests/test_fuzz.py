"""Property-based fuzzing of the tree loader and the command line with malformed input.

Every generated input must give either a correct load / a successful command, or a clear
user error (TreeFileError / exit code 2 with an ``error:`` line) — never another exception,
a traceback or a partial output. ``TREEINFER_FUZZ_EXAMPLES`` raises the example count for a
long fuzz run (see docs/troubleshooting.md, "Robustness tests")."""

from __future__ import annotations

import copy
import json
import math
import os
from pathlib import Path

import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from treeinfer.cli import main
from treeinfer.errors import TreeFileError
from treeinfer.examples import example_path
from treeinfer.tree.description import Tree, tree_from_dict

N = int(os.environ.get("TREEINFER_FUZZ_EXAMPLES", "150"))
FUZZ = settings(max_examples=N, deadline=None, suppress_health_check=list(HealthCheck))

BASE = yaml.safe_load(example_path("three_branch").read_text())

junk = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-10, 10),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=8),
    st.lists(st.floats(allow_nan=True), max_size=4),
    st.dictionaries(st.text(max_size=4), st.integers(), max_size=2),
)


def _paths(d, prefix=()):
    """Every (path to a value) in a nested dict/list."""
    out = [prefix]
    if isinstance(d, dict):
        for k, v in d.items():
            out += _paths(v, prefix + (k,))
    elif isinstance(d, list):
        for i, v in enumerate(d):
            out += _paths(v, prefix + (i,))
    return out


PATHS = _paths(BASE)[1:]


def _set(d, path, value):
    for k in path[:-1]:
        d = d[k]
    d[path[-1]] = value


def _delete(d, path):
    for k in path[:-1]:
        d = d[k]
    del d[path[-1]]


@FUZZ
@given(st.lists(st.tuples(st.sampled_from(PATHS), junk, st.booleans()), min_size=1, max_size=4))
def test_tree_loader_mutations(mutations):
    d = copy.deepcopy(BASE)
    for path, value, delete in mutations:
        try:
            if delete:
                _delete(d, path)
            else:
                _set(d, path, value)
        except (KeyError, IndexError, TypeError):
            continue  # an earlier mutation removed the container
    try:
        tree = tree_from_dict(d, source="fuzz.yaml")
    except TreeFileError as e:
        assert str(e).startswith("fuzz.yaml")
        return
    assert isinstance(tree, Tree)
    for b in tree.branches:
        assert b.length > 0 and b.radius > 0 and math.isfinite(b.angle_deg)
    assert 0 < tree.grasp_fraction <= 1


@FUZZ
@given(st.text(max_size=300))
def test_tree_loader_random_text(tmp_path_factory, text):
    path = Path(tmp_path_factory.mktemp("t")) / "tree.yaml"
    path.write_text(text, encoding="utf-8")
    from treeinfer.tree.description import load_tree

    try:
        load_tree(path)
    except TreeFileError as e:
        assert str(path) in str(e)


option_values = st.one_of(
    st.text(alphabet="0123456789-.,eEnaif", max_size=8),
    st.sampled_from(["0", "-1", "nan", "inf", "1e9", "0.5", "2", "1,2", "a", ""]),
)
TREE_OPTIONS = [
    "--depth",
    "--branching",
    "--length-ratio",
    "--fork-angles",
    "--base-length",
    "--base-radius",
    "--levels",
    "--grasp-fraction",
    "--kp-bounds",
    "--kd-bounds",
    "--n",
    "--lengths",
    "--radii",
    "--angles",
    "--lsystem-iterations",
    "--angle",
    "--step-length",
    "--seed",
]


@FUZZ
@given(
    st.sampled_from(["fractal", "chain", "lsystem"]),
    st.lists(st.tuples(st.sampled_from(TREE_OPTIONS), option_values), max_size=4),
)
def test_cli_tree_fuzz(tmp_path_factory, capsys, kind, options):
    out = Path(tmp_path_factory.mktemp("cli")) / "tree.yaml"
    argv = ["tree", "--kind", kind, "--out", str(out)]
    if kind == "lsystem":
        argv += ["--axiom", "F", "--rule", "F=F[+F]F"]
    for opt, val in options:
        argv.append(f"{opt}={val}")
    try:
        code = main(argv)
    except SystemExit as e:  # argparse rejects the option (exit 2, usage on stderr)
        code = e.code
    err = capsys.readouterr().err
    assert code in (0, 2), (argv, code, err)
    assert "Traceback" not in err
    if code == 0:
        from treeinfer.tree.description import load_tree

        load_tree(out)
    else:
        assert not out.exists()
        assert "error" in err


@FUZZ
@given(
    st.sampled_from(["infer", "predict", "evaluate", "simulate"]),
    st.lists(option_values, max_size=3),
)
def test_cli_missing_inputs_are_user_errors(tmp_path_factory, capsys, command, values):
    tmp = Path(tmp_path_factory.mktemp("cli"))
    args = {
        "infer": ["--tree", str(tmp / "nope.yaml"), "--data", str(tmp), "--out", str(tmp / "run")],
        "predict": [
            "--run",
            str(tmp / "norun"),
            "--force-csv",
            str(tmp / "f.csv"),
            "--out",
            str(tmp / "p"),
        ],
        "evaluate": ["--run", str(tmp / "norun"), "--data", str(tmp), "--out", str(tmp / "e")],
        "simulate": ["--tree", str(tmp / "nope.yaml"), "--out", str(tmp / "s")],
    }[command]
    extra = [f"--seed={v}" for v in values[:1]]
    try:
        code = main([command, *args, *extra])
    except SystemExit as e:
        code = e.code
    err = capsys.readouterr().err
    assert code == 2, (command, err)
    assert "Traceback" not in err
    assert not any(p.name in ("run", "p", "e", "s") for p in tmp.iterdir())


def test_json_and_yaml_loaders_agree(tmp_path):
    from treeinfer.tree.description import load_tree

    (tmp_path / "t.json").write_text(json.dumps(BASE))
    (tmp_path / "t.yaml").write_text(yaml.safe_dump(BASE))
    assert load_tree(tmp_path / "t.json") == load_tree(tmp_path / "t.yaml")
