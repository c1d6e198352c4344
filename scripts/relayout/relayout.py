#!/usr/bin/env python3
"""Move treeinfer's modules into packages by job (issue 26) and rewrite every reference to them.

Run from a repository root with a clean git tree:

    python /path/to/relayout.py [--mapping mapping.txt] [--templates templates/] [--dry-run]
                                [--no-ruff] [--no-verify]

What it does, in order (it stops with a message and exit 1 before touching anything when a check
fails):
  1. reads the mapping (old path -> new path; see mapping.txt) and the state of the tree: every
     move not yet made must have its source and not its destination; all moves made already means
     the relayout was applied before (nothing to do, exit 0); a mix means a half-applied tree;
  2. refuses unknown top-level modules of treeinfer/ (not in the mapping and not kept at the top):
     it lists them, so a line can be added to the mapping;
  3. computes every file's new text from the ORIGINAL layout: import statements (absolute,
     relative, ``import treeinfer.x as y``, at any depth of the code) parsed with ``ast`` and
     rewritten to the new module (relative imports recomputed from the module's new place,
     absolute ones kept absolute); every other mention of ``treeinfer.<module>`` (strings for
     mock.patch / monkeypatch / importlib, docstrings, comments, entry points) and of
     ``treeinfer/<path>.py`` in Python, Markdown, notebooks (code and markdown cells), TOML,
     YAML, shell and text files; the lazy export table of ``treeinfer/__init__.py``;
     ``Path(__file__)`` in a module that changes depth keeps pointing at the same folder;
  4. ``git mv``s every file, writes the new texts and the new packages' ``__init__.py`` from the
     templates, then runs ``ruff check --select I --fix`` and ``ruff format`` on the Python files
     it changed (the rewritten imports are re-sorted), and imports every module of the package in
     a fresh interpreter.
Old run folders (tests/fixtures) and recorded results (experiments/results) are data and are
never rewritten.
"""

from __future__ import annotations

import argparse
import ast
import io
import json
import re
import shutil
import subprocess
import sys
import tokenize
from pathlib import Path

HERE = Path(__file__).resolve().parent
PKG = "treeinfer"
KEEP_TOP = {"__init__.py", "__main__.py", "errors.py"}
# top-level folders that stay (packages already by job, or package data)
KEEP_DIRS = {"sim", "runs", "calibration", "cli", "examples", "data", "__pycache__"}
TEXT_SUFFIXES = {
    ".py",
    ".md",
    ".ipynb",
    ".toml",
    ".cfg",
    ".ini",
    ".txt",
    ".yaml",
    ".yml",
    ".sh",
    ".rst",
}
NEVER_REWRITE = ("tests/fixtures/", "experiments/results/")
PUBLIC_FOLDERS = ("benchmarks/", "experiments/", "notebooks/", "docs/")
MAX_LINE = 100  # ruff's line-length in pyproject.toml


class Stop(Exception):
    """A check failed: the message says what and what to do."""


# ---- the mapping -------------------------------------------------------------------------------
def read_mapping(path: Path) -> tuple[dict[str, str], set[str]]:
    moves, future = {}, set()
    for n, raw in enumerate(path.read_text().splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        if "->" not in line:
            raise Stop(f"{path}:{n}: expected 'old -> new', got {raw!r}")
        old, new = (s.strip() for s in line.split("->", 1))
        if new.endswith("(future)"):
            new = new[: -len("(future)")].strip()
            future.add(old)
        if old in moves:
            raise Stop(f"{path}:{n}: {old} is mapped twice")
        if old.endswith("/") != new.endswith("/"):
            raise Stop(f"{path}:{n}: a folder maps to a folder, a file to a file")
        moves[old] = new
    news = list(moves.values())
    dup = {x for x in news if news.count(x) > 1}
    if dup:
        raise Stop(f"{path}: several sources move to {sorted(dup)}")
    return moves, future


def modname(path: str) -> str:
    """treeinfer/a/b.py -> treeinfer.a.b; treeinfer/a/__init__.py -> treeinfer.a."""
    p = path[:-3] if path.endswith(".py") else path.rstrip("/")
    name = p.replace("/", ".")
    return name[: -len(".__init__")] if name.endswith(".__init__") else name


def file_moves(root: Path, moves: dict[str, str], future: set[str]) -> dict[str, str]:
    """Every tracked file that moves: old path -> new path (folders expanded, file lines win)."""
    tracked = git(root, "ls-files", PKG).split("\n")
    out = {}
    for old, new in moves.items():
        if old.endswith("/"):
            for f in tracked:
                if f.startswith(old) and f not in moves:
                    out[f] = new + f[len(old) :]
    for old, new in moves.items():
        if not old.endswith("/") and (root / old).exists():
            out[old] = new
    return out


# ---- the state of the tree ---------------------------------------------------------------------
def check_state(root: Path, moves: dict[str, str], future: set[str]) -> str:
    todo, done, bad = [], [], []
    for old, new in moves.items():
        o, n = (root / old).exists(), (root / new).exists()
        if old in future and not o:
            continue
        if o and not n:
            todo.append(old)
        elif n and not o:
            done.append(old)
        elif o and n and old.endswith("/") is False and new.endswith("/__init__.py") is False:
            bad.append(f"{old} and {new} both exist")
        elif not o and not n:
            bad.append(f"{old}: neither it nor {new} exists (remove the line or mark it (future))")
    if bad:
        raise Stop("the tree does not match the mapping:\n  " + "\n  ".join(bad))
    if done and not todo:
        return "applied"
    if done and todo:
        raise Stop(
            "half applied: moved already "
            + ", ".join(done[:5])
            + (" ..." if len(done) > 5 else "")
            + "; still to move "
            + ", ".join(todo[:5])
            + ". Reset the tree (git checkout .) first."
        )
    return "todo"


def unknown_top_level(root: Path, moves: dict[str, str]) -> list[str]:
    found = []
    for p in sorted((root / PKG).iterdir()):
        rel = p.relative_to(root).as_posix()
        if p.is_file() and p.suffix == ".py" and p.name not in KEEP_TOP and rel not in moves:
            found.append(rel)
        if p.is_dir() and p.name not in KEEP_DIRS and rel + "/" not in moves:
            if any(p.glob("*.py")):
                found.append(rel + "/")
    return found


# ---- module names ------------------------------------------------------------------------------
class Modules:
    """Old module name -> new module name, and what a module name resolves to."""

    def __init__(self, fmoves: dict[str, str], tracked: list[str]):
        self.old_files = {f for f in tracked if f.startswith(PKG + "/") and f.endswith(".py")}
        self.old = {modname(f): f for f in self.old_files}
        self.map = {modname(o): modname(n) for o, n in fmoves.items() if o.endswith(".py")}
        self.fmoves = fmoves

    def new(self, name: str) -> str:
        return self.map.get(name, name)

    def is_module(self, name: str) -> bool:
        return name in self.old

    def rewrite_dotted(self, dotted: str) -> str:
        """treeinfer.a.b.attr -> new module of the longest old-module prefix + .attr."""
        parts = dotted.split(".")
        for k in range(len(parts), 1, -1):
            head = ".".join(parts[:k])
            if head in self.map:
                return ".".join([self.map[head]] + parts[k:])
            if head in self.old:
                return dotted
        return dotted


def package_of(module: str, is_init: bool) -> str:
    return module if is_init else module.rpartition(".")[0]


def resolve(level: int, module: str | None, package: str) -> str:
    if not level:
        return module or ""
    base = package.split(".")
    if level - 1 > len(base) - 1:
        raise Stop(f"relative import beyond the top package in {package}")
    base = base[: len(base) - level + 1]
    return ".".join(base + ([module] if module else []))


def relative(target: str, package: str) -> tuple[int, str]:
    t, p = target.split("."), package.split(".")
    common = 0
    while common < min(len(t), len(p)) and t[common] == p[common]:
        common += 1
    if common == 0:
        raise Stop(f"cannot import {target} relatively from {package}")
    return len(p) - common + 1, ".".join(t[common:])


def from_text(level: int, module: str, names: list[tuple[str, str | None]]) -> str:
    spec = "." * level + module
    items = ", ".join(n if a is None or a == n else f"{n} as {a}" for n, a in names)
    return f"from {spec} import {items}"


# ---- rewriting Python ---------------------------------------------------------------------------
DOTTED = re.compile(r"(?<![\w.])" + PKG + r"(?:\.[A-Za-z_]\w*)+")
PATHREF = re.compile(r"(?<![\w/.])" + PKG + r"/[\w/]+(?:\.py|/)")
FILE_PARENT = re.compile(
    r"Path\(__file__\)(\.resolve\(\))?\.(parent(?![s\w])|parents\[(\d+)\])(?P<tail>(\.parent(?![s\w]))*)"
)


class Rewriter:
    def __init__(self, mods: Modules, log: list[str], exports: dict[str, dict[str, str]]):
        self.mods, self.log = mods, log
        # package -> {name: module that defines it}: the new packages' re-exports
        self.exports = exports
        # user-facing files (docs, notebooks, benchmarks, experiments) name the package's public
        # re-export where there is one (treeinfer.tree.description.Tree, not
        # treeinfer.tree.description.description.Tree); the package's own code and the tests name
        # the defining module (patching needs it)
        self.public = False

    def dotted(self, d: str) -> str:
        new = self.mods.rewrite_dotted(d)
        if self.public and new != d:
            mod, _, attr = new.rpartition(".")
            pkg = ".".join(new.split(".")[:2])
            if self.exports.get(pkg, {}).get(attr) == mod:
                return f"{pkg}.{attr}"
        return new

    # -- text that is not an import statement
    def text(self, s: str) -> str:
        s = DOTTED.sub(lambda m: self.dotted(m.group(0)), s)

        def path(m):
            ref = m.group(0)
            if ref in self.mods.fmoves:
                return self.mods.fmoves[ref]
            folder_moves = {
                o.rsplit("/", 1)[0] + "/": n.rsplit("/", 1)[0] + "/"
                for o, n in self.mods.fmoves.items()
            }
            if ref.endswith("/") and ref in folder_moves and ref != PKG + "/":
                inside = [o for o in self.mods.fmoves if o.startswith(ref)]
                targets = {self.mods.fmoves[o].rsplit("/", 1)[0] + "/" for o in inside}
                stays = [
                    f
                    for f in self.mods.old_files
                    if f.startswith(ref) and f not in self.mods.fmoves
                ]
                if len(targets) == 1 and not stays:
                    return targets.pop()
            return ref

        return PATHREF.sub(path, s)

    # -- one import statement
    def import_stmt(
        self, node, package: str | None, new_package: str | None, src: str
    ) -> str | None:
        mods = self.mods
        if isinstance(node, ast.Import):
            changed, parts = False, []
            for a in node.names:
                if a.name.split(".")[0] != PKG:
                    parts.append(a.name if a.asname is None else f"{a.name} as {a.asname}")
                    continue
                new = mods.rewrite_dotted(a.name)
                changed |= new != a.name
                parts.append(new if a.asname is None else f"{new} as {a.asname}")
            return [f"import {', '.join(parts)}"] if changed else None
        level, module = node.level, node.module
        if level and package is None:
            return None  # a relative import outside the package (experiments' own)
        absolute = resolve(level, module, package) if level else (module or "")
        if absolute.split(".")[0] != PKG:
            return None
        groups: dict[str, list[tuple[str, str | None]]] = {}
        for a in node.names:
            sub = f"{absolute}.{a.name}"
            if a.name != "*" and mods.is_module(sub):
                tgt = mods.new(sub)
                parent, _, last = tgt.rpartition(".")
                asname = a.asname or (a.name if last != a.name else None)
                groups.setdefault(parent, []).append((last, asname))
            else:
                if not mods.is_module(absolute) and absolute != PKG:
                    self.log.append(f"unresolved import of {absolute} (kept)")
                tgt = mods.new(absolute)
                groups.setdefault(tgt, []).append((a.name, a.asname))
        if self.public:
            merged: dict[str, list[tuple[str, str | None]]] = {}
            for tgt, names in groups.items():
                pkg = ".".join(tgt.split(".")[:2])
                table = self.exports.get(pkg, {})
                if tgt != pkg and all(table.get(n) == tgt for n, _ in names):
                    tgt = pkg
                merged.setdefault(tgt, []).extend(names)
            groups = merged
        stmts = []
        for tgt, names in groups.items():
            if level and new_package is not None:
                lv, mod = relative(tgt, new_package)
                stmts.append(from_text(lv, mod, names))
            else:
                stmts.append(from_text(0, tgt, names))
        old_names = [(a.name, a.asname) for a in node.names]
        if len(stmts) == 1:
            ((tgt, names),) = groups.items()
            if names == old_names:
                # only the module part changes: keep the statement's own layout and comments
                new_spec = stmts[0].split(" import ", 1)[0][len("from ") :]
                old_spec = "." * level + (module or "")
                if new_spec == old_spec:
                    return None
                return ("SPEC", old_spec, new_spec)
        return stmts

    def python(self, source: str, old_path: str | None, new_path: str | None) -> str:
        """New text of a Python file at old_path (None: outside the package) moving to new_path."""
        try:
            tree = ast.parse(source)
        except SyntaxError as e:
            raise Stop(f"{old_path or '?'}: cannot parse ({e}); fix it or leave it out") from None
        package = new_package = None
        if old_path and old_path.startswith(PKG + "/"):
            is_init = old_path.endswith("__init__.py")
            package = package_of(modname(old_path), is_init)
            new_package = package_of(modname(new_path), new_path.endswith("__init__.py"))
        lines = source.splitlines(keepends=True)
        offsets = [0]
        for ln in lines:
            offsets.append(offsets[-1] + len(ln))

        def pos(lineno, col):
            return offsets[lineno - 1] + len(lines[lineno - 1].encode()[:col].decode())

        edits = []  # (start, end, replacement)
        for node in ast.walk(tree):
            if not isinstance(node, (ast.Import, ast.ImportFrom)):
                continue
            res = self.import_stmt(node, package, new_package, source)
            start, end = (
                pos(node.lineno, node.col_offset),
                pos(node.end_lineno, node.end_col_offset),
            )
            if res is None:
                edits.append((start, end, None))
            elif isinstance(res, tuple):
                seg = source[start:end]
                m = re.match(r"from(\s+)" + re.escape(res[1]) + r"(\s+)import", seg)
                if not m:
                    raise Stop(f"{old_path}:{node.lineno}: cannot find {res[1]!r} in {seg!r}")
                seg = f"from{m.group(1)}{res[2]}{m.group(2)}import" + seg[m.end() :]
                edits.append((start, end, seg))
            else:
                indent = " " * node.col_offset
                if "#" in source[start:end]:
                    self.log.append(
                        f"{old_path}:{node.lineno}: comments inside a split import dropped"
                    )
                edits.append((start, end, ("\n" + indent).join(res)))
        edits.sort()
        out, last = [], 0
        for start, end, rep in edits:
            if start < last:
                continue  # nested (cannot happen for imports)
            out.append(self.text(source[last:start]))
            out.append(source[start:end] if rep is None else rep)
            last = end
        out.append(self.text(source[last:]))
        new = "".join(out)
        if old_path and new_path and old_path.startswith(PKG + "/"):
            new = self.file_refs(new, old_path, new_path)
            if old_path == PKG + "/__init__.py":
                new = self.lazy_table(new)
        return new

    def file_refs(self, text: str, old_path: str, new_path: str) -> str:
        """Keep ``Path(__file__).parent`` pointing at the same folder when the depth changes."""
        shift = new_path.count("/") - old_path.count("/")
        if new_path.endswith("__init__.py") and not old_path.endswith("__init__.py"):
            pass  # design.py -> design/__init__.py: one folder deeper, counted above
        if shift == 0 or "__file__" not in text:
            return text

        def fix(m):
            up = 0 if m.group(3) is None else int(m.group(3))
            up += m.group("tail").count(".parent")
            resolve_ = m.group(1) or ""
            return f"Path(__file__){resolve_}.parents[{up + shift}]"

        new = FILE_PARENT.sub(fix, text)
        rest = FILE_PARENT.sub("", new).count("__file__")
        if rest:
            raise Stop(
                f"{old_path}: uses __file__ in a way this script cannot move safely "
                f"({rest} place(s)); make it Path(__file__).resolve().parent first"
            )
        return new

    def lazy_table(self, text: str) -> str:
        """``_EXPORTS = {name: "module"}`` and ``_MODULES = {"module", ...}`` of the top package:
        module paths relative to treeinfer, rewritten like the imports."""
        tree = ast.parse(text)
        edits = []
        for node in tree.body:
            if not isinstance(node, ast.Assign) or len(node.targets) != 1:
                continue
            name = getattr(node.targets[0], "id", "")
            if name == "_EXPORTS" and isinstance(node.value, ast.Dict):
                for v in node.value.values:
                    if isinstance(v, ast.Constant) and isinstance(v.value, str):
                        new = self.mods.new(f"{PKG}.{v.value}")[len(PKG) + 1 :]
                        if new != v.value:
                            edits.append((v, json.dumps(new)))
            if name == "_MODULES" and isinstance(node.value, (ast.Set, ast.List, ast.Tuple)):
                seen = set()
                for v in node.value.elts:
                    if isinstance(v, ast.Constant) and isinstance(v.value, str):
                        new = self.mods.new(f"{PKG}.{v.value}")[len(PKG) + 1 :].split(".")[0]
                        # an old module now inside a package: the package is the attribute
                        edits.append((v, None if new in seen else json.dumps(new)))
                        seen.add(new)
        lines = text.splitlines(keepends=True)
        for v, rep in sorted(edits, key=lambda e: (e[0].lineno, e[0].col_offset), reverse=True):
            i = v.lineno - 1
            line = lines[i]
            seg = line[v.col_offset : v.end_col_offset]
            if rep is None:  # a duplicate package name: drop the element (one per line)
                if line.strip() in (seg + ",", seg):
                    lines[i] = ""
                    continue
                rep = seg
            lines[i] = line[: v.col_offset] + rep + line[v.end_col_offset :]
        return "".join(lines)

    # -- other text files
    def other(self, text: str, suffix: str, where: str) -> str:
        if suffix == ".ipynb":
            return self.notebook(text, where)
        return "\n".join(self.code_line(ln) for ln in text.split("\n"))

    def code_line(self, line: str) -> str:
        """A line of Markdown/shell/TOML: an import statement in it is parsed, the rest is text."""
        s = line.strip()
        if s.startswith(("from " + PKG, "import " + PKG, ">>> from " + PKG, ">>> import " + PKG)):
            prefix = line[: len(line) - len(line.lstrip())]
            body = s[4:] if s.startswith(">>> ") else s
            lead = prefix + (">>> " if s.startswith(">>> ") else "")
            try:
                return lead + self.python(body, None, None).rstrip("\n")
            except Stop:
                pass
        return self.text(line)

    def notebook(self, text: str, where: str) -> str:
        nb = json.loads(text)
        for cell in nb.get("cells", []):
            src = cell.get("source", [])
            joined = "".join(src) if isinstance(src, list) else src
            if cell.get("cell_type") == "code":
                masked = "\n".join(
                    ("pass  # " + ln) if ln.lstrip().startswith(("%", "!")) else ln
                    for ln in joined.split("\n")
                )
                try:
                    new = self.python(masked, None, None)
                    new = "\n".join(
                        ln[len("pass  # ") :] if ln.startswith("pass  # ") else ln
                        for ln in new.split("\n")
                    )
                except Stop:
                    self.log.append(f"{where}: a code cell does not parse; rewritten as text")
                    new = self.text(joined)
            else:
                new = self.text(joined)
            if new != joined:
                cell["source"] = new.splitlines(keepends=True) if isinstance(src, list) else new
        out = json.dumps(nb, indent=1, ensure_ascii=False) + "\n"
        return out


def template_exports(templates: Path) -> dict[str, dict[str, str]]:
    out = {}
    for t in sorted(templates.glob("*/__init__.py")):
        pkg = f"{PKG}.{t.parent.name}"
        for node in ast.parse(t.read_text()).body:
            if isinstance(node, ast.Assign) and getattr(node.targets[0], "id", "") == "_EXPORTS":
                out[pkg] = {k: f"{pkg}.{v}" for k, v in ast.literal_eval(node.value).items()}
    return out


def wrap_long_lines(path: Path, rel: str) -> list[str]:
    """Lines the longer module paths pushed over MAX_LINE, in comments and docstrings: broken at
    the last space that fits (the rest goes on a line of its own, same indentation). Long lines
    elsewhere (code, other strings) are returned to be reported."""
    text = path.read_text(encoding="utf-8")
    lines = text.split("\n")
    if not any(len(ln) > MAX_LINE for ln in lines):
        return []
    tree = ast.parse(text)
    doc_lines = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = getattr(node, "body", [])
            if (
                body
                and isinstance(body[0], ast.Expr)
                and isinstance(body[0].value, ast.Constant)
                and isinstance(body[0].value.value, str)
            ):
                doc_lines |= set(range(body[0].lineno, body[0].end_lineno + 1))
    comment_lines = set()
    for tok in tokenize.generate_tokens(io.StringIO(text).readline):
        if tok.type == tokenize.COMMENT and not tok.line[: tok.start[1]].strip():
            comment_lines.add(tok.start[0])
    kinds = [
        "comment" if i in comment_lines else "doc" if i in doc_lines else None
        for i in range(1, len(lines) + 1)
    ]
    left, k = [], 0
    marks = ("* ", "- ", ":", "..", ">>>", '"""', "#")

    def split(ln, kind):
        indent = ln[: len(ln) - len(ln.lstrip())]
        lead = indent + "# " if kind == "comment" else indent
        body = (
            ln[len(lead) :] if kind == "comment" and ln.lstrip().startswith("# ") else ln.lstrip()
        )
        return lead, body

    while k < len(lines):
        ln, kind = lines[k], kinds[k]
        if len(ln) <= MAX_LINE:
            k += 1
            continue
        if kind is None:
            left.append(f"{rel}:{k + 1}")
            k += 1
            continue
        lead, body = split(ln, kind)
        cut = body.rfind(" ", 0, MAX_LINE - len(lead) + 1)
        if cut <= 0:
            left.append(f"{rel}:{k + 1}")
            k += 1
            continue
        head, overflow = body[:cut], body[cut + 1 :]
        lines[k] = lead + head
        nxt = lines[k + 1] if k + 1 < len(lines) else None
        n_lead, n_body = split(nxt, kinds[k + 1]) if nxt is not None else ("", "")
        joinable = (
            nxt is not None
            and kinds[k + 1] == kind
            and n_lead == lead
            and n_body.strip()
            and not n_body.lstrip().startswith(marks)
            and not re.match(r"\d+\. ", n_body)
            and not overflow.endswith('"""')
        )
        if joinable:  # the paragraph goes on: the words that did not fit start the next line
            lines[k + 1] = lead + overflow + " " + n_body
        else:
            lines.insert(k + 1, lead + overflow)
            kinds.insert(k + 1, kind)
        k += 1
    path.write_text("\n".join(lines), encoding="utf-8")
    return left


# ---- helpers -------------------------------------------------------------------------------------
def git(root: Path, *args: str) -> str:
    r = subprocess.run(["git", *args], cwd=root, capture_output=True, text=True)
    if r.returncode:
        raise Stop(f"git {' '.join(args)}: {r.stderr.strip()}")
    return r.stdout.strip()


def check_templates(root: Path, templates: Path, fmoves: dict[str, str]) -> list[str]:
    """Every name a template re-exports is defined or imported at the top of its module."""
    problems = []
    for t in sorted(templates.glob("*/__init__.py")):
        pkg = t.parent.name
        table = {}
        for node in ast.parse(t.read_text()).body:
            if isinstance(node, ast.Assign) and getattr(node.targets[0], "id", "") == "_EXPORTS":
                table = ast.literal_eval(node.value)
        for name, mod in table.items():
            f = root / PKG / pkg / (mod.replace(".", "/") + ".py")
            if not f.exists():
                f = root / PKG / pkg / mod.replace(".", "/") / "__init__.py"
            if not f.exists():
                problems.append(f"{t}: {name}: no module {pkg}.{mod}")
                continue
            top = set()
            for node in ast.parse(f.read_text()).body:
                if isinstance(node, (ast.FunctionDef, ast.ClassDef, ast.AsyncFunctionDef)):
                    top.add(node.name)
                elif isinstance(node, (ast.Import, ast.ImportFrom)):
                    top |= {(a.asname or a.name).split(".")[0] for a in node.names}
                elif isinstance(node, (ast.Assign, ast.AnnAssign)):
                    if (
                        getattr(
                            node.targets[0] if isinstance(node, ast.Assign) else node.target,
                            "id",
                            "",
                        )
                        == "__all__"
                    ):  # a lazy face names them here
                        top |= set(ast.literal_eval(node.value))
                    for tg in node.targets if isinstance(node, ast.Assign) else [node.target]:
                        for n in ast.walk(tg):
                            if isinstance(n, ast.Name):
                                top.add(n.id)
                elif isinstance(node, ast.If):  # TYPE_CHECKING / try blocks: names they bind
                    for n in ast.walk(node):
                        if isinstance(n, (ast.FunctionDef, ast.ClassDef)):
                            top.add(n.name)
            if name not in top:
                problems.append(f"{t.relative_to(templates)}: {name} is not in {pkg}.{mod}")
        subs = (
            {p.stem for p in (root / PKG / pkg).glob("*.py")}
            | {p.name for p in (root / PKG / pkg).iterdir() if (p / "__init__.py").exists()}
            if (root / PKG / pkg).exists()
            else set()
        )
        clash = sorted(set(table) & subs)
        if clash:
            problems.append(f"{t}: exported names equal to submodules (patching breaks): {clash}")
    return problems


# ---- main ---------------------------------------------------------------------------------------
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--root", default=".", help="repository root (default: here)")
    ap.add_argument("--mapping", default=str(HERE / "mapping.txt"))
    ap.add_argument("--templates", default=str(HERE / "templates"))
    ap.add_argument(
        "--dry-run", action="store_true", help="print what would change, change nothing"
    )
    ap.add_argument("--allow-dirty", action="store_true", help="run on a tree with local changes")
    ap.add_argument("--no-ruff", action="store_true", help="do not re-sort/format changed files")
    ap.add_argument("--no-verify", action="store_true", help="do not import every module after")
    args = ap.parse_args(argv)
    root = Path(args.root).resolve()
    if not (root / PKG / "__init__.py").is_file() or not (root / "pyproject.toml").is_file():
        raise Stop(f"{root}: not a treeinfer checkout (no {PKG}/__init__.py or pyproject.toml)")
    moves, future = read_mapping(Path(args.mapping))
    templates = Path(args.templates)
    state = check_state(root, moves, future)
    if state == "applied":
        print("relayout: already applied (every move of the mapping is made); nothing to do")
        return 0
    if not args.allow_dirty and git(root, "status", "--porcelain", "--untracked-files=no", PKG):
        raise Stop("local changes under treeinfer/: commit or stash them first (--allow-dirty)")
    unknown = unknown_top_level(root, moves)
    if unknown:
        raise Stop(
            "modules at the top of treeinfer/ that the mapping does not place; add a line for "
            "each to the mapping (old -> new):\n  " + "\n  ".join(unknown)
        )
    tracked = [f for f in git(root, "ls-files").split("\n") if f]
    untracked_py = [
        f
        for f in git(root, "ls-files", "--others", "--exclude-standard", PKG).split("\n")
        if f.endswith(".py")
    ]
    if untracked_py:
        raise Stop(
            "untracked modules in treeinfer/ (git add or remove them):\n  "
            + "\n  ".join(untracked_py)
        )
    fmoves = file_moves(root, moves, future)
    mods = Modules(fmoves, tracked)
    log: list[str] = []
    rw = Rewriter(mods, log, template_exports(templates))

    # new texts, computed from the original layout
    new_texts: dict[str, str] = {}
    for f in tracked:
        p = root / f
        if f.startswith(NEVER_REWRITE) or p.suffix not in TEXT_SUFFIXES or not p.is_file():
            continue
        if p.is_symlink():
            continue
        text = p.read_text(encoding="utf-8")
        rw.public = f.startswith(PUBLIC_FOLDERS) or p.suffix in (".md", ".ipynb")
        if p.suffix == ".py":
            new = rw.python(text, f if f.startswith(PKG + "/") else None, fmoves.get(f, f))
        else:
            new = rw.other(text, p.suffix, f)
        if new != text:
            new_texts[fmoves.get(f, f)] = new

    # templates of the new packages' __init__.py (not where a module becomes the face)
    inits = {}
    for t in sorted(templates.glob("*/__init__.py")):
        dest = f"{PKG}/{t.parent.name}/__init__.py"
        if dest in fmoves.values():
            raise Stop(f"{t}: {dest} is made by a move of the mapping; drop the template")
        if (root / dest).exists():
            raise Stop(f"{dest} exists already; the template {t} would overwrite it")
        inits[dest] = t.read_text()
    new_pkgs = {n.rsplit("/", 1)[0] for n in fmoves.values()}
    missing = sorted(
        d
        for d in new_pkgs
        if not (root / d / "__init__.py").exists()
        and f"{d}/__init__.py" not in inits
        and f"{d}/__init__.py" not in fmoves.values()
    )
    if missing:
        raise Stop("new folders without an __init__.py template: " + ", ".join(missing))

    if args.dry_run:
        for o, n in sorted(fmoves.items()):
            print(f"git mv {o} {n}")
        for f in sorted(new_texts):
            print(f"rewrite {f}")
        for f in sorted(inits):
            print(f"write {f}")
        print("\n".join(sorted(set(log))))
        return 0

    # the moves: files inside a moving folder that go elsewhere first, then folders, then files
    dir_moves = {o: n for o, n in moves.items() if o.endswith("/") and (root / o).exists()}
    inside = {
        o: n for o, n in fmoves.items() if any(o.startswith(d) for d in dir_moves) and o in moves
    }
    for o, n in inside.items():
        (root / n).parent.mkdir(parents=True, exist_ok=True)
        git(root, "mv", o, n)
    for o, n in dir_moves.items():
        (root / n).parent.mkdir(parents=True, exist_ok=True)
        git(root, "mv", o.rstrip("/"), n.rstrip("/"))
    for o, n in moves.items():
        if o.endswith("/") or o in inside or not (root / o).exists():
            continue
        (root / n).parent.mkdir(parents=True, exist_ok=True)
        git(root, "mv", o, n)
    for f, text in {**new_texts, **inits}.items():
        (root / f).parent.mkdir(parents=True, exist_ok=True)
        (root / f).write_text(text, encoding="utf-8")
    git(root, "add", *inits)
    problems = check_templates(root, templates, fmoves)
    if problems:
        raise Stop(
            "the moves are made, but the templates do not match the code:\n  "
            + "\n  ".join(problems)
        )
    changed_py = sorted(f for f in {**new_texts, **inits} if f.endswith(".py"))
    if not args.no_ruff and changed_py:
        for cmd in (["ruff", "check", "--select", "I", "--fix", "-q"], ["ruff", "format", "-q"]):
            exe = shutil.which("ruff") or str(Path(sys.executable).with_name("ruff"))
            r = subprocess.run(
                [exe, *cmd[1:], *changed_py], cwd=root, capture_output=True, text=True
            )
            if r.returncode:
                log.append(f"{' '.join(cmd)}: {r.stdout.strip()} {r.stderr.strip()}")
    long_left = []
    for f in changed_py:
        long_left += wrap_long_lines(root / f, f)
    if long_left:
        log.append(
            f"{len(long_left)} line(s) over {MAX_LINE} characters outside comments and "
            "docstrings, to wrap by hand: " + ", ".join(long_left)
        )
    print(
        f"relayout: moved {len(fmoves)} files, rewrote {len(new_texts)}, wrote {len(inits)} "
        "__init__.py"
    )
    for line in sorted(set(log)):
        print("note:", line)
    if not args.no_verify:
        code = (
            "import importlib, pkgutil, sys, treeinfer\n"
            "bad = []\n"
            "for m in pkgutil.walk_packages(treeinfer.__path__, 'treeinfer.'):\n"
            "    if m.name.endswith('__main__'): continue\n"
            "    try: importlib.import_module(m.name)\n"
            "    except Exception as e: bad.append(f'{m.name}: {type(e).__name__}: {e}')\n"
            "for n in getattr(treeinfer, '_EXPORTS', {}):\n"
            "    try: getattr(treeinfer, n)\n"
            "    except Exception as e: bad.append(f'treeinfer.{n}: {type(e).__name__}: {e}')\n"
            "print('\\n'.join(bad)); sys.exit(1 if bad else 0)\n"
        )
        r = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True)
        if r.returncode:
            raise Stop(
                "moved and rewritten, but some modules do not import:\n"
                + r.stdout
                + r.stderr[-3000:]
            )
        print("relayout: every module of treeinfer imports")
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except Stop as e:
        print(f"relayout: {e}", file=sys.stderr)
        sys.exit(1)
