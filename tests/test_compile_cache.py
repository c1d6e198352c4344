"""The persistent compilation cache: on by default in the command line and
``treeinfer.configure_runtime()`` (not on ``import treeinfer``), keyed by the
treeinfer/jax/jaxlib versions, and hit by a second process (what a reinstall of the same
versions is, as far as JAX can tell)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import jax

import treeinfer

ROOT = Path(__file__).resolve().parent.parent

PROBE = """
import json, jax, jax.numpy as jnp
import treeinfer
treeinfer.configure_runtime()
hits = []
jax.monitoring.register_event_listener(
    lambda e, **k: hits.append(e) if e == "/jax/compilation_cache/cache_hits" else None)
jax.jit(lambda x: jnp.sin(x) * 3.0 + x ** 2)(jnp.arange(7.0)).block_until_ready()
print(json.dumps({"dir": jax.config.jax_compilation_cache_dir, "hits": len(hits)}))
"""


def _probe(env_cache: str) -> dict:
    env = {
        **os.environ,
        "TREEINFER_JAX_CACHE": env_cache,
        "JAX_PLATFORMS": "cpu",
        "PYTHONPATH": str(ROOT),
    }
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    out = subprocess.run(
        [sys.executable, "-c", PROBE],
        env=env,
        capture_output=True,
        text=True,
        check=True,
        timeout=300,
        cwd=ROOT,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_cache_tag_names_the_versions():
    tag = treeinfer._cache_tag()
    assert (
        tag == f"treeinfer-{treeinfer.__version__}_jax-{jax.__version__}_jaxlib-"
        f"{__import__('jaxlib').__version__}"
    )


def test_cache_is_on_by_default_and_a_second_process_hits_it(tmp_path):
    first = _probe(str(tmp_path))
    assert first["dir"] == str(tmp_path / treeinfer._cache_tag())
    assert any((tmp_path / treeinfer._cache_tag()).iterdir())  # the program was written
    second = _probe(str(tmp_path))
    assert second["hits"] >= 1 and first["hits"] == 0


def test_cache_can_be_turned_off(tmp_path):
    assert _probe("off")["dir"] is None
