"""The package's import graph read from its sources (``ast``, no imports run), shared by
``test_architecture`` (layering, cycles, caches) and ``test_layout`` (packages by job)."""

from __future__ import annotations

import ast
from pathlib import Path

import treeinfer

ROOT = Path(treeinfer.__file__).resolve().parent


def module_file(name: str) -> Path:
    """The source file of module ``name`` (``treeinfer.x.y``): a package's ``__init__.py``."""
    rel = Path(*name.split(".")[1:])
    pkg = ROOT / rel / "__init__.py"
    return pkg if pkg.is_file() else (ROOT / rel).with_suffix(".py")


def import_targets(name: str, modules) -> list[tuple[str, set[str]]]:
    """``(module, submodules)`` for every treeinfer import in ``name``'s code at any depth:
    the absolute module an ``import`` or ``from ... import`` names (relative imports resolved),
    and those of the imported names that are themselves modules in ``modules``."""
    path = module_file(name)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    known = set(modules)
    out = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            out += [(a.name, set()) for a in node.names if a.name.startswith("treeinfer")]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if mod.startswith("treeinfer"):
                out.append((mod, {f"{mod}.{a.name}" for a in node.names} & known))
    return out
