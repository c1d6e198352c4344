"""The Python snippets of README.md and docs/*.md run as written, from a folder outside the
repository (issue 26): a reader copies them into a notebook anywhere, not into the checkout.

A fenced ``python`` block runs when the line before its fence is ``<!-- run -->`` (a fast
snippet, in the default run) or ``<!-- run: slow -->`` (it compiles a sampler: with the slow
tests). The tagged blocks of one page run in order in one fresh interpreter, so a page's
snippets may build on each other as a reader's session would. Untagged blocks (a cluster job,
a GPU-only call) are shown, not run. Examples are found through the package
(``ti.example_path``), never through a path in the checkout."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
TAG = re.compile(r"^<!-- run(?::\s*(slow))? -->\s*$")


def snippets(path: Path) -> list[tuple[str, bool]]:
    """``(code, slow)`` of every tagged ``python`` block of ``path``, in order."""
    lines = path.read_text(encoding="utf-8").splitlines()
    out = []
    for i, line in enumerate(lines):
        tag = TAG.match(line)
        if not tag:
            continue
        if i + 1 >= len(lines) or lines[i + 1].strip() != "```python":
            raise AssertionError(f"{path.name}:{i + 1}: a run tag must precede a ```python fence")
        end = next(j for j in range(i + 2, len(lines)) if lines[j].strip() == "```")
        out.append(("\n".join(lines[i + 2 : end]), tag.group(1) == "slow"))
    return out


def _cases():
    for page in PAGES:
        found = snippets(page)
        if found:
            slow = any(s for _, s in found)
            marks = [pytest.mark.slow] if slow else []
            yield pytest.param(page, id=str(page.relative_to(ROOT)), marks=marks)


def test_the_readme_and_the_docs_have_snippets_to_run():
    assert snippets(ROOT / "README.md"), "README.md has no <!-- run --> python block"
    assert sum(len(snippets(p)) for p in PAGES if p.parent != ROOT) >= 3


def test_a_tag_without_a_python_block_is_refused(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("<!-- run -->\n```bash\nls\n```\n")
    with pytest.raises(AssertionError, match="must precede"):
        snippets(page)


@pytest.mark.parametrize("page", list(_cases()))
def test_page_snippets_run_outside_the_repository(page, tmp_path):
    assert ROOT not in tmp_path.parents  # the point of the test
    code = "\n\n".join(c for c, _ in snippets(page))
    script = tmp_path / "snippets.py"
    script.write_text(code, encoding="utf-8")
    env = dict(os.environ)
    # this checkout's treeinfer (an installed one would be found anyway); nothing else of the
    # repository is importable, and the working folder is the temporary one
    env["PYTHONPATH"] = str(ROOT)
    env.setdefault("JAX_PLATFORMS", "cpu")
    env["MPLBACKEND"] = "Agg"
    done = subprocess.run(
        [sys.executable, str(script)],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=1200,
    )
    assert done.returncode == 0, f"{page.name} snippets failed:\n{done.stderr[-4000:]}"


def commands(path: Path) -> list[tuple[int, list[str]]]:
    """``(line, argv)`` of every ``treeinfer ...`` command in the ``bash`` blocks of ``path``
    (continuation lines joined, comments dropped)."""
    import shlex

    out, inside, pending, start = [], False, "", 0
    for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if line.strip().startswith("```"):
            inside = line.strip() == "```bash"
            continue
        if not inside:
            continue
        text = (pending + " " + line.strip()) if pending else line.strip()
        start = start if pending else i
        if text.endswith("\\"):
            pending = text[:-1]
            continue
        pending = ""
        for part in re.split(r"&&|;", text.split(" #")[0]):
            argv = shlex.split(part, comments=True)
            if argv[:1] == ["treeinfer"]:
                out.append((start, argv[1:]))
    return out


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_documented_commands_parse(page):
    """Every ``treeinfer`` command shown in a bash block names a command and options that exist
    (parsed by the real parser; nothing runs), so a renamed option cannot linger in the docs."""
    import contextlib
    import io

    from treeinfer.cli.main import build_parser

    for line, argv in commands(page):
        parser = build_parser(argv[0] if argv else None, lazy=True)
        with contextlib.redirect_stderr(io.StringIO()) as err:
            try:
                parser.parse_args(argv)
            except SystemExit as e:
                raise AssertionError(f"{page.name}:{line}: treeinfer {' '.join(argv)}\n"
                                     f"{err.getvalue()}") from e  # fmt: skip
