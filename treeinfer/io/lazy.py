"""Lazy package faces (PEP 562): a package's ``__getattr__`` and ``__dir__`` that import a
public name's module, or a submodule, on first use, so importing one module of a package does
not import the others (start-up cost; no import order between them). One definition for every
package of treeinfer (tree, data, model, inference, evaluation, io)."""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Iterable, Mapping


def lazy_package(
    package: str, exports: Mapping[str, str], submodules: Iterable[str]
) -> tuple[Callable[[str], object], Callable[[], list[str]]]:
    """``(__getattr__, __dir__)`` for ``package``: ``exports`` maps a public name to the
    submodule that defines it; ``submodules`` are importable as attributes."""
    subs = frozenset(submodules)

    def __getattr__(name: str):
        if name in exports:
            return getattr(importlib.import_module(f"{package}.{exports[name]}"), name)
        if name in subs:
            return importlib.import_module(f"{package}.{name}")
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(exports) | subs)

    return __getattr__, __dir__
