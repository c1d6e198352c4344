"""GPU start-up settings treeinfer applies on import (issue 15, cold start): XLA's GPU client
grows its memory pool on demand instead of reserving 75% of the card in the first transfer
(1.4-1.9 s of a cold process on an H200), unless the user chose a memory setting."""

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
def test_importing_treeinfer_sets_it_before_jax_starts(user, expected):
    env = {k: v for k, v in os.environ.items() if k not in treeinfer._GPU_MEMORY_SETTINGS}
    if user is not None:
        env["XLA_PYTHON_CLIENT_PREALLOCATE"] = user
    code = "import os, treeinfer; print(os.environ.get('XLA_PYTHON_CLIENT_PREALLOCATE'))"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == expected
