"""Provenance of a run: file hashes, the data manifest, package versions, JSON in and out,
the config hash.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
from pathlib import Path

import jax
import numpy as np

from .. import __version__
from .jsonio import jsonable as _jsonable

# Options that do not change the sampled particles: left out of the config hash, so a resume
# may differ in them (max_unstable_share may even be overridden on --resume).
_UNHASHED_OPTIONS = ("out", "force", "max_unstable_share", "progress")


# ==== files, hashes, versions =====================================================================
def file_sha256(path: str | os.PathLike) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def data_manifest(directory: str | os.PathLike, pattern: str = "*.csv") -> list[dict]:
    """``[{name, sha256, bytes}]`` of the files :func:`read_trajectory_dir` reads, in its order."""
    directory = Path(directory)
    files = sorted(p for p in directory.glob(pattern) if p.is_file())
    return [{"name": p.name, "sha256": file_sha256(p), "bytes": p.stat().st_size} for p in files]


def _dist_version(name: str) -> str | None:
    try:
        from importlib.metadata import version

        return version(name)
    except Exception:  # noqa: BLE001 -- not installed as a distribution: record that
        return None


def versions(extended: bool = False) -> dict:
    """The one record of what ran: treeinfer, jax, mujoco, mujoco-mjx, numpy, python; with
    ``extended`` also the platform, jaxlib, blackjax, optax and the JAX backend and devices
    (studies and benchmarks)."""
    import mujoco

    out = {
        "treeinfer": __version__,
        "jax": jax.__version__,
        "mujoco": mujoco.__version__,
        "mujoco_mjx": _dist_version("mujoco-mjx"),
        "numpy": np.__version__,
        "python": platform.python_version(),
    }
    if extended:
        out.update(
            platform=platform.platform(),
            jaxlib=_dist_version("jaxlib"),
            blackjax=_dist_version("blackjax"),
            optax=_dist_version("optax"),
        )
        try:
            out["jax_backend"] = jax.default_backend()
            out["jax_devices"] = [str(d) for d in jax.devices()]
        except Exception:  # noqa: BLE001 -- recording versions must never fail a study
            pass
    return out


def config_hash(config: dict) -> str:
    """sha256 of what determines the sampled particles: the options (less ``out``, ``force``,
    ``max_unstable_share``), the tree, the data files' hashes, and the problem and sampler
    settings the code derived from them."""
    ident = {
        "options": {k: v for k, v in config["options"].items() if k not in _UNHASHED_OPTIONS},
        "tree": tree_to_dict_json(config["tree_dict"]),
        "data": [(f["name"], f["sha256"]) for f in config["data"]["files"]],
        "problem": config.get("problem"),
        "sampler": config.get("sampler"),
    }
    blob = json.dumps(_jsonable(ident), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(blob.encode("utf-8")).hexdigest()


def tree_to_dict_json(d) -> str:
    return json.dumps(_jsonable(d), sort_keys=True, separators=(",", ":"))
