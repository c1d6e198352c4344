"""The table of option names (issue 29, "one meaning per option name"): every option of every
command with its one meaning, the old spellings still accepted, and the markdown of
docs/cli.md, which tests/test_cli_options.py compares with what the parsers hold.

An option name used by more than one command has an entry in :data:`SHARED`: its meaning (with
its unit) and a pattern that the help text of every command using it must match, so that a
command cannot give the name another meaning or unit without the test saying so. An option of
one command only is described by its own help text.

Regenerate the docs table after changing an option: ``python -m treeinfer.cli.option_table``
prints the block between the markers of docs/cli.md.
"""

from __future__ import annotations

import argparse
from typing import NamedTuple


class Meaning(NamedTuple):
    """One shared option name: what it means (with its unit), and a regular expression that
    every command's ``METAVAR help`` of that option must match."""

    meaning: str
    pattern: str


SHARED: dict[str, Meaning] = {
    "--allow-large": Meaning("go past the size limit checked before any work", r"size limit"),
    "--allow-modified": Meaning(
        "use a run whose files changed since `infer` wrote them", r"files changed"
    ),
    "--backend": Meaning("simulator: auto, fused, pallas or mjx", r"simulator: 'auto'"),
    "--data": Meaning("folder of trajectory CSVs", r"folder of .*trajectory CSVs"),
    "--debug": Meaning("show full tracebacks on errors", r"tracebacks"),
    "--direction": Meaning(
        "direction of the pull: down | horizontal | X,Y,Z (import-bag: X,Y,Z in the pose frame)",
        r"X,Y,Z",
    ),
    "--dt": Meaning("time between samples, s", r"(^|\W)s(\W|$)"),
    "--duration": Meaning("length of a pull, s", r"(^|\W)s(\W|$)"),
    "--allow-poor-fit": Meaning(
        "exit 0 even if the fit checks judge the posterior a poor fit (exit code 4 otherwise)",
        r"poor fit",
    ),
    "--force": Meaning("replace (overwrite) existing output; takes no value", r"replace"),
    "--force-interp": Meaning(
        "force between samples: linear or hold (each sample held until the next)", r"'hold'"
    ),
    "--formats": Meaning("file formats of the figures: png, pdf, svg (default png)", r"png, pdf"),
    "--grasp-branch": Meaning("name of the grasped branch", r"grasped branch"),
    "--grasp-distance": Meaning("grasp point, m from the branch's joint", r"\bm\b"),
    "--grasp-fraction": Meaning(
        "grasp point, a fraction of the grasped branch's length in (0, 1]", r"\(0, 1\]"
    ),
    "--init": Meaning("how the initial particles are drawn", r"initial particles"),
    "--iterations": Meaning(
        "iterations of the sampler (or of its optimiser), >= 1", r"^N .*iterations, >= 1"
    ),
    "--likelihood": Meaning("noise model: gaussian, student_t, ar1 or boltzmann", r"gaussian"),
    "--max-sim-dt": Meaning(
        "upper bound on the simulation step, s", r"(^|\W)s, upper bound on the simulation step"
    ),
    "--model": Meaning("the user's own URDF/MJCF model file", r"URDF"),
    "--n-traj": Meaning("number of pulls (trajectories)", r"(pulls|trajectories)"),
    "--no-progress": Meaning("no progress bar", r"no progress bar"),
    "--noise-displacement": Meaning(
        "displacement noise std sigma_x, m: 0.002 or 2mm (cm, um); 'auto' where the command "
        "decides it from the data",
        r"m \(0\.002 or 2mm; cm, um\)",
    ),
    "--noise-force": Meaning(
        "noise std of the (recorded) force: N (0.05 or 0.05N; mN, kN), P% of the largest force "
        "(2%) or 'auto' (estimated from a recording); each command says which forms it uses",
        r"(?s)(\bN\b.*P%|P%.*\bN\b)",
    ),
    "--out": Meaning("where the command writes (a folder; a file for `tree`)", r"(folder|file)"),
    "--particles": Meaning(
        "number of posterior particles (draws, chains)", r"(particles|draws|chains)"
    ),
    "--peak-range": Meaning(
        "N, range of the random force profiles' peaks", r"N, range of the random peaks"
    ),
    "--profile": Meaning("force profile spec, e.g. 'ramp:peak=5,ramp=1'", r"profile spec"),
    "--profile-kind": Meaning(
        "kind of the random force profiles: mixed, ramp, hold, release, step", r"kind of .*random"
    ),
    "--reinit-stragglers": Meaning(
        "re-initialise stuck particles up to iteration N (0: off)", r"stuck particles"
    ),
    "--repair-inertia": Meaning(
        "repair links with zero or non-positive-definite inertia", r"inertia"
    ),
    "--run": Meaning("run folder written by `treeinfer infer`", r"run folder"),
    "--sampler": Meaning("the posterior sampler", r"sampler"),
    "--seed": Meaning("seed of everything random the command draws", r"seed"),
    "--sim-tolerance": Meaning(
        "accuracy target of the simulated displacement, m", r"^M m, accuracy target"
    ),
    "--tie-scale": Meaning(
        "softness of the stiffness tie: log-stiffness ~ Normal(tie, TAU)", r"Normal\(0, TAU\)"
    ),
    "--tree": Meaning("tree description (YAML/JSON)", r"tree description"),
}

# Shared names whose argparse type differs between commands, and why (the meaning is the same).
TYPE_EXCEPTIONS: dict[str, str] = {
    "--direction": "import-bag takes X,Y,Z in the pose frame only; tree and import-csv also "
    "down|horizontal",
    "--dt": "import-bag also takes 'source' (the slower stream's own interval)",
    "--tie-scale": "tree also takes 'none' (a hard tie)",
}

DOC_START = "<!-- option-table:start (python -m treeinfer.cli.option_table) -->"
DOC_END = "<!-- option-table:end -->"


def command_parsers() -> dict[str, argparse.ArgumentParser]:
    """Every command's parser, as ``treeinfer COMMAND`` builds it (imports every command)."""
    from .main import COMMANDS, build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return {name: sub.choices[name] for name in COMMANDS}


def option_uses(parsers=None) -> dict[str, dict[str, argparse.Action]]:
    """option name -> {command: its action}, without the hidden (deprecated) spellings and
    ``-h``/``--help``."""
    parsers = parsers or command_parsers()
    uses: dict[str, dict[str, argparse.Action]] = {}
    for cmd, p in parsers.items():
        for a in p._actions:
            if a.help == argparse.SUPPRESS:
                continue
            for s in a.option_strings:
                if s.startswith("--") and s != "--help":
                    uses.setdefault(s, {})[cmd] = a
    return dict(sorted(uses.items()))


def expanded_help(a: argparse.Action) -> str:
    """An action's help with argparse's ``%%`` and ``%(default)s`` expanded."""
    text = a.help or ""
    try:
        return text % {"default": a.default, "prog": ""}
    except (KeyError, TypeError, ValueError):
        return text.replace("%%", "%")


def value_of(a: argparse.Action) -> str:
    """What follows the option: its METAVAR, ``{choices}``, or "" for a flag."""
    if a.nargs == 0 or getattr(a, "shown_as_flag", False):
        return ""
    if isinstance(a.metavar, str):
        return a.metavar
    if a.choices:
        return "{" + ",".join(map(str, a.choices)) + "}"
    return a.dest.upper()


def help_text(a: argparse.Action) -> str:
    """``VALUE help``: what the shared patterns of :data:`SHARED` are matched against."""
    return f"{value_of(a)} {expanded_help(a)}".strip()


def _first_clause(text: str, width: int = 110) -> str:
    """The help up to its first "; " outside parentheses, at most ``width`` characters."""
    text, depth = " ".join(text.split()), 0
    for i, c in enumerate(text):
        depth += (c == "(") - (c == ")")
        if depth == 0 and text.startswith("; ", i):
            text = text[:i]
            break
    if len(text) > width:
        text = text[:width].rsplit(" ", 1)[0] + " ..."
    return text


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def markdown(parsers=None) -> str:
    """The block of docs/cli.md between :data:`DOC_START` and :data:`DOC_END`."""
    from .options import deprecated_options

    parsers = parsers or command_parsers()
    rows = ["| option | value | commands | meaning |", "|---|---|---|---|"]
    for name, by_cmd in option_uses(parsers).items():
        if name in SHARED:
            meaning = SHARED[name].meaning
        else:
            a = next(iter(by_cmd.values()))
            meaning = _first_clause(expanded_help(a))
        cmds = "all" if len(by_cmd) == len(parsers) else ", ".join(by_cmd)
        value = " / ".join(dict.fromkeys(value_of(a) for a in by_cmd.values()))
        rows.append(f"| `{name}` | {_cell(value)} | {cmds} | {_cell(meaning)} |")
    old = ["", "Old spellings, accepted for one release with a DeprecationWarning on stderr:", ""]
    old += ["| command | old | write instead | note |", "|---|---|---|---|"]
    for cmd, p in parsers.items():
        for o, (new, note) in sorted(deprecated_options(p).items()):
            old.append(f"| {cmd} | `{o}` | `{new}` | {_cell(note)} |")
    old.append(
        "| predict | `--force FILE` | `--force-csv FILE` | `--force` alone means overwrite; "
        "a number after it is refused, saying what changed |"
    )
    return "\n".join([DOC_START, "", *rows, *old, "", DOC_END])


if __name__ == "__main__":
    print(markdown())
