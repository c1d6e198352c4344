"""The package's layering: every module imports on its own, without import cycles, and nothing
in the package imports the CLI (``treeinfer.cli`` sits on top; the data path runs one way)."""

from __future__ import annotations

import ast
import pkgutil
import subprocess
import sys
from pathlib import Path

import treeinfer

ROOT = Path(treeinfer.__file__).resolve().parent
MODULES = sorted(
    m.name
    for m in pkgutil.walk_packages([str(ROOT)], prefix="treeinfer.")
    if not m.name.startswith("treeinfer.examples.")
)


def _module_file(name: str) -> Path:
    rel = Path(*name.split(".")[1:])
    pkg = ROOT / rel / "__init__.py"
    return pkg if pkg.is_file() else (ROOT / rel).with_suffix(".py")


def _imports(name: str) -> set[str]:
    """Absolute names of the treeinfer modules ``name`` imports (at any depth of its code)."""
    path = _module_file(name)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.startswith("treeinfer")}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if mod.startswith("treeinfer"):
                out.add(mod)
                out |= {f"{mod}.{a.name}" for a in node.names if f"{mod}.{a.name}" in MODULES}
    return {m for m in out if m in MODULES or m == "treeinfer"}


def test_nothing_in_the_package_imports_the_cli():
    offenders = {
        m: sorted(i for i in _imports(m) if i == "treeinfer.cli" or i.startswith("treeinfer.cli."))
        for m in MODULES
        if not (m == "treeinfer.cli" or m.startswith("treeinfer.cli.") or m == "treeinfer.__main__")
    }
    assert not {m: v for m, v in offenders.items() if v}


def test_every_module_imports_alone():
    code = (
        "import importlib, sys\n"
        "bad = []\n"
        "for name in sys.argv[1:]:\n"
        "    for m in [k for k in sys.modules if k.startswith('treeinfer')]:\n"
        "        del sys.modules[m]\n"
        "    try:\n"
        "        importlib.import_module(name)\n"
        "    except Exception as e:\n"
        "        bad.append(f'{name}: {type(e).__name__}: {e}')\n"
        "print('\\n'.join(bad)); sys.exit(1 if bad else 0)\n"
    )
    mods = [m for m in MODULES if m != "treeinfer.__main__"]
    r = subprocess.run(
        [sys.executable, "-c", code, *mods],
        capture_output=True,
        text=True,
        cwd=ROOT.parent,
        timeout=600,
    )
    assert r.returncode == 0, r.stdout + r.stderr


def test_no_import_cycles_between_modules():
    """Module-level and function-level imports together form an acyclic graph (a package's
    ``__init__`` importing its own submodules is not a cycle)."""
    graph = {m: {i for i in _imports(m) if i != m} for m in MODULES}

    def is_parent(a, b):  # a package and its submodule
        return b.startswith(a + ".") or a.startswith(b + ".")

    state: dict[str, int] = {}
    cycles = []

    def visit(m, stack):
        state[m] = 1
        for n in graph.get(m, ()):
            if is_parent(m, n) or n == "treeinfer":
                continue
            if state.get(n) == 1:
                cycles.append(stack[stack.index(n) :] + [n] if n in stack else [m, n])
            elif state.get(n) is None:
                visit(n, stack + [n])
        state[m] = 2

    for m in MODULES:
        if m not in state:
            visit(m, [m])
    assert not cycles, cycles
