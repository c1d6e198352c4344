"""Writes templates/<pkg>/__init__.py for the new packages from the mapping and today's code
(run once in a checkout before the move; the templates are then reviewed and kept)."""

import ast
import pathlib
import sys
import textwrap

sys.path.insert(0, str(pathlib.Path(__file__).parent))
from relayout import read_mapping

root = pathlib.Path(sys.argv[1])
here = pathlib.Path(__file__).parent
moves, future = read_mapping(here / "mapping.txt")

DOCS = {
    "io": (
        "Files in and out, for every layer: atomic writes that never destroy data, one bounded "
        "loader for YAML and JSON, strict JSON, and provenance (file hashes, library versions, "
        "config hashes).",
        "treeinfer.errors only (the lowest layer; everything else may import it).",
    ),
    "tree": (
        "Trees: the tree description (branches, grasp point, inferred joints, prior boxes), its "
        "types and checks, generators (chains, fractals, L-systems, the stem), export to "
        "MJCF/URDF and users' own URDF/MJCF models.",
        "treeinfer.io and treeinfer.errors.",
    ),
    "data": (
        "Recordings: force-deformation trajectories and their files, where and in which "
        "direction each pull acted, plausibility checks of data against a tree, force profiles, "
        "and the importers (CSV, ROS bags).",
        "treeinfer.tree.description, treeinfer.io, treeinfer.errors.",
    ),
    "model": (
        "The log-density: theta's parameterisation (gains), priors and the learned inequality "
        "prior (NNSVGD's network), the Boltzmann and Gaussian likelihoods, noise models and the "
        "force-noise term, the temperature rule, and gradient estimators (central differences).",
        "treeinfer.sim, treeinfer.data, treeinfer.tree.description, treeinfer.io, treeinfer.errors. "
        "Known exception until it is split: force_noise's noise estimate calls "
        "treeinfer.inference.problem.mapfit (inside a function).",
    ),
    "inference": (
        "From a problem to particles: the front end (make_problem, infer, predict), "
        "starts (MAP fit, Laplace, importance sampling, the fast posterior), the samplers "
        "(BlackJAX-style kernels: SVGD, SGLD, SGHMC, MH), their diagnostics, sequential "
        "priors, batched posteriors, sharding, and the quasi-static model (static/).",
        "treeinfer.model, treeinfer.sim, treeinfer.data, treeinfer.tree.description, treeinfer.io, "
        "treeinfer.errors.",
    ),
    "evaluation": (
        "A posterior judged: predictions of every particle with their bands, metrics on "
        "plain arrays, figures returning (fig, axes), and the fit checks after inference.",
        "treeinfer.inference.problem and every layer below it.",
    ),
}

pkgs = {}
for old, new in moves.items():
    if old.endswith("/") or not new.startswith("treeinfer/"):
        continue
    parts = new.split("/")
    if len(parts) == 3 and parts[1] in DOCS and (root / old).exists():
        pkgs.setdefault(parts[1], []).append((old, parts[2][:-3]))
for old, new in moves.items():  # folders moved whole: their __init__ is a submodule face
    if old.endswith("/"):
        parts = new.rstrip("/").split("/")
        if parts[1] in DOCS:
            pkgs.setdefault(parts[1], []).append((old + "__init__.py", parts[2]))


def exports(path):
    t = ast.parse(path.read_text())
    defined, alls = [], None
    for n in t.body:
        if isinstance(n, (ast.FunctionDef, ast.ClassDef)) and not n.name.startswith("_"):
            defined.append(n.name)
        if isinstance(n, ast.Assign) and getattr(n.targets[0], "id", "") == "__all__":
            alls = list(ast.literal_eval(n.value))
    return defined, alls


for pkg, members in sorted(pkgs.items()):
    table = {}
    subs = []
    for old, sub in members:
        subs.append(sub)
        if sub.startswith("_"):
            continue
        defined, alls = exports(root / old)
        names = alls if alls is not None else defined
        for n in names:
            own = n in defined
            if n not in table or (own and not table[n][1]):
                table[n] = (sub, own)
    subs_set = set(subs)
    table = {k: v for k, v in table.items() if k not in subs_set}
    what, may = DOCS[pkg]
    doc = textwrap.fill(what, 96) + "\n\nMay import: " + textwrap.fill(may, 96 - 12)
    subline = textwrap.fill(
        "Submodules: " + ", ".join(sorted(s for s in subs if not s.startswith("_"))) + ".", 96
    )
    lines = [
        f'"""{doc}',
        "",
        "The public API is re-exported here name by name, imported lazily (on first use), so",
        "importing one module of the package does not import the others (startup cost, and no",
        "import order between them).",
        "",
        subline + '"""',
        "",
        "_EXPORTS = {",
    ]
    for name in sorted(table, key=lambda n: (table[n][0], n)):
        lines.append(f'    "{name}": "{table[name][0]}",')
    lines += [
        "}",
        f"_SUBMODULES = {tuple(sorted(subs))!r}",
        "",
        "__all__ = sorted(_EXPORTS)",
        "",
        "",
        "def __getattr__(name):",
        "    import importlib",
        "",
        "    if name in _EXPORTS:",
        '        return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)',
        "    if name in _SUBMODULES:",
        '        return importlib.import_module(f"{__name__}.{name}")',
        '    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")',
        "",
        "",
        "def __dir__():",
        "    return sorted(set(globals()) | set(_EXPORTS) | set(_SUBMODULES))",
        "",
    ]
    out = here / "templates" / pkg / "__init__.py"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines))
    print(pkg, len(table), "names,", len(subs), "submodules")
