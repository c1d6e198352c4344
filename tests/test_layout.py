"""The package's layout by job (issue 26; docs/layout.md): packages import one way, down the
layers; no cycle between packages; no module over 500 lines (but the listed ones, until they are
split); after the move to packages, nothing at the top of ``treeinfer/`` but ``__init__``,
``__main__`` and ``errors``; benchmarks and experiments use public names only."""

from __future__ import annotations

import ast
import pkgutil
from pathlib import Path

import pytest
from import_graph import import_targets, module_file

import treeinfer

ROOT = Path(treeinfer.__file__).resolve().parent
REPO = ROOT.parent
MODULES = sorted(m.name for m in pkgutil.walk_packages([str(ROOT)], prefix="treeinfer."))

# The layers, lowest first: a package imports only from its own layer or a lower one. Old
# packages (samplers, diagnostics, static) sit in the layer they move to.
LAYERS = {
    "io": ("io", 0),
    "tree": ("tree", 1),
    "examples": ("tree", 1),
    "data": ("data", 2),
    "sim": ("sim", 3),
    "model": ("model", 4),
    "inference": ("inference", 5),
    "samplers": ("inference", 5),
    "diagnostics": ("inference", 5),
    "static": ("inference", 5),
    "evaluation": ("evaluation", 6),
    "design": ("design", 7),
    "calibration": ("calibration", 7),
    "amortised": ("amortised", 7),
    "runs": ("runs", 8),
    "cli": ("cli", 9),
}
# Imports that go up a layer today, each with its way out. Shrink it; never grow it.
KNOWN_UPWARD = {
    (
        "treeinfer.model.force_noise_reference",
        "treeinfer.inference.mapfit",
    ): "the force-noise reference fits a MAP point; move reference_theta to the inference layer",
    # Posterior (the result type of infer, in inference/) draws bands and figures through
    # evaluation/ inside its methods (predict, pair_plot, plot_trace), imported on call.
    ("treeinfer.inference.posterior", "treeinfer.evaluation.bands"): "Posterior.predict; "
    "move Posterior and infer's front end to a user-facing layer above evaluation",
    ("treeinfer.inference.posterior", "treeinfer.evaluation.plots"): "Posterior.plot_*; as above",
    ("treeinfer.inference.posterior", "treeinfer.evaluation.posterior_bands"): "Posterior.predict; "
    "as above",
    ("treeinfer.inference.posterior_io", "treeinfer.evaluation.posterior_plots"): "the pair "
    "plot of a run's posterior; as above",
}
# Modules over 500 lines today, to be split (the lead shrinks this list as they are): none since
# the last three were split (issue 26); keep it empty.
LONG_MODULES: dict[str, str] = {}
MAX_LINES = 500
TOP_LEVEL = {"__init__", "__main__", "errors"}
# after the move, a package per job; before it, the old flat layout (this part waits for it)
MOVED = all((ROOT / p / "__init__.py").is_file() for p in ("tree", "data", "model", "inference"))


def _imports(name: str) -> set[str]:
    """The treeinfer modules ``name`` imports, at any depth of its code."""
    out = set()
    for mod, subs in import_targets(name, MODULES):
        out |= subs if subs else {mod}
    return out


def _unit(name: str) -> str | None:
    """The package (or, before the move, the top-level module) a module belongs to."""
    parts = name.split(".")
    if len(parts) < 2 or parts[1] in TOP_LEVEL:
        return None  # the top package and errors: anyone may import them
    return parts[1]


def _edges():
    for m in MODULES:
        for i in _imports(m):
            a, b = _unit(m), _unit(i)
            if a and b and a != b:
                yield m, i, a, b


def test_no_import_cycle_between_packages():
    graph: dict[str, set[str]] = {}
    for m, i, a, b in _edges():
        if (m, i) not in KNOWN_UPWARD:  # listed, each with its way out
            graph.setdefault(a, set()).add(b)
    state: dict[str, int] = {}
    cycles = []

    def visit(n, stack):
        state[n] = 1
        for k in sorted(graph.get(n, ())):
            if state.get(k) == 1:
                cycles.append(stack[stack.index(k) :] + [k])
            elif k not in state:
                visit(k, stack + [k])
        state[n] = 2

    for n in sorted(graph):
        if n not in state:
            visit(n, [n])
    assert not cycles, cycles


def test_lower_layers_never_import_upper_ones():
    bad = []
    for m, i, a, b in _edges():
        if a not in LAYERS or b not in LAYERS:
            continue  # a top-level module of the old layout: placed by the move
        (la, ra), (lb, rb) = LAYERS[a], LAYERS[b]
        if la != lb and rb >= ra and (m, i) not in KNOWN_UPWARD:
            bad.append(f"{m} ({la}) imports {i} ({lb})")
    assert not bad, "\n".join(sorted(bad))


def test_the_cli_is_imported_by_nothing_below_it():
    bad = [f"{m} -> {i}" for m, i, a, b in _edges() if b == "cli" and a != "cli"]
    assert not [x for x in bad if not x.startswith("treeinfer.__main__")]


def test_no_module_over_500_lines():
    long = {}
    for m in MODULES:
        n = len(module_file(m).read_text(encoding="utf-8").splitlines())
        if n > MAX_LINES and m not in LONG_MODULES:
            long[m] = n
    assert not long, f"split these modules (at most {MAX_LINES} lines): {long}"


def test_nothing_at_the_top_but_init_main_errors():
    top = sorted(p.stem for p in ROOT.glob("*.py") if p.stem not in TOP_LEVEL)
    if not MOVED:
        pytest.skip(f"old flat layout ({len(top)} top-level modules); checked after the move")
    assert not top, f"modules at the top of treeinfer/: {top}; move each into its package"


def _private_uses(path: Path) -> list[str]:
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("treeinfer"):
            names = [a.name for a in node.names if a.name.startswith("_")]
            names = [n for n in names if n != "__version__"]
            if names:
                found.append(f"{path.name}:{node.lineno}: {node.module} {names}")
            mods = [c for c in node.module.split(".") if c.startswith("_")]
            if mods and node.module not in PRIVATE_MODULES_UNTIL_THE_MOVE:
                found.append(f"{path.name}:{node.lineno}: private module {node.module}")
    return found


# treeinfer.io.atomic: the atomic writers, public since the move (it was the private _io)
PRIVATE_MODULES_UNTIL_THE_MOVE = {"treeinfer.io.atomic"}


def test_benchmarks_and_experiments_use_public_names():
    found = []
    for folder in ("benchmarks", "experiments"):
        for path in sorted((REPO / folder).glob("*.py")):
            found += _private_uses(path)
    assert not found, "\n".join(found)


def test_the_private_name_check_catches_one(tmp_path):
    p = tmp_path / "x.py"
    p.write_text(
        "from treeinfer.evaluation.metrics import _outside\n"  # a private name
        "from treeinfer.tree._generate import f\n"  # a private module
    )
    assert len(_private_uses(p)) == 2
