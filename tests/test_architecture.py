"""The package's layering: every module imports on its own, without import cycles, and nothing
in the package imports the CLI (``treeinfer.cli`` sits on top; the data path runs one way)."""

from __future__ import annotations

import ast
import pkgutil
import subprocess
import sys
from pathlib import Path

from import_graph import import_targets, module_file

import treeinfer

ROOT = Path(treeinfer.__file__).resolve().parent
MODULES = sorted(
    m.name
    for m in pkgutil.walk_packages([str(ROOT)], prefix="treeinfer.")
    if not m.name.startswith("treeinfer.examples.")
)


def _imports(name: str) -> set[str]:
    """Absolute names of the treeinfer modules ``name`` imports (at any depth of its code)."""
    out = set()
    for mod, subs in import_targets(name, MODULES):
        out |= {mod} | subs
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


# ---- no process-global caches hidden in modules ---------------------------------------------
# Compiled programs and simulators are cached only in objects their owner passes down
# (treeinfer.sim.program_cache.ProgramCache, treeinfer.runs.SimulatorCache). Memoised pure functions
# that build no program may stay, each with its reason here.
ALLOWED_MEMOS = {
    "treeinfer.sim.levels.layout": "NumPy index arrays of a hashable tuple of constants",
    "experiments._posterior_cache._source_digest": "the sources' hash, read once per process",
}
_CONTAINERS = {"dict", "list", "set", "OrderedDict", "defaultdict", "WeakValueDictionary"}
_MUTATORS = {"append", "add", "clear", "extend", "insert", "pop", "popitem", "setdefault"}
_MUTATORS |= {"update", "remove", "discard", "move_to_end"}


def _name_of(node) -> str:
    node = node.func if isinstance(node, ast.Call) else node
    if isinstance(node, ast.Attribute):
        return node.attr
    return getattr(node, "id", "")


def module_caches(source: str, module: str) -> list[str]:
    """What in ``source`` keeps state across calls at module level: functions memoised with
    ``functools.lru_cache`` / ``functools.cache``, and module-level dicts, lists or sets that
    a function writes to (item assignment or deletion, a mutating method, ``global``) or that
    are handed to a call as its ``cache=``."""
    tree = ast.parse(source)
    found = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            for d in node.decorator_list:
                if _name_of(d) in ("lru_cache", "cache"):
                    found.append(f"{module}.{node.name}: @{_name_of(d)}")
    containers = set()
    for stmt in tree.body:
        value = getattr(stmt, "value", None)
        targets = stmt.targets if isinstance(stmt, ast.Assign) else [getattr(stmt, "target", None)]
        mutable = isinstance(value, (ast.Dict, ast.List, ast.Set, ast.DictComp, ast.ListComp))
        mutable |= isinstance(value, ast.Call) and _name_of(value) in _CONTAINERS
        if isinstance(stmt, (ast.Assign, ast.AnnAssign)) and mutable:
            containers |= {t.id for t in targets if isinstance(t, ast.Name)}
    for fn in ast.walk(tree):
        if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            continue
        written = set()
        for node in ast.walk(fn):
            if isinstance(node, ast.Global):
                written |= set(node.names) & containers
            elif isinstance(node, ast.Subscript) and isinstance(node.ctx, (ast.Store, ast.Del)):
                written.add(getattr(node.value, "id", None))
            elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
                if node.func.attr in _MUTATORS:
                    written.add(getattr(node.func.value, "id", None))
        name = getattr(fn, "name", "<lambda>")
        found += [f"{module}.{c}: written by {name}()" for c in sorted(written & containers)]
    for node in ast.walk(tree):  # handed to a library function as its cache
        if isinstance(node, ast.keyword) and "cache" in (node.arg or ""):
            if getattr(node.value, "id", None) in containers:
                found.append(f"{module}.{node.value.id}: passed as {node.arg}=")
    return found


def test_the_cache_scanner_finds_the_old_driver_caches():
    """The check below would have failed on the old sampler driver (an lru_cache on the chunk
    builder and a module-level dict of compiled executables); a cache object passed in, a
    constant table and a local dict are not caches of the module."""
    old = (
        "import functools\n"
        "@functools.lru_cache(maxsize=4)\n"
        "def _build_chunk(init, step):\n"
        "    return jax.jit(init)\n"
        "_COMPILED: dict = {}\n"
        "TABLE = {'a': 1}\n"
        "def _compiled(jitted, args, cache):\n"
        "    key = (jitted, args)\n"
        "    local = {}\n"
        "    local[key] = TABLE['a']\n"
        "    cache[key] = 1\n"
        "    if key not in _COMPILED:\n"
        "        _COMPILED[key] = jitted.lower(*args).compile()\n"
        "    return _COMPILED[key]\n"
    )
    assert module_caches(old, "old") == [
        "old._build_chunk: @lru_cache",
        "old._COMPILED: written by _compiled()",
    ]
    assert module_caches("_S = []\ndef f(x):\n    _S.append(x)\n", "m") == ["m._S: written by f()"]
    study = "_PROGRAMS: dict = {}\ndef run(sim):\n    return program(sim, cache=_PROGRAMS)\n"
    assert module_caches(study, "m") == ["m._PROGRAMS: passed as cache="]


def test_no_module_keeps_a_cache():
    """No module of the package, the experiments or the benchmarks keeps a cache (but the
    memoised pure functions of ``ALLOWED_MEMOS``)."""
    found = []
    for m in MODULES:
        found += module_caches(module_file(m).read_text(encoding="utf-8"), m)
    for folder in ("experiments", "benchmarks"):
        for path in sorted((ROOT.parent / folder).glob("*.py")):
            found += module_caches(path.read_text(encoding="utf-8"), f"{folder}.{path.stem}")
    allowed = {f"{name}: @lru_cache" for name in ALLOWED_MEMOS}
    assert sorted(set(found) - allowed) == []
