"""`treeinfer COMMAND --help` is short and grouped (issue 26): the common options come first and
fit a screen; every other option sits under the "expert options" heading; nothing is lost."""

from __future__ import annotations

import argparse
import re

import pytest

from treeinfer.cli.common import COMMON_OPTIONS, EXPERT_HEADING, group_options
from treeinfer.cli.main import COMMANDS, build_parser, main

COMMON_BUDGET = 60  # lines from "usage:" to the end of the common options


def _help(capsys, name: str) -> str:
    assert main([name, "--help"]) == 0
    return capsys.readouterr().out


def _sections(text: str) -> dict[str, list[str]]:
    """Help text cut at argparse's group headings (a line ``title:`` at column 0 that is
    followed by indented option lines)."""
    sections: dict[str, list[str]] = {"": []}
    current = ""
    for line in text.splitlines():
        if re.fullmatch(r"[a-z][^:]*:", line):
            current = line[:-1]
            sections[current] = []
        else:
            sections[current].append(line)
    return sections


def _options_in(lines: list[str]) -> set[str]:
    """Option strings an option line names, aliases included (``--time COL, --time-column COL``:
    the part of the line before its help text)."""
    heads = [re.split(r"\s{2,}", line.strip())[0] for line in lines if re.match(r"  -", line)]
    return {m for head in heads for m in re.findall(r"--[\w-]+", head)}


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_common_part_fits_the_budget(capsys, name):
    text = _help(capsys, name).splitlines()
    start = next(i for i, line in enumerate(text) if line == "common options:")
    end = next(
        (i for i in range(start + 1, len(text)) if re.fullmatch(r"[a-z][^:]*:", text[i])),
        len(text),
    )
    assert end <= COMMON_BUDGET, f"{name} --help: the common part takes {end} lines"


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_expert_options_are_under_their_heading(capsys, name):
    sections = _sections(_help(capsys, name))
    common = _options_in(sections["common options"])
    parser = build_parser(name)
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    chosen = {  # the listed options with their aliases (import-csv's --time, --time-column)
        s for a in sub.choices[name]._actions if set(a.option_strings) & set(COMMON_OPTIONS[name])
        for s in a.option_strings
    }  # fmt: skip
    assert common <= chosen | {"--help", "--debug"}, name
    every = {  # hidden: the deprecated spellings (treeinfer.cli.options.add_deprecated)
        s for a in sub.choices[name]._actions for s in a.option_strings
        if s.startswith("--") and s != "--help"  # "-h, --help" opens the common options
        and a.help != argparse.SUPPRESS
    }  # fmt: skip
    shown = set().union(*(_options_in(lines) for lines in sections.values()))
    assert every <= shown, f"{name} --help hides {sorted(every - shown)}"
    rest = every - common - {"--debug"}
    grouped = {
        o for title, lines in sections.items() if title not in ("", "common options")
        for o in _options_in(lines)
    }  # fmt: skip
    assert rest <= grouped, f"{name}: {sorted(rest - grouped)} listed with the common options"
    if name == "infer":  # the command with the most options keeps its experts' ones apart
        expert = _options_in(sections[EXPERT_HEADING])
        assert {"--kT", "--backend", "--gradients", "--mcmc-thin", "--shape-buckets"} <= expert


def test_usage_lists_the_common_options_only(capsys):
    text = _help(capsys, "infer")
    usage = text.split("\n\n")[0]
    assert "--tree" in usage and "[expert options]" in usage
    assert "--mcmc-thin" not in usage and "--shape-buckets" not in usage


def test_grouping_keeps_parsing_unchanged():
    """An expert option still parses, with its default, after being moved under the heading."""
    p = argparse.ArgumentParser(prog="x")
    p.add_argument("--a", type=int, default=1)
    p.add_argument("--b", type=int, default=2)
    group_options(p, ["--a"])
    args = p.parse_args(["--b", "5"])
    assert (args.a, args.b) == (1, 5)
    assert "expert options:" in p.format_help()


def test_a_misspelt_common_option_is_refused():
    p = argparse.ArgumentParser(prog="x")
    p.add_argument("--a")
    with pytest.raises(ValueError, match="--bogus"):
        group_options(p, ["--bogus"])
