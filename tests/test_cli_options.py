"""One meaning per option name, one spelling per quantity (issue 29): the table of every option
of every command (docs/cli.md) against the parsers, the shared names' meaning and units in every
command's help, the value parsers of --noise-force / --noise-displacement / --formats, and the
old spellings (accepted with a message naming the new one). Parsing only: no command runs past
its option checks, so the file takes seconds."""

from __future__ import annotations

import argparse
import contextlib
import io
import re
from pathlib import Path

import pytest

from treeinfer.cli import main
from treeinfer.cli.option_table import (
    DOC_END,
    DOC_START,
    SHARED,
    TYPE_EXCEPTIONS,
    command_parsers,
    help_text,
    markdown,
    option_uses,
)
from treeinfer.cli.options import (
    FIGURE_FORMATS,
    deprecated_options,
    displacement_noise,
    figure_formats,
    force_noise,
    length,
)
from treeinfer.examples import example_path

DOCS = Path(__file__).resolve().parents[1] / "docs" / "cli.md"
TREE = example_path("two_branch")


@pytest.fixture(scope="module")
def parsers():
    return command_parsers()


@pytest.fixture(scope="module")
def uses(parsers):
    return option_uses(parsers)


def _main(*argv):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main([str(a) for a in argv])
    return rc, out.getvalue(), err.getvalue()


# ---- the table ------------------------------------------------------------------------------
def test_every_shared_name_has_one_meaning(uses):
    """A name used by two commands is in the table, and every command's help of it says the
    table's meaning/unit (the pattern): a command cannot give it another meaning silently."""
    shared = {name for name, by in uses.items() if len(by) > 1}
    missing = shared - set(SHARED)
    assert not missing, f"options used by several commands with no SHARED entry: {missing}"
    stale = set(SHARED) - shared
    assert not stale, f"SHARED entries no longer shared by two commands: {stale}"
    for name in sorted(shared):
        for cmd, a in uses[name].items():
            assert re.search(SHARED[name].pattern, help_text(a)), (
                f"{cmd} {name}: help {help_text(a)!r} does not say the shared meaning "
                f"{SHARED[name].meaning!r}"
            )


def test_shared_names_parse_alike(uses):
    """The same argparse type (unit parser) and the same kind (flag or value) in every command,
    except the documented exceptions."""
    for name, by in uses.items():
        if len(by) < 2:
            continue
        kinds = {
            cmd: "flag" if a.nargs == 0 or getattr(a, "shown_as_flag", False) else "value"
            for cmd, a in by.items()
        }
        assert len(set(kinds.values())) == 1, f"{name}: {kinds}"
        if name not in TYPE_EXCEPTIONS:
            types = {cmd: getattr(a.type, "__name__", a.type) for cmd, a in by.items()}
            assert len(set(types.values())) == 1, f"{name} parses differently: {types}"


def test_force_means_overwrite_everywhere(uses):
    for cmd, a in uses["--force"].items():
        assert a.const is True and a.default in (False, None), cmd
        assert re.search(r"replace", a.help), cmd


def test_no_deprecated_name_is_also_a_live_option(parsers):
    """An old spelling must not be a current option of the same command (it would shadow it),
    and its replacement must exist there."""
    for cmd, p in parsers.items():
        live = {s for a in p._actions if a.help != argparse.SUPPRESS for s in a.option_strings}
        for old, (new, _) in deprecated_options(p).items():
            assert old not in live, (cmd, old)
            assert new in live, (cmd, new)


def test_docs_table_matches_the_parsers(parsers):
    text = DOCS.read_text()
    assert DOC_START in text and DOC_END in text, f"{DOCS}: the table's markers are missing"
    block = text[text.index(DOC_START) : text.index(DOC_END) + len(DOC_END)]
    assert block == markdown(parsers), (
        "docs/cli.md's option table is out of date: regenerate it with "
        "`python -m treeinfer.cli.option_table` (the block between the markers)"
    )


def test_figure_formats_match_the_plot_writer():
    from treeinfer.evaluation.plots import FIGURE_FORMATS as WRITER

    assert FIGURE_FORMATS == tuple(WRITER)


# ---- the value parsers ----------------------------------------------------------------------
@pytest.mark.parametrize(
    "text, value",
    [("0.05", 0.05), ("0.05N", 0.05), (" 0.05 N ", 0.05), ("50mN", 0.05), ("0.002kN", 2.0),
     ("1e-2", 0.01), ("2%", "2%"), ("2.50%", "2.5%"), ("0%", "0%"), ("auto", "auto"),
     ("AUTO", "auto"), ("0", 0.0)],
)  # fmt: skip
def test_force_noise_values(text, value):
    got = force_noise(text)
    assert got == pytest.approx(value) if isinstance(value, float) else got == value


@pytest.mark.parametrize(
    "text, message",
    [("-0.1", ">= 0"), ("nan", ">= 0"), ("inf", ">= 0"), ("100%", "below 100%"),
     ("2mm", "displacement unit"), ("0.05kg", "unknown force unit"), ("abc", "newtons"),
     ("", "newtons")],
)  # fmt: skip
def test_force_noise_refusals(text, message):
    with pytest.raises(argparse.ArgumentTypeError, match=re.escape(message)):
        force_noise(text)


@pytest.mark.parametrize(
    "text, value",
    [("0.002", 0.002), ("2mm", 0.002), ("0.2cm", 0.002), ("2000um", 0.002), ("2 mm", 0.002),
     ("0.002m", 0.002), ("auto", "auto")],
)  # fmt: skip
def test_displacement_noise_values(text, value):
    got = displacement_noise(text)
    assert got == pytest.approx(value) if isinstance(value, float) else got == value


@pytest.mark.parametrize(
    "text, message",
    [("-1mm", ">= 0"), ("2%", "not a length"), ("0.05N", "force unit"), ("2ft", "unknown length"),
     ("x", "metres")],
)  # fmt: skip
def test_displacement_noise_refusals(text, message):
    with pytest.raises(argparse.ArgumentTypeError, match=re.escape(message)):
        displacement_noise(text)


def test_length_has_no_auto():
    assert length("120mm") == pytest.approx(0.12)
    with pytest.raises(argparse.ArgumentTypeError, match="metres"):
        length("auto")


def test_figure_formats_values():
    assert figure_formats("png") == ("png",)
    assert figure_formats("PNG, pdf,svg,pdf") == ("png", "pdf", "svg")
    for bad in ("jpg", "", "png,gif"):
        with pytest.raises(argparse.ArgumentTypeError, match="png,pdf,svg"):
            figure_formats(bad)


# ---- the same spelling in every command (parsed, then refused or accepted by the command) -----
def _parse(parsers, cmd, *argv):
    return parsers[cmd].parse_args([str(a) for a in argv])


def test_noise_spellings_parse_alike_in_every_command(parsers):
    base = {
        "simulate": ["--tree", TREE, "--out", "x"],
        "infer": ["--tree", TREE, "--data", "d", "--out", "x"],
        "calibrate": ["--tree", TREE, "--out", "x"],
        "demo": [],
        "suggest": ["--run", "r"],
    }
    for cmd, argv in base.items():
        ns = _parse(parsers, cmd, *argv, "--noise-displacement", "2mm")
        dest = "sigma_x" if cmd == "suggest" else "noise_displacement"
        assert getattr(ns, dest) == pytest.approx(0.002), cmd
    for cmd in ("simulate", "infer", "calibrate"):
        for text, want in (("0.05N", 0.05), ("2%", "2%"), ("auto", "auto")):
            ns = _parse(parsers, cmd, *base[cmd], "--noise-force", text)
            assert ns.noise_force == (pytest.approx(want) if isinstance(want, float) else want)


@pytest.mark.parametrize(
    "argv, flag, words",
    [(["simulate", "--noise-force", "auto"], "--noise-force", "RECORDED"),
     (["simulate", "--noise-displacement", "auto"], "--noise-displacement", "metres"),
     (["calibrate", "--noise-force", "0.05N"], "--noise-force", "give a share"),
     (["calibrate", "--noise-force", "auto"], "--noise-force", "give a share"),
     (["demo", "--quick", "--noise-displacement", "auto"], "--noise-displacement", "metres")],
)  # fmt: skip
def test_a_form_a_command_cannot_use_is_refused_clearly(tmp_path, argv, flag, words):
    extra = {"simulate": ["--tree", TREE], "calibrate": ["--tree", TREE, "--datasets", "2"]}
    rc, out, err = _main(*argv, *extra.get(argv[0], []), "--out", tmp_path / "o")
    assert rc == 2, out + err
    assert flag in err and words in err, err
    assert not (tmp_path / "o").exists()


def test_simulate_percent_force_noise_is_a_share_of_the_largest_force(tmp_path):
    """`simulate --noise-force 2%` adds 2% of the largest force of the profiles, recorded in
    config.json in newtons, as `infer --noise-force 2%` reads it on the written data."""
    import json

    rc, out, err = _main(
        "simulate", "--tree", TREE, "--out", tmp_path / "s", "--n-traj", "1", "--duration",
        "0.3", "--dt", "0.02", "--profile", "ramp:peak=5,ramp=0.2", "--noise-force", "2%",
    )  # fmt: skip
    assert rc == 0, err
    cfg = json.loads((tmp_path / "s" / "config.json").read_text())
    assert cfg["options"]["noise_force"] == "2%"
    assert cfg["options"]["noise_force_N"] == pytest.approx(0.02 * 5.0)


# ---- old spellings ----------------------------------------------------------------------------
OLD = [  # command, old argv, new argv, (dest, value)
    ("tree", ["--iterations", "2"], ["--lsystem-iterations", "2"], ("iterations", 2)),
    ("tree", ["--grasp", "b1"], ["--grasp-branch", "b1"], ("grasp", "b1")),
    ("import-csv", ["a.csv", "--time", "ms"], ["a.csv", "--time-column", "ms"], ("time", "ms")),
    ("import-csv", ["a.csv", "--displacement", "x"], ["a.csv", "--displacement-column", "x"],
     ("displacement", "x")),
    ("import-bag", ["b.bag", "--displacement", "distance"],
     ["b.bag", "--displacement-mode", "distance"], ("displacement", "distance")),
    ("suggest", ["--run", "r", "--sigma-x", "0.002"],
     ["--run", "r", "--noise-displacement", "0.002"], ("sigma_x", 0.002)),
    ("warmup", ["--tree", "t", "--trajectories", "2"], ["--tree", "t", "--n-traj", "2"],
     ("trajectories", 2)),
    ("predict", ["--run", "r", "--out", "o", "--overwrite"], ["--run", "r", "--out", "o",
     "--force"], ("force_flag", True)),
    ("simulate", ["--tree", "t", "--out", "o", "--profiles", "step"],
     ["--tree", "t", "--out", "o", "--profile-kind", "step"], ("profiles", "step")),
]  # fmt: skip
_REQUIRED = {
    "tree": ["--out", "t.yaml"],
    "import-csv": ["--out", "d"],
    "import-bag": ["--out", "d"],
}


@pytest.mark.parametrize("cmd, old, new, dest_value", OLD)
def test_old_spelling_parses_as_the_new_with_a_message(parsers, capsys, cmd, old, new, dest_value):
    dest, value = dest_value
    extra = _REQUIRED.get(cmd, [])
    got_new = _parse(parsers, cmd, *new, *extra)
    assert capsys.readouterr().err == ""
    got_old = _parse(parsers, cmd, *old, *extra)
    err = capsys.readouterr().err
    assert getattr(got_old, dest) == getattr(got_new, dest) == value
    assert vars(got_old) == vars(got_new)
    old_flag = next(a for a in old if a.startswith("--") and a not in new)
    new_flag = next(a for a in new if a.startswith("--") and a not in old)
    assert "DeprecationWarning" in err and old_flag in err and new_flag in err, err


def test_tree_iterations_message_says_what_changed(capsys, parsers):
    _parse(parsers, "tree", "--iterations", "2", "--out", "t.yaml")
    err = capsys.readouterr().err
    assert "rewriting passes" in err and "sampler" in err, err


def test_predict_force_file_is_the_old_force_csv(parsers, capsys):
    ns = _parse(parsers, "predict", "--run", "r", "--out", "o", "--force", "pull.csv")
    err = capsys.readouterr().err
    assert ns.force_file == Path("pull.csv") and ns.force_flag is False
    assert "DeprecationWarning" in err and "--force-csv pull.csv" in err


@pytest.mark.parametrize("value", ["5", "5N", "2.5"])
def test_predict_force_with_a_number_is_refused_with_what_changed(tmp_path, value):
    rc, out, err = _main("predict", "--run", tmp_path, "--out", tmp_path / "o", "--force", value)
    assert rc == 2, out + err
    assert "means overwrite" in err and "--force-csv" in err and "--profile" in err, err


def test_predict_plain_force_is_overwrite(parsers):
    ns = _parse(parsers, "predict", "--run", "r", "--out", "o", "--force", "--profile", "x")
    assert ns.force_flag is True and ns.profile == "x" and ns.force_file is None


def test_tree_error_names_the_new_flag(tmp_path):
    rc, out, err = _main(
        "tree", "--kind", "chain", "--n", "2", "--lsystem-iterations", "2", "--out",
        tmp_path / "t.yaml",
    )  # fmt: skip
    assert rc == 2 and "--lsystem-iterations does not apply" in err, err


def test_noise_displacement_auto_is_the_default_where_there_is_one(tmp_path):
    """`suggest --noise-displacement auto` is the run's noise model (the default): the command
    goes on to read the run; 0 is refused naming the new flag."""
    rc, out, err = _main("suggest", "--run", tmp_path / "norun", "--noise-displacement", "auto")
    assert rc == 2 and "norun" in err and "--noise-displacement" not in err, err
    rc, out, err = _main("suggest", "--run", tmp_path / "norun", "--noise-displacement", "0")
    assert rc == 2 and "--noise-displacement: must be a positive number of metres" in err, err
