"""The safe YAML/JSON loader and the tree checks built on it (issue 14, items 1-2)."""

from __future__ import annotations

import os
import threading

import pytest
import yaml

from treeinfer.errors import ConfigError, TreeFileError
from treeinfer.examples import example_path
from treeinfer.io.safe_load import (
    boolean,
    load_file,
    loads_json,
    loads_yaml,
    number,
    read_regular_file,
    string,
)
from treeinfer.tree.description import load_tree, tree_from_dict, tree_scale_warnings

BASE = yaml.safe_load(example_path("two_branch").read_text())


def _bomb(levels: int = 9, width: int = 9) -> str:
    """The classic 'billion laughs' document: ``width ** levels`` leaves from ~350 bytes."""
    lines = ["a0: &a0 [" + ", ".join(['"lol"'] * width) + "]"]
    for i in range(1, levels):
        lines.append(f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * width) + "]")
    return "\n".join(lines) + "\n"


def test_alias_bomb_is_refused_fast():
    text = _bomb()
    assert len(text) < 2000
    # refused before expansion: expanding would build 9**9 leaves (gigabytes), so reaching the
    # error at all shows the check ran first (no timed assertion: a loaded CI box varies 10x)
    with pytest.raises(ConfigError, match="alias bomb"):
        loads_yaml(text, "bomb.yaml")
    # a few honest aliases are fine and expand as PyYAML's would
    ok = "d: &d [1, 2]\ne: *d\n"
    assert loads_yaml(ok, "ok.yaml") == yaml.safe_load(ok)


def test_alias_count_limit_and_recursive_alias():
    text = "a: &a 1\nb: [" + ", ".join(["*a"] * 20) + "]\n"
    with pytest.raises(ConfigError, match="more than 10 aliases"):
        loads_yaml(text, "x.yaml", max_aliases=10)
    with pytest.raises(ConfigError, match="contains itself"):
        loads_yaml("a: &a [*a]\n", "x.yaml")


@pytest.mark.parametrize(
    "deep", ["[" * 100_000, "a:\n" + "".join(" " * i + "b:\n" for i in range(1, 200))]
)
def test_deep_yaml_is_a_clean_error(deep):
    with pytest.raises(ConfigError, match="deeper than 64"):
        loads_yaml(deep, "deep.yaml")


def test_deep_json_is_a_clean_error():
    with pytest.raises(ConfigError, match=r"deep.json, line 1: nested deeper"):
        loads_json("[" * 100_000 + "]" * 100_000, "deep.json")
    # brackets inside strings do not count
    assert loads_json('{"a": "' + "[" * 500 + '"}', "s.json") == {"a": "[" * 500}


def test_duplicate_keys_name_the_line():
    with pytest.raises(
        ConfigError, match=r"t.yaml, line 3: .*duplicate key 'b' \(first at line 2\)"
    ):
        loads_yaml("a: 1\nb: 2\nb: 3\n", "t.yaml")
    with pytest.raises(ConfigError, match=r"t.json, line 3: duplicate key 'b'"):
        loads_json('{"a": 1,\n "b": 2,\n "b": 3}', "t.json")
    # the same key in two different mappings is fine
    assert loads_json('{"x": {"b": 1}, "y": {"b": 2}}') == {"x": {"b": 1}, "y": {"b": 2}}


def test_json_nan_literal_refused():
    with pytest.raises(ConfigError, match="NaN"):
        loads_json('{"kT": NaN}', "c.json")


def test_typed_field_helpers():
    with pytest.raises(ConfigError, match="length: expected a number, got True .*booleans"):
        number(True, "length", "t.yaml")
    with pytest.raises(ConfigError, match="expected a number, got None"):
        number(None, "kT", "c.json")
    with pytest.raises(ConfigError, match="expected a number, got '0.05'"):
        number("0.05", "kT", "c.json")
    assert number(3, "x") == 3.0
    with pytest.raises(ConfigError, match="name: expected a name.*got None"):
        string(None, "name", "t.yaml")
    assert string(12, "name") == "12"
    with pytest.raises(ConfigError, match="expected true or false"):
        boolean(1, "fixed")


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_fifo_refused_without_blocking(tmp_path):
    fifo = tmp_path / "tree.yaml"
    os.mkfifo(fifo)
    out: list = []

    def go():
        try:
            load_tree(fifo)
        except TreeFileError as e:
            out.append(str(e))

    th = threading.Thread(target=go, daemon=True)
    th.start()
    th.join(5.0)
    assert not th.is_alive(), "loading a FIFO blocked"
    assert out and "FIFO" in out[0] and str(fifo) in out[0]


@pytest.mark.parametrize("path", ["/dev/zero", "/dev/null"])
def test_devices_refused(path):
    if not os.path.exists(path):
        pytest.skip(f"no {path}")
    with pytest.raises(TreeFileError, match="character device"):
        load_tree(path)


def test_folder_broken_link_and_size_limit(tmp_path):
    with pytest.raises(ConfigError, match="is a folder"):
        read_regular_file(tmp_path, "run config")
    link = tmp_path / "gone.yaml"
    link.symlink_to(tmp_path / "missing.yaml")
    with pytest.raises(ConfigError, match="broken symbolic link"):
        read_regular_file(link)
    big = tmp_path / "big.json"
    big.write_text("[" + "0," * 1000 + "0]")
    with pytest.raises(ConfigError, match="limit of 100 bytes"):
        load_file(big, max_bytes=100)


def _tree_yaml(tmp_path, text: str):
    p = tmp_path / "t.yaml"
    p.write_text(text)
    return p


def test_tree_yaml_bool_and_null_fields(tmp_path):
    text = yaml.safe_dump(BASE, sort_keys=False)
    p = _tree_yaml(tmp_path, text.replace("length: 0.6", "length: yes", 1))
    with pytest.raises(
        TreeFileError,
        match=r"t.yaml: branches\[1\] \('child'\): length: expected a "
        r"positive number, got True",
    ):
        load_tree(p)
    p = _tree_yaml(tmp_path, text.replace("name: child", "name: null", 1))
    with pytest.raises(
        TreeFileError, match=r"branches\[1\].name: expected a name \(text\), got None"
    ):
        load_tree(p)


def test_tree_duplicate_key(tmp_path):
    text = yaml.safe_dump(BASE, sort_keys=False).replace(
        "  length: 0.6\n", "  length: 0.6\n  length: 0.9\n", 1
    )
    with pytest.raises(TreeFileError, match=r"t.yaml, line \d+: .*duplicate key 'length'"):
        load_tree(_tree_yaml(tmp_path, text))


def _with_branch(**changes):
    d = yaml.safe_load(yaml.safe_dump(BASE))
    d["branches"][1].update(changes)
    return d


@pytest.mark.parametrize(
    "changes, pattern",
    [
        ({"density": 1e-12}, r"branches\[1\] \('child'\): density: 1e-12 kg/m\^3 is outside"),
        ({"radius": 1e-300}, r"branches\[1\] \('child'\): radius 1e-300 m is outside"),
        (
            {"length": 600.0, "radius": 0.02},
            r"length 600 m is longer than 50 m; looks like millimetres",
        ),
        ({"kp": 1e300}, r"kp: 1e\+300 N m/rad is outside the plausible range"),
    ],
)
def test_degenerate_branch_values(changes, pattern):
    with pytest.raises(TreeFileError, match=pattern):
        tree_from_dict(_with_branch(**changes), "t.yaml")


def test_absurd_prior_bounds_are_clean_errors():
    d = yaml.safe_load(yaml.safe_dump(BASE))
    d.setdefault("inference", {}).setdefault("prior", {})["kp"] = [1e-300, 1e300]
    with pytest.raises(
        TreeFileError, match=r"t.yaml: inference.prior.kp\[0\]: 1e-300 N m/rad is outside"
    ):
        tree_from_dict(d, "t.yaml")


def test_reserved_and_generated_names():
    d = _with_branch(name="world")
    with pytest.raises(TreeFileError, match="'world' is reserved"):
        tree_from_dict(d, "t.yaml")
    d = yaml.safe_load(yaml.safe_dump(BASE))
    d["branches"].append({"name": "child_geom", "parent": "child", "length": 0.2, "radius": 0.01})
    with pytest.raises(
        TreeFileError, match="'child_geom' clashes with the name generated for branch 'child'"
    ):
        tree_from_dict(d, "t.yaml")


def test_mass_floor_is_checked_independently_of_field_limits():
    # every field within its own limits, but the body is far lighter than MIN_MASS
    d = _with_branch(radius=1.0e-4, length=1.0e-3, density=1.0)
    d["branches"][1].pop("angle_deg", None)
    with pytest.raises(
        TreeFileError, match=r"\('child'\): mass .* below 1e-09 kg: a degenerate body"
    ):
        tree_from_dict(d, "t.yaml")


def test_scale_warnings():
    tree = tree_from_dict(_with_branch(length=8.0, radius=0.05), "t.yaml")
    w = tree_scale_warnings(tree, "t.yaml")
    assert len(w) == 1 and "length 8 m is unusually long" in w[0]
    assert tree_scale_warnings(tree_from_dict(BASE, "t.yaml")) == []


def test_list_data_files_names_what_it_skips(tmp_path):
    from treeinfer.io.safe_load import list_data_files

    (tmp_path / "b.csv").write_text("x")
    (tmp_path / "a.csv").write_text("x")
    (tmp_path / "UP.CSV").write_text("x")
    (tmp_path / "gone.csv").symlink_to(tmp_path / "missing.csv")
    (tmp_path / "dir.csv").mkdir()
    (tmp_path / "notes.txt").write_text("x")
    if hasattr(os, "mkfifo"):
        os.mkfifo(tmp_path / "pipe.csv")
    files, skipped = list_data_files(tmp_path)
    assert [p.name for p in files] == ["a.csv", "b.csv"]
    text = "\n".join(skipped)
    assert "UP.CSV: not read: the suffix must be '.csv' in lower case" in text
    assert "gone.csv: not read: broken symbolic link" in text
    assert "dir.csv: not read: it is a folder" in text
    if hasattr(os, "mkfifo"):
        assert "pipe.csv: not read: it is a FIFO" in text
    with pytest.raises(ConfigError, match="no such folder"):
        list_data_files(tmp_path / "nope")
