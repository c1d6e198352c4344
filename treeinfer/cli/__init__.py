"""The ``treeinfer`` command line (argument parsing and printing only); see
:mod:`treeinfer.cli.main`. Nothing else in the package imports this package."""

from __future__ import annotations

import importlib

from .common import (
    EXIT_INTERNAL_ERROR,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_USER_ERROR,
    add_command_parser,
)
from .main import COMMANDS, Command, build_parser, main

__all__ = [
    "COMMANDS",
    "EXIT_INTERNAL_ERROR",
    "EXIT_INTERRUPTED",
    "EXIT_OK",
    "EXIT_USER_ERROR",
    "INFER_DEFAULTS",
    "Command",
    "add_command_parser",
    "build_parser",
    "main",
]

# Names of the command modules, served lazily (``treeinfer.cli.run_infer`` imports ``cli.infer``).
_LAZY = {"INFER_DEFAULTS": "infer"}
_MODULES = ("tree", "simulate", "import_bag", "infer", "predict", "evaluate", "demo")


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        for m in _MODULES:
            if name in (f"configure_{m}", f"run_{m}"):
                module = m
    if module is None:
        raise AttributeError(f"module 'treeinfer.cli' has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{module}"), name)
