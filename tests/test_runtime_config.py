"""Issue 25: ``import treeinfer`` changes nothing outside the package; the command line sets up
JAX's runtime (``treeinfer.configure_runtime``) and refuses an unsupported environment with one
clear message (``treeinfer.cli.environment``)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from importlib import metadata
from pathlib import Path

import pytest

from treeinfer.cli.environment import (
    UnsupportedEnvironment,
    check_environment,
    environment_problems,
)
from treeinfer.cli.main import main

ROOT = Path(__file__).resolve().parent.parent


def _python(code: str, env: dict) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True,
        timeout=300,
    )  # fmt: skip


def _clean_env(tmp_path) -> dict:
    """The test process's environment without what conftest or an earlier configure set."""
    drop = ("JAX_COMPILATION_CACHE_DIR", "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS",
            "JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "XLA_PYTHON_CLIENT_PREALLOCATE",
            "XLA_PYTHON_CLIENT_MEM_FRACTION", "XLA_CLIENT_MEM_FRACTION",
            "XLA_PYTHON_CLIENT_ALLOCATOR", "TREEINFER_JAX_CACHE")  # fmt: skip
    env = {k: v for k, v in os.environ.items() if k not in drop}
    return {**env, "HOME": str(tmp_path), "PYTHONPATH": str(ROOT), "JAX_PLATFORMS": "cpu"}


def test_importing_treeinfer_leaves_the_environment_unchanged(tmp_path):
    """A fresh process: the environment and JAX's cache setting are the same before and after
    importing treeinfer and its submodules, and no cache folder appears in the home."""
    # JAX itself sets TF_CPP_MIN_LOG_LEVEL and TPU_SKIP_MDS_QUERY when imported: imported first,
    # so that only what treeinfer does is compared (the test passed in a full run, where an
    # earlier test had imported JAX into the parent whose environment the child inherits, and
    # failed alone)
    code = (
        "import json, os\n"
        "import jax\n"
        "before = dict(os.environ)\n"
        "import treeinfer, treeinfer.tree.description, treeinfer.inference.diagnostics\n"
        "import treeinfer.inference.diagnostics.arviz_compat\n"
        "import treeinfer.inference.problem, jax\n"
        "after = dict(os.environ)\n"
        "print(json.dumps({'changed': sorted(k for k in before.keys() | after.keys()\n"
        "                                  if before.get(k) != after.get(k)),\n"
        "                  'cache': jax.config.jax_compilation_cache_dir}))\n"
    )
    out = _python(code, _clean_env(tmp_path))
    assert out.returncode == 0, out.stderr[-3000:]
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got == {"changed": [], "cache": None}
    assert not (tmp_path / ".cache" / "treeinfer").exists()


def test_the_command_line_configures_the_runtime(tmp_path):
    """``main`` (the ``treeinfer`` entry point) turns the compile cache on in the user's cache
    folder and lets GPU memory grow on demand; a user's own memory setting is kept."""
    code = (
        "import os, sys\n"
        "from treeinfer.cli.main import main\n"
        f"rc = main(['tree', '--kind', 'fractal', '--depth', '1', '--out', {str(tmp_path / 't.yaml')!r}])\n"  # noqa: E501
        "print(rc, os.environ.get('JAX_COMPILATION_CACHE_DIR'),\n"
        "      os.environ.get('XLA_PYTHON_CLIENT_PREALLOCATE'))\n"
    )
    env = _clean_env(tmp_path)
    out = _python(code, env)
    assert out.returncode == 0, out.stderr[-3000:]
    rc, cache, prealloc = out.stdout.split()[-3:]
    assert rc == "0" and prealloc == "false"
    assert Path(cache).parent == tmp_path / ".cache" / "treeinfer" / "jax"
    out = _python(code, {**env, "XLA_PYTHON_CLIENT_PREALLOCATE": "true"})
    assert out.stdout.split()[-1] == "true"


def test_configure_runtime_returns_what_it_set(tmp_path, monkeypatch):
    import treeinfer

    for name in ("XLA_PYTHON_CLIENT_PREALLOCATE", "XLA_PYTHON_CLIENT_MEM_FRACTION",
                 "XLA_CLIENT_MEM_FRACTION", "XLA_PYTHON_CLIENT_ALLOCATOR"):  # fmt: skip
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("TREEINFER_JAX_CACHE", "off")  # leaves this session's JAX cache alone
    assert treeinfer.configure_runtime() == {"cache_dir": None, "gpu_preallocate": False}
    assert os.environ["XLA_PYTHON_CLIENT_PREALLOCATE"] == "false"


# ---- supported versions -------------------------------------------------------------------------


def test_this_environment_is_supported():
    assert environment_problems() == []
    check_environment()


@pytest.fixture
def fake_requirements(monkeypatch):
    """treeinfer's metadata replaced by the given Requires-Python and Requires-Dist lines."""

    def install(requires_python: str, requires: list[str]):
        real_metadata = metadata.metadata

        def fake_metadata(name):
            if name != "treeinfer":
                return real_metadata(name)
            return {"Requires-Python": requires_python}

        monkeypatch.setattr(metadata, "metadata", fake_metadata)
        monkeypatch.setattr(metadata, "requires", lambda name: requires)

    return install


def test_each_unmet_requirement_is_named_with_found_and_needed_versions(fake_requirements):
    numpy_version = metadata.version("numpy")
    fake_requirements(
        ">=3.99",
        [
            "numpy>=99",
            "no-such-package-treeinfer-test>=1.2",
            "pytest>=999; extra == 'dev'",  # an extra that is not installed: not required
            f"numpy>={numpy_version}",
        ],
    )
    problems = environment_problems()
    python = ".".join(map(str, sys.version_info[:3]))
    assert problems == [
        f"Python {python} ({sys.executable}): treeinfer needs Python >=3.99",
        f"numpy {numpy_version} is installed; treeinfer needs numpy >=99 (pip install 'numpy>=99')",
        "no-such-package-treeinfer-test is not installed; treeinfer needs "
        "no-such-package-treeinfer-test >=1.2 (pip install 'no-such-package-treeinfer-test>=1.2')",
    ]
    with pytest.raises(UnsupportedEnvironment, match="numpy >=99"):
        check_environment()


def test_the_command_line_stops_with_exit_2_before_running(fake_requirements, tmp_path, capsys):
    fake_requirements(">=3.11", ["numpy>=99"])
    out = tmp_path / "t.yaml"
    assert main(["tree", "--kind", "fractal", "--depth", "1", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: unsupported environment:") and "needs numpy >=99" in err
    assert "Traceback" not in err and not out.exists()
