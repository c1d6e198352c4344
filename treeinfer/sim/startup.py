"""Cold start: shapes padded to a few buckets, so a new data set reuses compiled programs.

XLA compiles one program per array shape. A robot that records 3 pulls of 300 steps today and 4
pulls of 287 steps tomorrow would compile the whole finite-difference simulator again (tens of
seconds on a small CPU), even with the persistent compilation cache on, because the cache is
keyed by shape. Padding the observations to a few bucket sizes makes both data sets one shape:

* trajectories: the next of ``2^k * {1, 1.5}`` (1, 2, 3, 4, 6, 8, 12, ...: at most 50% extra
  rows, 3 stays 3; a padded row is simulated like a real one, so on a CPU it costs its share);
* time steps: the next of ``2^k * {1, 1.25, 1.5, 1.75}`` (at most 25% extra steps to simulate,
  four buckets per doubling), at least :data:`MIN_STEPS`.

Padded entries carry ``mask = False``, which every likelihood already honours (a shorter pull
stacked with a longer one is padded the same way by
:func:`treeinfer.data.trajectories.stack_trajectories`), so the log density is unchanged
(``tests/test_startup.py`` checks it for the Boltzmann and Gaussian likelihoods). Particles are
*not* padded: SVGD particles interact through the kernel, so a padded particle would change the
result; use a few particle counts (64, 128, 256) instead.

Wiring: the run layer records the bucket of an ``--init importance`` run
(:func:`treeinfer.runs.problem.shape_bucket_for`, ``shape_bucket`` in config.json's problem
settings) and :class:`treeinfer.inference.fast_evaluator.BatchEvaluator` pads the data to it;
its rollout program takes the data as arguments, so it is shared by every data set of the
bucket. New runs of the paper's dynamic model also pad the samplers' data
(:func:`treeinfer.runs.problem.sampler_bucket_for`, ``make_problem(shape_bucket=)``): the
sampler chunk takes the data as an argument (:class:`treeinfer.inference.samplers.base.
DataSamplingAlgorithm`), so a second data set of the bucket reuses its compiled program.

A new data set of a bucket compiles nothing on the CPU's ``--init importance`` path of
``treeinfer infer`` (``tests/test_cold_start.py``, counted with :mod:`treeinfer.sim.compile_stats`):

* the accuracy-controlled step's check (:func:`treeinfer.sim.accuracy.
  choose_substeps_for_accuracy`) simulates the forces padded to their bucket (the step count was
  already an argument) and cuts the padding off before the error estimate: the same step as
  before, to the bit;
* the training fit after sampling (:func:`treeinfer.evaluation.training_fit._training_fit`:
prediction,
  parameter and predictive bands, NLLs, and the small array operations between them) runs on
  the observations padded to the run's ``shape_bucket``, with the step count as a program
  argument (:func:`treeinfer.inference.problem.predict`'s ``traced_substeps``): each data set's
  accuracy-controlled step comes out different (31 and 83 substeps on two recordings of one
  tree), and a step baked into the program would compile it anew. Its values equal the
  unpadded fit's to float32 rounding (``tests/test_bucketed_programs.py``);
* ``jax.device_put`` instead of ``jnp.asarray`` for the likelihood's forces (jax compiles a
  small program per shape for ``jnp.asarray`` of a NumPy array; :func:`device_array`).

A new recording also traces nothing on the GPU's importance path: the step check's rollout
program and the importance program are kept as ``jax.export`` artifacts keyed without the step
(:func:`cached_program` for the importance program, :func:`stored_export` inlined by the
step check's jit; :meth:`treeinfer.sim.Simulator.program_key`), so only 3 programs load
from the persistent cache (BENCHMARKS.md, "H100: a new recording in under 3 s").

``treeinfer warmup`` fills the cache for a bucket from synthetic data before the first recording.

What still compiles per data set: static models, stiffness-only layouts, per-recording pulls
(``pulls.yaml``) and force-noise runs keep the data's own shape in the training fit; the
samplers' programs take the data as an argument but embed the simulator's step, so a sampler run
(or an importance run that falls back to the sampler) compiles its chunk again when the data's
accurate step differs from the cached one's. On the GPU the Pallas kernel of the importance
program and of the step check takes the step as a runtime count
(:data:`treeinfer.sim.pallas.TRACED_SUBSTEPS`, on by default since timed on an H100;
``TREEINFER_PALLAS_TRACED_SUBSTEPS=off`` makes it a constant).
``treeinfer predict`` and ``evaluate`` predict at the data's shape.
"""

from __future__ import annotations

import math

import numpy as np

from ..data.trajectories import Observations
from ..errors import ConfigError

__all__ = [
    "MIN_STEPS",
    "bucket_observations",
    "device_array",
    "steps_bucket",
    "trajectories_bucket",
]

MIN_STEPS = 64


def _count(n, what: str) -> int:
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ConfigError(f"{what}: must be an integer >= 1, got {n!r}")
    return int(n)


def trajectories_bucket(n: int) -> int:
    """The bucket of ``n`` trajectories: the smallest ``2^k`` or ``3 * 2^k`` that is >= ``n``."""
    n = _count(n, "number of trajectories")
    two = 1 << (n - 1).bit_length()
    return 3 * two // 4 if two >= 4 and 3 * two // 4 >= n else two


def steps_bucket(n: int) -> int:
    """The bucket of ``n`` time steps: the smallest ``2^k * m`` (m in 1, 1.25, 1.5, 1.75) that
    is at least ``n`` and :data:`MIN_STEPS`."""
    n = max(_count(n, "number of time steps"), MIN_STEPS)
    k = max(int(math.floor(math.log2(n))) - 2, 0)  # 2^k * {4, 5, 6, 7} spans [2^(k+2), 2^(k+3))
    while True:
        for m in (4, 5, 6, 7, 8):
            if m * (1 << k) >= n:
                return m * (1 << k)
        k += 1


def bucket_observations(
    obs: Observations, n_trajectories: int | None = None, n_steps: int | None = None
) -> Observations:
    """``obs [B, T]`` padded to ``[n_trajectories, n_steps]`` (default: the buckets of B, T).

    Padded steps hold each row's last force and displacement with velocity 0; padded rows are
    at rest (force, displacement and velocity 0); every padded entry has ``mask = False``.
    """
    b, t = np.shape(obs.force)
    nb = trajectories_bucket(b) if n_trajectories is None else _count(n_trajectories, "rows")
    nt = steps_bucket(t) if n_steps is None else _count(n_steps, "steps")
    if nb < b or nt < t:
        raise ConfigError(f"bucket_observations: [{nb}, {nt}] is smaller than the data [{b}, {t}]")

    def pad(x, hold: bool, dtype=float):
        x = np.asarray(x, dtype)
        out = np.zeros((nb, nt), dtype)
        out[:b, :t] = x
        if hold and nt > t:
            out[:b, t:] = x[:, -1:]
        return out

    return Observations(
        force=pad(obs.force, True),
        displacement=pad(obs.displacement, True),
        velocity=pad(obs.velocity, False),
        mask=pad(obs.mask, False, bool),
        dt=obs.dt,
    )


def device_array(x, dtype):
    """``x`` on the default device as ``dtype``, converted on the host: ``jnp.asarray(x,
    dtype)`` of a NumPy array or a Python number runs a small XLA program per shape and dtype
    (``convert_element_type``, ``stage``), and in a cold process each is one more program to load
    from the persistent cache (about 20 ms on a GPU; 12 of the 15 programs a new recording's
    importance fit loaded were such conversions, BENCHMARKS.md issue 15)."""
    import jax

    return jax.device_put(np.asarray(x, dtype=np.dtype(dtype)))


# ---- traced programs kept on disk ---------------------------------------------------------------
# The persistent compilation cache skips XLA's compile, not JAX's Python tracing and lowering of
# the simulator, which a cold process still pays in full (3.9 s of the importance path's 14 s on
# the loaded 2-core CPU with a warm compile cache, BENCHMARKS.md issue 15 fifth pass). A
# program whose inputs are all arguments (no data baked in, as BatchEvaluator's) can be kept as a
# serialized jax.export artifact: the next process deserializes it and goes straight to the
# (cached) compile. The key covers the caller's key, the platform, the jax/jaxlib/treeinfer
# versions (the cache folder) and a hash of treeinfer's own source, so any code change starts
# afresh.


def _source_hash() -> str:
    """sha256 of every ``.py`` file of the installed treeinfer package (computed once)."""
    global _SOURCE_HASH
    if _SOURCE_HASH is None:
        import hashlib
        from pathlib import Path

        h = hashlib.sha256()
        root = Path(__file__).resolve().parents[1]
        for p in sorted(root.rglob("*.py")):
            h.update(str(p.relative_to(root)).encode())
            h.update(p.read_bytes())
        _SOURCE_HASH = h.hexdigest()
    return _SOURCE_HASH


_SOURCE_HASH: str | None = None


def export_path(key: str):
    """``<compile cache>/<cache tag>/exports/<sha256>.jaxexport`` of ``key`` (the platform and
    treeinfer's source hash included), or None when the cache is off
    (``TREEINFER_JAX_CACHE=off``)."""
    import hashlib
    import os

    import jax

    from .. import _CACHE_OFF, _cache_tag

    env = os.environ.get("TREEINFER_JAX_CACHE")
    if env is not None and env.strip().lower() in _CACHE_OFF:
        return None
    root = env or os.path.join(os.path.expanduser("~"), ".cache", "treeinfer", "jax")
    h = hashlib.sha256(key.encode())
    h.update(jax.default_backend().encode())
    h.update(_source_hash().encode())
    return os.path.join(root, _cache_tag(), "exports", h.hexdigest() + ".jaxexport")


def cached_program(fn, example_args, key: str):
    """``jax.jit`` of ``fn`` (a function of the arrays ``example_args`` only: nothing that
    differs between calls may be closed over, or the key must name it), traced once per
    machine: the serialized ``jax.export`` of it is kept under :func:`export_path` and a later
    process deserializes it instead of tracing ``fn`` again. Falls back to a plain
    ``jax.jit(fn)`` when the cache is off, unwritable, or the program cannot be exported."""
    import jax

    exp = stored_export(fn, example_args, key)
    return jax.jit(fn) if exp is None else jax.jit(exp.call)


def stored_export(fn, example_args, key: str):
    """The ``jax.export.Exported`` of ``jax.jit(fn)`` at the shapes and dtypes of
    ``example_args`` (arrays, tracers or ``ShapeDtypeStruct``), read from :func:`export_path`
    of ``key`` when a process stored it there, else exported now and stored; None when the
    cache is off or the program cannot be exported. Calling ``.call`` of it inside a jitted
    function inlines the stored program: the caller's jit keeps it in memory, and a new process
    skips tracing ``fn``."""
    import os

    import jax
    from jax import export

    path = export_path(key)
    if path is None:
        return None
    try:
        with open(path, "rb") as f:
            return export.deserialize(bytearray(f.read()))
    except Exception:  # noqa: BLE001 - missing, truncated or foreign: trace and write it anew
        pass
    try:
        specs = [jax.ShapeDtypeStruct(np.shape(a), jax.numpy.result_type(a)) for a in example_args]
        checks = [export.DisabledSafetyCheck.custom_call("__gpu$xla.gpu.triton")]  # Pallas
        exp = export.export(jax.jit(fn), disabled_checks=checks)(*specs)
        blob = exp.serialize()
    except Exception:  # noqa: BLE001 - a program export cannot take: trace it every time
        return None
    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        tmp = f"{path}.{os.getpid()}.tmp"
        with open(tmp, "wb") as f:
            f.write(blob)
        os.replace(tmp, path)
    except OSError:
        pass
    return exp
