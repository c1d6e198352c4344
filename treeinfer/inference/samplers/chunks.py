"""The compiled pieces the sampler driver (:func:`treeinfer.inference.samplers.driver.run`) runs:
the scanned chunk of iterations (with or without a data argument), its compiled program looked up
in the caller's :class:`~treeinfer.sim.program_cache.ProgramCache`, and the straggler re-init step
(split from the driver as a pure move, to keep modules under 500 lines)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ...sim.program_cache import ProgramCache
from ..diagnostics import ReinitStragglers, straggler_mask
from ..diagnostics import reinit_stragglers as _reinit_positions

_INIT_TAG = np.uint32(0xFFFFFFFF)
_REINIT_TAG = 0x5EED  # straggler re-init after iteration i: fold_in(fold_in(key, tag), i)


def iteration_key(rng_key, i):
    """Key of 0-based iteration ``i``."""
    return jax.random.fold_in(rng_key, i)


def init_key(rng_key):
    """Key handed to ``algorithm.init``."""
    return jax.random.fold_in(rng_key, _INIT_TAG)


def _scalars(info) -> dict:
    fields = info._asdict() if hasattr(info, "_asdict") else {}
    return {k: v for k, v in fields.items() if jnp.ndim(v) == 0}


def _build_chunk(init, step, length: int, record_trace: bool, scalar_template: tuple):
    """Jitted chunk of ``length`` iterations, ``init`` folded in: one program per run.

    ``chunk(state, positions, fresh, rng_key, first, stop)``: when ``fresh``, ``state`` (zeros
    of the state's shapes) is replaced by ``init(init_key(rng_key), positions)`` before the
    iterations; otherwise ``positions`` is ignored and ``state`` is continued. Both the first
    chunk of a run and every later one (and a resumed run) call the same executable, so a run
    compiles once, where a separate ``init`` program compiled the whole simulator a second
    time. Iterations ``i >= stop`` are padding (held, no evaluation). Returns ``(state,
    (scalars, trace), (position [P, D], logdensity [P]))``, the last the state after the
    (optional) init: the run's initial particles and their log density on a fresh run.
    :func:`run` compiles it once per (algorithm, length, shapes) and keeps the executable in
    its ``cache``.
    """
    return jax.jit(_chunk_fn(init, step, length, record_trace, scalar_template))


def _build_data_chunk(build, length: int, record_trace: bool, scalar_template: tuple):
    """:func:`_build_chunk` of a :class:`DataSamplingAlgorithm`: ``chunk(state, positions,
    fresh, rng_key, first, stop, data)``, the sampler built on ``data`` (an argument of the
    program, not constants in it)."""

    def chunk(state, positions, fresh, rng_key, first, stop, data):
        algorithm = build(data)
        run_chunk = _chunk_fn(algorithm.init, algorithm.step, length, record_trace, scalar_template)
        return run_chunk(state, positions, fresh, rng_key, first, stop)

    return jax.jit(chunk)


def _chunk_fn(init, step, length: int, record_trace: bool, scalar_template: tuple):
    """The Python function :func:`_build_chunk` jits."""
    scalar_template = dict(scalar_template)

    def chunk(state, positions, fresh, rng_key, first, stop):
        state = jax.lax.cond(
            fresh, lambda s: init(init_key(rng_key), positions), lambda s: s, state
        )
        initial = (state.position, state.logdensity)

        def body(state, i):
            def advance(s):
                s, info = step(iteration_key(rng_key, i), s)
                return s, _scalars(info)

            def hold(s):  # padding past the end of the run: no evaluation
                return s, {k: jnp.zeros(v.shape, v.dtype) for k, v in scalar_template.items()}

            state, scalars = jax.lax.cond(i < stop, advance, hold, state)
            trace = (state.position, state.logdensity) if record_trace else None
            return state, (scalars, trace)

        state, out = jax.lax.scan(body, state, first + jnp.arange(length, dtype=jnp.int32))
        return state, out, initial

    return chunk


def _signature(args) -> tuple:
    leaves, treedef = jax.tree.flatten(args)
    return (
        treedef,
        tuple(
            (np.shape(x), str(getattr(x, "dtype", type(x))), str(getattr(x, "sharding", None)))
            for x in leaves
        ),
    )


def _compiled_chunk(cache: ProgramCache, chunk_key: tuple, args):
    """The chunk of ``chunk_key`` (:func:`_build_chunk`'s arguments) compiled for ``args``
    (arrays or shape structs), from ``cache`` (compiled and kept there on a miss)."""
    return cache.get(
        ("sampler chunk", chunk_key, _signature(args)),
        lambda: _build_chunk(*chunk_key).lower(*args).compile(),
    )


def _compiled_data_chunk(cache: ProgramCache, chunk_key: tuple, args):
    """The chunk of a :class:`DataSamplingAlgorithm` (``chunk_key``: :func:`_build_data_chunk`'s
    arguments) compiled for ``args`` (the data last), from ``cache``. Keyed by the lowered
    program's text: the algorithm is rebuilt for every data set (new closures), and the text is
    what identifies the program -- two data sets of one shape lower to the same text, so the
    second one is traced but not compiled (the persistent compile cache, keyed by the same
    program, serves a later process)."""
    import hashlib

    lowered = _build_data_chunk(*chunk_key).lower(*args)
    digest = hashlib.sha256(lowered.as_text().encode()).hexdigest()
    return cache.get(("sampler chunk, data argument", digest, _signature(args)), lowered.compile)


def _single_device(tree) -> bool:
    devices = set()
    for x in jax.tree.leaves(tree):
        if isinstance(x, jax.Array):
            devices |= set(x.sharding.device_set)
    return len(devices) <= 1


def _zeros_like_shapes(tree):
    return jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), tree)


def _key_record(rng_key) -> dict:
    if isinstance(rng_key, (int, np.integer)):
        return {"seed": int(rng_key)}
    key = rng_key
    if jnp.issubdtype(jnp.asarray(key).dtype, jax.dtypes.prng_key):
        return {
            "seed": None,
            "rng_key_data": np.asarray(jax.random.key_data(key)).tolist(),
            "rng_impl": str(jax.random.key_impl(key)),
        }
    return {"seed": None, "rng_key_data": np.asarray(key).tolist()}


def _straggler_reinit(init_of, policy: ReinitStragglers):
    """Jitted ``(state, key, iteration, extra) -> (state, n_moved)``: stragglers of ``state``
    moved next to good particles, their state rows taken from ``init = init_of(extra)`` at the
    new positions (every state leaf whose leading axis is the particle axis; scalars such as
    step counters are kept). ``extra``: ``()``, or ``(data,)`` of a
    :class:`DataSamplingAlgorithm` (an argument of the program). ``init`` (one batched target
    evaluation) runs only when some particle is flagged."""
    lower = jnp.asarray(policy.lower)
    upper = jnp.asarray(policy.upper)

    def apply(state, key, iteration, extra):
        init = init_of(*extra)
        mask = straggler_mask(
            state.logdensity,
            state.position,
            lower,
            upper,
            z_max=policy.z_max,
            min_gap=policy.min_gap,
            max_box_excess=policy.max_box_excess,
        )[0]
        k = jax.random.fold_in(jax.random.fold_in(key, _REINIT_TAG), iteration)
        n_particles = state.position.shape[0]

        def move(s):
            new_pos = _reinit_positions(k, s.position, mask, policy.jitter)
            fresh = init(jax.random.fold_in(k, 1), new_pos)

            def pick(new, old):
                if jnp.ndim(old) >= 1 and old.shape[0] == n_particles:
                    m = mask.reshape((n_particles,) + (1,) * (old.ndim - 1))
                    return jnp.where(m, new, old)
                return old

            return jax.tree.map(pick, fresh, s)

        # nothing to move, or nothing good to move them to: leave the state as it is
        do = jnp.any(mask) & ~jnp.all(mask)
        state = jax.lax.cond(do, move, lambda s: s, state)
        return state, jnp.where(do, jnp.sum(mask), 0)

    return jax.jit(apply)
