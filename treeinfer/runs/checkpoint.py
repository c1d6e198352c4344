"""Checkpoints of a run in progress: ``RUN.partial/checkpoint.npz`` (the sampler state pytree
flattened, the iteration, the config hash, a coarse trace) and the driver callback that writes it.
"""

from __future__ import annotations

import dataclasses
import io
import json
import os
import time
import zipfile
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import __version__
from ..errors import ConfigError
from ..io.atomic import (
    atomic_write_bytes,
)

CHECKPOINT_FORMAT = 1
CHECKPOINT_FILE = "checkpoint.npz"
PARTIAL_SUFFIX = ".partial"


# ==== checkpoints =================================================================================
def partial_dir(run_dir: str | os.PathLike) -> Path:
    """``RUN.partial``: where a run in progress keeps its config and checkpoint."""
    p = Path(run_dir)
    return p.with_name(p.name + PARTIAL_SUFFIX)


class Checkpoint(NamedTuple):
    """A loaded checkpoint: ``state`` (the sampler's pytree) after ``iteration`` completed
    iterations; the coarse trace ``trace_iterations [m]``, ``trace_positions [m, P, D]``,
    ``trace_logdensity [m, P]`` (the state at each checkpoint so far)."""

    iteration: int
    state: Any
    config_hash: str
    trace_iterations: np.ndarray
    trace_positions: np.ndarray
    trace_logdensity: np.ndarray


def _is_key(x) -> bool:
    return jax.dtypes.issubdtype(getattr(x, "dtype", np.float32), jax.dtypes.prng_key)


def flatten_state(state) -> tuple[dict[str, np.ndarray], list[dict]]:
    """Sampler state pytree -> (``{"leaf_<i>": array}``, leaf specs). Key leaves are stored as
    their ``key_data`` with ``{"kind": "key", "impl": ...}``."""
    arrays, specs = {}, []
    for i, leaf in enumerate(jax.tree_util.tree_leaves(state)):
        if _is_key(leaf):
            arrays[f"leaf_{i}"] = np.asarray(jax.random.key_data(leaf))
            specs.append({"kind": "key", "impl": str(jax.random.key_impl(leaf))})
        else:
            a = np.asarray(leaf)
            arrays[f"leaf_{i}"] = a
            specs.append({"kind": "array", "dtype": str(a.dtype), "shape": list(a.shape)})
    return arrays, specs


def unflatten_state(
    arrays: dict[str, np.ndarray], specs: list[dict], template, where: str = "checkpoint"
):
    """Inverse of :func:`flatten_state` onto ``template``'s structure (a state or its
    ``jax.eval_shape``); every leaf's kind, shape and dtype must match."""
    t_leaves, treedef = jax.tree_util.tree_flatten(template)
    if len(t_leaves) != len(specs):
        raise ConfigError(
            f"{where}: holds {len(specs)} state arrays but this sampler's state has "
            f"{len(t_leaves)}; it was written by another sampler or treeinfer version"
        )
    leaves = []
    for i, (t, spec) in enumerate(zip(t_leaves, specs)):
        a = arrays[f"leaf_{i}"]
        if _is_key(t):
            if spec.get("kind") != "key":
                raise ConfigError(f"{where}: state array {i} should be a random key")
            leaves.append(jax.random.wrap_key_data(jnp.asarray(a), impl=spec["impl"]))
            continue
        if (
            spec.get("kind") != "array"
            or tuple(a.shape) != tuple(t.shape)
            or a.dtype != np.dtype(t.dtype)
        ):
            raise ConfigError(
                f"{where}: state array {i} is {a.dtype}{list(a.shape)}, expected "
                f"{np.dtype(t.dtype)}{list(t.shape)} (different particles count or sampler?)"
            )
        leaves.append(jnp.asarray(a))
    return jax.tree_util.tree_unflatten(treedef, leaves)


def _zero_value_and_grad(theta):
    return jnp.zeros(theta.shape[:1], theta.dtype), jnp.zeros_like(theta)


def _zero_log_density(theta):
    return jnp.zeros(theta.shape[:1], theta.dtype)


def state_template(problem, sampler: str, theta0, **sampler_options):
    """Shapes and structure of ``sampler``'s state for particles like ``theta0 [P, D]``, without
    touching the simulator (the target is swapped for a zero function in ``jax.eval_shape``)."""
    dummy = dataclasses.replace(
        problem, value_and_grad=_zero_value_and_grad, log_density=_zero_log_density
    )
    algorithm = dummy.sampler(sampler, **sampler_options)
    return jax.eval_shape(algorithm.init, jax.random.key(0), jnp.asarray(theta0))


def _npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def save_checkpoint(
    path: str | os.PathLike,
    iteration: int,
    state,
    config_hash: str,
    trace_iterations=(),
    trace_positions=None,
    trace_logdensity=None,
) -> Path:
    """Write ``state`` after ``iteration`` completed iterations to ``path`` (.npz) atomically."""
    arrays, specs = flatten_state(jax.device_get(state))
    meta = {
        "format": CHECKPOINT_FORMAT,
        "iteration": int(iteration),
        "config_hash": config_hash,
        "leaves": specs,
        "treeinfer": __version__,
        "written_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    arrays["meta"] = np.asarray(json.dumps(meta))
    arrays["trace_iterations"] = np.asarray(trace_iterations, np.int64)
    if trace_positions is not None and len(trace_iterations):
        arrays["trace_positions"] = np.asarray(trace_positions)
        arrays["trace_logdensity"] = np.asarray(trace_logdensity)
    return atomic_write_bytes(path, _npz_bytes(arrays))


def _open_checkpoint(path: Path) -> tuple[dict, dict[str, np.ndarray]]:
    from .integrity import validate_checkpoint_file

    if not Path(path).exists():
        raise ConfigError(f"{path}: no such checkpoint")
    validate_checkpoint_file(path)  # 0-byte, FIFO, foreign file: a clean error naming it
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        meta = json.loads(str(arrays.pop("meta")))
        if not isinstance(meta, dict):
            raise ValueError("meta is not a JSON object")  # noqa: TRY004 -- caught below
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such checkpoint") from None
    except (
        OSError,
        ValueError,
        KeyError,
        EOFError,
        zipfile.BadZipFile,
    ) as e:  # truncated / foreign file
        raise ConfigError(f"{path}: not a readable treeinfer checkpoint ({e})") from None
    if meta.get("format") != CHECKPOINT_FORMAT:
        raise ConfigError(
            f"{path}: checkpoint format {meta.get('format')!r}, expected {CHECKPOINT_FORMAT}"
        )
    for key, kind in (("config_hash", str), ("iteration", int), ("leaves", list)):
        if not isinstance(meta.get(key), kind) or isinstance(meta.get(key), bool):
            raise ConfigError(
                f"{path}: checkpoint field 'meta.{key}' is missing or malformed "
                f"({meta.get(key)!r}); delete the checkpoint to restart from iteration 0"
            )
    return meta, arrays


def read_checkpoint_info(path: str | os.PathLike) -> dict:
    """The checkpoint's ``meta`` (iteration, config_hash, leaf specs) without rebuilding a state."""
    return _open_checkpoint(Path(path))[0]


def load_checkpoint(
    path: str | os.PathLike, template, expected_hash: str | None = None
) -> Checkpoint:
    """Read a checkpoint onto ``template`` (see :func:`state_template`); refuse one written for
    another config (``expected_hash``)."""
    path = Path(path)
    meta, arrays = _open_checkpoint(path)
    if expected_hash is not None and meta["config_hash"] != expected_hash:
        raise ConfigError(
            f"{path}: written for another configuration (config hash {meta['config_hash'][:12]}, "
            f"config.json gives {expected_hash[:12]}); the folder was modified, start a new run"
        )
    state = unflatten_state(arrays, meta["leaves"], template, str(path))
    it = arrays.get("trace_iterations", np.zeros(0, np.int64))
    n_p, dim = state.position.shape
    pos = arrays.get("trace_positions", np.zeros((0, n_p, dim), np.float32))
    ld = arrays.get("trace_logdensity", np.zeros((0, n_p), np.float32))
    return Checkpoint(int(meta["iteration"]), state, meta["config_hash"], it, pos, ld)


class Checkpointer:
    """The driver's ``callback(iteration, state)``: writes ``checkpoint.npz`` atomically and
    keeps the coarse trace (the state at every checkpoint) that goes with it."""

    def __init__(
        self, path: str | os.PathLike, config_hash: str, previous: Checkpoint | None = None
    ):
        self.path = Path(path)
        self.config_hash = config_hash
        self.iterations: list[int] = (
            [] if previous is None else [int(i) for i in previous.trace_iterations]
        )
        self.positions: list[np.ndarray] = (
            [] if previous is None else list(previous.trace_positions)
        )
        self.logdensity: list[np.ndarray] = (
            [] if previous is None else list(previous.trace_logdensity)
        )
        self.last_iteration: int | None = None if previous is None else previous.iteration

    def __call__(self, iteration: int, state) -> None:
        iteration = int(iteration)
        if not self.iterations or self.iterations[-1] != iteration:
            self.iterations.append(iteration)
            self.positions.append(np.asarray(state.position))
            self.logdensity.append(np.asarray(state.logdensity))
        save_checkpoint(
            self.path,
            iteration,
            state,
            self.config_hash,
            self.iterations,
            np.stack(self.positions) if self.positions else None,
            np.stack(self.logdensity) if self.logdensity else None,
        )
        self.last_iteration = iteration
