"""GPU start-up settings the command line and ``treeinfer.configure_runtime`` apply (issue 15,
cold start; not ``import treeinfer`` since issue 25): XLA's GPU client grows its memory pool on
demand instead of reserving 75% of the card in the first transfer (1.4-1.9 s of a cold process
on an H200), unless the user chose a memory setting."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

import treeinfer


@pytest.fixture
def clean_env(monkeypatch):
    for name in treeinfer._GPU_MEMORY_SETTINGS:
        monkeypatch.delenv(name, raising=False)
    return monkeypatch


def test_memory_pool_grows_on_demand_by_default(clean_env):
    assert treeinfer._grow_gpu_memory_on_demand() is True
    assert os.environ["XLA_PYTHON_CLIENT_PREALLOCATE"] == "false"


@pytest.mark.parametrize(
    "name, value",
    [
        ("XLA_PYTHON_CLIENT_PREALLOCATE", "true"),
        ("XLA_PYTHON_CLIENT_MEM_FRACTION", "0.5"),
        ("XLA_PYTHON_CLIENT_ALLOCATOR", "platform"),
    ],
)
def test_a_users_memory_setting_is_kept(clean_env, name, value):
    clean_env.setenv(name, value)
    assert treeinfer._grow_gpu_memory_on_demand() is False
    assert os.environ[name] == value
    if name != "XLA_PYTHON_CLIENT_PREALLOCATE":
        assert "XLA_PYTHON_CLIENT_PREALLOCATE" not in os.environ


@pytest.mark.parametrize("user, expected", [(None, "false"), ("true", "true")])
def test_configure_runtime_sets_it_before_jax_starts(user, expected):
    """A fresh process: ``import treeinfer`` leaves the setting alone, ``configure_runtime()``
    sets it (before JAX is imported) unless the user chose one."""
    env = {k: v for k, v in os.environ.items() if k not in treeinfer._GPU_MEMORY_SETTINGS}
    if user is not None:
        env["XLA_PYTHON_CLIENT_PREALLOCATE"] = user
    code = (
        "import os, sys, treeinfer\n"
        "print(os.environ.get('XLA_PYTHON_CLIENT_PREALLOCATE'))\n"
        "treeinfer.configure_runtime(compilation_cache=False)\n"
        "print(os.environ.get('XLA_PYTHON_CLIENT_PREALLOCATE'), 'jax' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split("\n")[:2] == [str(user), f"{expected} False"]


@pytest.mark.parametrize("choice, expected", [(True, "true"), (False, "false")])
def test_an_explicit_choice_overrides_the_environment(clean_env, choice, expected):
    clean_env.setenv("XLA_PYTHON_CLIENT_PREALLOCATE", "false" if choice else "true")
    got = treeinfer.configure_runtime(compilation_cache=False, gpu_preallocate=choice)
    assert os.environ["XLA_PYTHON_CLIENT_PREALLOCATE"] == expected
    assert got == {"cache_dir": None, "gpu_preallocate": choice}
