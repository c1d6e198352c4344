"""The ``treeinfer`` command line: the command table, the parser and ``main``.

Each command lives in its own module of :mod:`treeinfer.cli` (``tree``, ``simulate``,
``import_bag``, ``import_csv``, ``infer``, ``predict``, ``evaluate``, ``demo``, ``suggest``)
as a pair ``configure_<name>(subparsers) -> parser`` and ``run_<name>(args) -> exit code``;
those modules import what they need at their top and are imported only when their command runs, so
``treeinfer --help`` loads neither JAX nor MuJoCo. To add a command, write its module, add a
line to :data:`~treeinfer.cli.common.COMMAND_HELP` and an entry to :data:`COMMANDS`. Commands
parse and print; the work is done by the library (:mod:`treeinfer.sim.synthetic`,
:mod:`treeinfer.runs`, :mod:`treeinfer.evaluation.predictive`, ...).

Exit codes: 0 success; 2 a user error (a :class:`~treeinfer.errors.TreeinferError`, a file that
cannot be written, or a bad option: ``error: <message>`` on stderr, no traceback); 3 a bug in
treeinfer (a short message; ``--debug`` shows the traceback); 130 interrupted (Ctrl-C).
"""

from __future__ import annotations

import argparse
import importlib
import sys
import textwrap
import traceback
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

from .. import __version__
from ..errors import TreeinferError
from .common import (
    _WIDTH,
    COMMAND_HELP,
    COMMON_OPTIONS,
    EXIT_INTERNAL_ERROR,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_USER_ERROR,
    group_options,
)


class Command(NamedTuple):
    """A subcommand: ``configure(subparsers) -> parser`` and ``run(args) -> exit code``."""

    configure: Callable[[Any], argparse.ArgumentParser]
    run: Callable[[argparse.Namespace], int | None]


def _lazy(module: str, attr: str) -> Callable:
    """``treeinfer.cli.<module>.<attr>``, imported on the first call."""

    def call(*args, **kwargs):
        return getattr(importlib.import_module(f"{__package__}.{module}"), attr)(*args, **kwargs)

    call.__name__ = attr
    return call


def _command(module: str) -> Command:
    return Command(_lazy(module, f"configure_{module}"), _lazy(module, f"run_{module}"))


COMMANDS: dict[str, Command] = {
    "tree": _command("tree"),
    "simulate": _command("simulate"),
    "import-bag": _command("import_bag"),
    "import-csv": _command("import_csv"),
    "import-pul": _command("import_pul"),
    "infer": _command("infer"),
    "predict": _command("predict"),
    "evaluate": _command("evaluate"),
    "demo": _command("demo"),
    "suggest": _command("suggest"),
    "calibrate": _command("calibrate"),
    "warmup": _command("warmup"),
    "batch": _command("batch"),
    "amortise": _command("amortise"),
}

_MAIN_EPILOG = """\
a typical sim-to-sim session:
  treeinfer tree --kind fractal --depth 1 --base-pitch 10 --out tree.yaml
  treeinfer simulate --tree tree.yaml --out data/train --n-traj 8 --seed 1
  treeinfer simulate --tree tree.yaml --out data/test --n-traj 8 --seed 2 \\
      --params-json data/train/true_params.json
  treeinfer infer --tree tree.yaml --data data/train --out run
  treeinfer evaluate --run run --data data/test --out eval
  treeinfer predict --run run --force-csv data/test/traj_000.csv --out pred

or all of it on the built-in example: treeinfer demo

Run `treeinfer COMMAND --help` for a command's options and examples. Errors in your input are
reported in one line (exit code 2); add --debug to see the traceback.

exit codes: 0 success; 2 an error in your input (file, option, implausible data); 3 an internal
error (a bug: please report it); 4 `infer` finished but its fit checks judged the posterior a
poor fit (summary.json "fit"; --allow-poor-fit makes that exit 0); 5 `batch` finished but some
items failed (their errors are in its results table); 130 interrupted.
"""


def _command_of(argv: Sequence[str]) -> str | None:
    """The command named in ``argv`` (its first non-option word; the global options are flags)."""
    return next((a for a in argv if not a.startswith("-")), None)


def build_parser(only: str | None = None, lazy: bool = False) -> argparse.ArgumentParser:
    """The full parser; with ``lazy``, only command ``only`` gets its options (the others are
    listed with their one-line help, without importing their modules)."""
    parser = argparse.ArgumentParser(
        prog="treeinfer",
        description=textwrap.fill(
            "Infer the stiffness and damping of tree-branch joints from robot force-deformation "
            "trajectories, with a batched MuJoCo simulator in JAX (a fused hinge-tree step, or "
            "MJX).",
            width=_WIDTH,
        ),
        epilog=_MAIN_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"treeinfer {__version__}")
    parser.add_argument("--debug", action="store_true", help="show full tracebacks on errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", title="commands")
    sub.required = True
    for name, cmd in COMMANDS.items():
        if lazy and name != only:
            sub.add_parser(name, help=COMMAND_HELP[name], add_help=False)
            continue
        p = cmd.configure(sub)
        if p.prog.split()[-1] != name:  # the table's key is the command's name
            raise RuntimeError(f"COMMANDS['{name}'] configures a parser named '{p.prog}'")
        group_options(p, COMMON_OPTIONS[name])  # common options first, the rest under a heading
        p.set_defaults(_run=cmd.run)
    return parser


def _start_runtime() -> None:
    """What a command needs before it runs: a supported Python and dependency set (one clear
    message otherwise: :func:`treeinfer.cli.environment.check_environment`, exit 2) and JAX's
    runtime settings (:func:`treeinfer.configure_runtime`: persistent compile cache, GPU memory
    grown on demand), which ``import treeinfer`` leaves to the program that uses it."""
    import treeinfer
    from treeinfer.cli.environment import check_environment

    check_environment()
    treeinfer.configure_runtime()


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit code (see the module docstring)."""
    if argv is None:  # the real command line: Ctrl-C always ends it (treeinfer.io.interrupt)
        from ..io.interrupt import exit_if_interrupted, install

        install()
        return exit_if_interrupted(_main(sys.argv[1:]))
    return _main([str(a) for a in argv])


def _main(argv: list[str]) -> int:
    try:
        parser = build_parser(_command_of(argv), lazy=True)
        args = parser.parse_args(argv)
    except SystemExit as e:  # --help, --version, or a usage error (argparse printed it)
        return (
            e.code if isinstance(e.code, int) else (EXIT_OK if e.code is None else EXIT_USER_ERROR)
        )
    except KeyboardInterrupt:  # Ctrl-C while the command's modules are imported
        print("interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    debug = bool(getattr(args, "debug", False))
    try:
        _start_runtime()
        rc = args._run(args)
        return EXIT_OK if rc is None else int(rc)
    except TreeinferError as e:
        if debug:
            traceback.print_exc()
        print(f"error: {e}", file=sys.stderr)
        return EXIT_USER_ERROR
    except OSError as e:  # disk full, permission denied, a folder where a file should be...
        if debug:
            traceback.print_exc()
        where = f"{e.filename}: " if e.filename else ""
        print(f"error: {where}{e.strerror or e}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        if debug:
            traceback.print_exc()
        print("interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as e:  # noqa: BLE001 -- anything else is a bug: report it, exit 3
        if debug:
            traceback.print_exc()
        print(
            f"internal error ({type(e).__name__}: {e}); this is a bug in treeinfer, please "
            "report it (rerun with --debug for the traceback)",
            file=sys.stderr,
        )
        return EXIT_INTERNAL_ERROR


if __name__ == "__main__":
    sys.exit(main())
