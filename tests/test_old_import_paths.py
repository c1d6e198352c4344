"""Old module paths (the flat layout of release 0.1, before the layout by job of issue 26) import
for one release, as the same module object, with a DeprecationWarning naming the new path."""

from __future__ import annotations

import importlib
import subprocess
import sys
from pathlib import Path

import pytest

import treeinfer


def test_every_old_path_points_at_a_module_that_exists():
    missing = []
    for old, new in treeinfer._MOVED.items():
        try:
            importlib.import_module(f"treeinfer.{new}")
        except ImportError as e:
            missing.append(f"{old} -> {new}: {e}")
    assert not missing, missing


def test_no_old_path_shadows_a_module_of_today():
    # the finder runs first: an old name that is also a real module today would hide it
    root = Path(treeinfer.__file__).parent
    for old in treeinfer._MOVED:
        p = root.joinpath(*old.split("."))
        # a folder counts only with an __init__.py (a stale __pycache__ folder is no module)
        assert not p.with_suffix(".py").exists() and not (p / "__init__.py").exists(), old


@pytest.mark.parametrize(
    "old, new",
    [
        ("treeinfer.metrics", "treeinfer.evaluation.metrics"),
        ("treeinfer.fast_posterior", "treeinfer.inference.fast"),
        ("treeinfer.samplers.svgd", "treeinfer.inference.samplers.svgd"),
        ("treeinfer.runs.provenance", "treeinfer.io.provenance"),
    ],
)
def test_old_path_is_the_same_module_with_a_warning(old, new):
    # a fresh interpreter: in this one the module may already be imported under its old name
    code = (
        "import importlib, warnings\n"
        "with warnings.catch_warnings(record=True) as w:\n"
        "    warnings.simplefilter('always')\n"
        f"    a = importlib.import_module({old!r})\n"
        f"b = importlib.import_module({new!r})\n"
        "assert a is b, (a, b)\n"
        f"assert any({new!r} in str(x.message) and x.category is DeprecationWarning for x in w), "
        "[str(x.message) for x in w]\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


def test_other_imports_pass_the_finder_untouched_in_a_bare_interpreter():
    # -S -I: no site, no editable-install hooks, so importlib.util is not loaded beforehand (a
    # fresh virtualenv's console script met a recursion in the finder this way)
    code = "import treeinfer, importlib.util, email.message, json; print('ok')"
    r = subprocess.run(
        [sys.executable, "-S", "-I", "-c", f"import sys; sys.path[:0] = {sys.path!r}; {code}"],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr[-2000:]


def test_an_unknown_name_is_still_an_import_error():
    with pytest.raises(ImportError):
        importlib.import_module("treeinfer.no_such_module")
    with pytest.raises(AttributeError):
        treeinfer.no_such_module  # noqa: B018
