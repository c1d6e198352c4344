"""Run any :class:`SamplingAlgorithm` for many iterations, in jitted chunks.

Iterations run in chunks of one jitted ``lax.scan`` (compiled once per run; kept in the
caller's :class:`~treeinfer.sim.program_cache.ProgramCache` when one is given, so a resumed run
reuses it), so progress can be reported, a callback can checkpoint, and the run can be
resumed between chunks. The key for (0-based) iteration ``i`` is
``jax.random.fold_in(rng_key, i)`` and the key for ``init`` is
``fold_in(rng_key, 2**32 - 1)``, so a run resumed from a saved state at
iteration ``k`` reproduces the uninterrupted run exactly.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from ...errors import ConfigError
from ...sim.program_cache import ProgramCache
from ..diagnostics import ReinitStragglers
from .base import DataSamplingAlgorithm, SamplingAlgorithm, check_positions

# the compiled pieces, split into chunks.py as a pure move; the names stay importable from here
from .chunks import (  # noqa: F401
    _INIT_TAG,
    _REINIT_TAG,
    _build_chunk,
    _build_data_chunk,
    _chunk_fn,
    _compiled_chunk,
    _compiled_data_chunk,
    _key_record,
    _scalars,
    _signature,
    _single_device,
    _straggler_reinit,
    _zeros_like_shapes,
    init_key,
    iteration_key,
)

__all__ = ["RunResult", "init_key", "iteration_key", "run"]


class RunResult(NamedTuple):
    """Output of :func:`run` (host numpy arrays unless noted).

    final_positions: [P, D] particles after the last iteration.
    final_state: the sampler state after the last iteration (jax arrays): pass it
      back as ``initial_state`` with ``start_iteration=n_iterations`` to continue.
    trace_positions: [n_trace, P, D]; trace_logdensity: [n_trace, P];
    trace_iterations: [n_trace] completed-iteration count of each trace entry
      (0 is the initial state, recorded on fresh runs only).
    diagnostics: name -> [n_run] per-iteration scalars of the sampler's info
      (``mean_logdensity``, ``bandwidth``, ``mean_acceptance_rate``, ...), for
      iterations ``start_iteration + 1 .. n_iterations``.
    settings: everything needed to reproduce the run (sampler name and
      hyperparameters, seed or key, iteration counts, shapes; ``n_iterations_done`` is the
      completed count, below ``n_iterations`` when ``stop_when`` stopped the run).
    elapsed_s: wall-clock seconds of this call.
    stop_reason: why the run ended: ``"max_iterations"`` or the reason ``stop_when`` gave
      (``"converged at iteration ..."``).
    """

    final_positions: np.ndarray
    final_state: Any
    trace_positions: np.ndarray
    trace_logdensity: np.ndarray
    trace_iterations: np.ndarray
    diagnostics: dict
    settings: dict
    elapsed_s: float
    stop_reason: str = "max_iterations"


def to_host(x) -> np.ndarray:
    """A device array as NumPy. An array sharded over several hosts (``jax.distributed``) is
    gathered from every process first, so each process gets the whole array."""
    if isinstance(x, jax.Array) and not x.is_fully_addressable:
        from jax.experimental import multihost_utils

        return np.asarray(multihost_utils.process_allgather(x, tiled=True))
    return np.asarray(x)


def _addressable(tree) -> bool:
    return all(
        not isinstance(x, jax.Array) or x.is_fully_addressable for x in jax.tree.leaves(tree)
    )


def run(
    algorithm: SamplingAlgorithm,
    rng_key,
    initial_positions=None,
    n_iterations: int = 1000,
    *,
    progress: bool = True,
    trace_every: int | None = 1,
    chunk_size: int | None = None,
    callback: Callable[[int, Any], None] | None = None,
    callback_every: int | None = None,
    initial_state=None,
    start_iteration: int = 0,
    stop_when: Callable[..., str | None] | None = None,
    reinit_stragglers: ReinitStragglers | None = None,
    cache: ProgramCache | None = None,
) -> RunResult:
    """Run ``algorithm`` from ``initial_positions [P, D]`` (or a saved state) to ``n_iterations``.

    Args:
      algorithm: a :class:`SamplingAlgorithm` (``make_sampler(...)``), or a
        :class:`DataSamplingAlgorithm`, whose programs take its data as an argument: the
        compiled chunk is then kept in ``cache`` by the lowered program itself, so a run on
        other data of the same shapes (a new algorithm object) reuses it.
      rng_key: a JAX key or an integer seed (``jax.random.key(seed)``).
      initial_positions: ``[P, D]`` starting particles (ignored when resuming).
      n_iterations: total iteration count of the whole run, *including* the
        ``start_iteration`` already done when resuming.
      progress: show a tqdm bar (iteration, mean log p, SVGD bandwidth, elapsed).
      trace_every: record particles and log-densities every this many
        iterations (at completed counts divisible by it); None records nothing.
      chunk_size: iterations per jitted chunk (default 100, or
        ``callback_every``); chunk ends are multiples of it, so the bar and the
        callback see whole chunks.
      callback: ``callback(iteration, state)`` called on the host after the
        chunk ending at every multiple of ``callback_every`` (completed
        iteration count); use it to checkpoint ``state``.
      initial_state, start_iteration: resume from ``state`` saved after
        ``start_iteration`` iterations of a run with the same ``rng_key``;
        the result equals the uninterrupted run.
      stop_when: ``stop_when(iteration, positions [P, D], previous_positions [P, D] | None,
        diagnostics) -> reason | None``, called on the host after every chunk (e.g.
        :class:`treeinfer.inference.diagnostics.ConvergenceCriterion`); ``previous_positions`` are
        the particles at the previous chunk end of this call, ``diagnostics`` the per-iteration
        scalars so far. A reason (str) ends the run there; it is ``result.stop_reason``.
      reinit_stragglers: a :class:`treeinfer.inference.diagnostics.ReinitStragglers` warm-up remedy:
        after each chunk ending at or before its ``until``, stragglers are moved next to good
        particles and their state re-initialised (one extra batched target evaluation, only
        when some are found); ``diagnostics["n_reinitialised"]`` counts them per iteration.
        Deterministic (keyed by iteration), so resume stays exact.
      cache: a :class:`~treeinfer.sim.program_cache.ProgramCache` the caller owns: the compiled
        chunk is kept there per (algorithm object, chunk length, shapes), so another run (or a
        resumed run) of the same algorithm object with that cache does not recompile. None: a
        cache local to this call (the program is compiled, used and dropped).

    One program per run: ``init`` is folded into the jitted scan chunk (run inside it, under
    ``lax.cond``, on the first chunk of a fresh run), so a run compiles one executable where
    it used to compile two (``tests/test_samplers.py`` counts them).
    """
    t0 = time.perf_counter()
    for nm, v in (("n_iterations", n_iterations), ("start_iteration", start_iteration)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 0:
            raise ConfigError(f"run: {nm} must be a non-negative integer, got {v!r}")
    if start_iteration > n_iterations:
        raise ConfigError(
            f"run: start_iteration={start_iteration} is beyond n_iterations={n_iterations}"
        )
    for nm, v in (
        ("trace_every", trace_every),
        ("chunk_size", chunk_size),
        ("callback_every", callback_every),
    ):
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1):
            raise ConfigError(f"run: {nm} must be a positive integer or None, got {v!r}")
    if stop_when is not None and not callable(stop_when):
        raise ConfigError(f"run: stop_when must be callable, got {stop_when!r}")
    if reinit_stragglers is not None and not isinstance(reinit_stragglers, ReinitStragglers):
        raise ConfigError("run: reinit_stragglers must be a diagnostics.ReinitStragglers")
    if callback is not None and callback_every is None:
        raise ConfigError("run: callback needs callback_every")
    if chunk_size is None:
        chunk_size = callback_every if callback_every is not None else 100
    if callback_every is not None and callback_every % chunk_size:
        raise ConfigError(
            f"run: callback_every={callback_every} must be a multiple of chunk_size={chunk_size}"
        )

    # a sampler on data given as an argument: its programs take them as one (build(data))
    data_algorithm = isinstance(algorithm, DataSamplingAlgorithm)
    if data_algorithm:
        build, data = algorithm.build, algorithm.data
        extra = (data,)
        plain = build(data)  # closes over the data: used for shapes (eval_shape) only
    else:
        build, extra, plain = None, (), algorithm

    key_record = _key_record(rng_key)
    key = jax.random.key(int(rng_key)) if isinstance(rng_key, (int, np.integer)) else rng_key

    fresh = initial_state is None
    if fresh:
        if start_iteration != 0:
            raise ConfigError(
                "run: start_iteration > 0 needs the initial_state saved at that iteration"
            )
        if initial_positions is None:
            raise ConfigError("run: give initial_positions [P, D] (or initial_state to resume)")
        positions = check_positions(initial_positions)
        state = jax.eval_shape(plain.init, init_key(key), positions)  # shapes only
    else:
        state = initial_state
    n_particles, dim = state.position.shape

    record_trace = trace_every is not None
    diagnostics: dict[str, list] = {}
    remaining = n_iterations - start_iteration
    programs = ProgramCache() if cache is None else cache
    if not isinstance(programs, ProgramCache):
        raise ConfigError(f"run: cache must be a ProgramCache or None, got {cache!r}")
    chunk_key = None
    if remaining > 0 or fresh:
        _, info_shape = jax.eval_shape(plain.step, iteration_key(key, 0), state)
        template = tuple(
            (k, jax.ShapeDtypeStruct(v.shape, v.dtype)) for k, v in _scalars(info_shape).items()
        )
        length = max(1, min(chunk_size, remaining))
        chunk_key = (
            (build, length, record_trace, template)
            if data_algorithm
            else (algorithm.init, algorithm.step, length, record_trace, template)
        )
    if fresh and not _single_device(positions):
        # sharded particles: init runs on its own so the chunk sees the state's real shardings
        if data_algorithm:
            state = jax.jit(lambda k, p, d: build(d).init(k, p))(init_key(key), positions, data)
        else:
            state = jax.jit(algorithm.init)(init_key(key), positions)
        fresh = False
    if fresh:
        state = _zeros_like_shapes(state)
    else:
        positions = state.position
    chunk = None
    if chunk_key is not None:
        args = (state, positions, jnp.asarray(True), key, jnp.int32(0), jnp.int32(0))
        if data_algorithm:
            compiled = _compiled_data_chunk(programs, chunk_key, (*args, data))

            def chunk(*a):
                return compiled(*a, data)

        else:
            chunk = _compiled_chunk(programs, chunk_key, args)

    trace_pos, trace_ld, trace_it = [], [], []
    initial_trace = record_trace and start_iteration == 0
    if initial_trace and not fresh:
        trace_pos.append(to_host(state.position))
        trace_ld.append(to_host(state.logdensity))
        trace_it.append(0)
    if fresh and remaining == 0:  # nothing to run: the chunk only initialises
        state, _, initial = chunk(
            state, positions, jnp.asarray(True), key, jnp.int32(0), jnp.int32(0)
        )
        if initial_trace:
            trace_pos.append(to_host(initial[0]))
            trace_ld.append(to_host(initial[1]))
            trace_it.append(0)
        fresh = False

    stop_reason = "max_iterations"
    it = start_iteration
    previous = None
    reinit_fn = None
    if remaining > 0:
        bar = tqdm(
            total=n_iterations,
            initial=start_iteration,
            disable=not progress,
            desc=algorithm.name or "sampling",
            unit="it",
            dynamic_ncols=True,
        )
        try:
            while it < n_iterations:
                stop = min((it // chunk_size + 1) * chunk_size, n_iterations)
                state, (scalars, trace), initial = chunk(
                    state, positions, jnp.asarray(fresh), key, jnp.int32(it), jnp.int32(stop)
                )
                if fresh and initial_trace:  # the initial state, evaluated inside the chunk
                    trace_pos.append(to_host(initial[0]))
                    trace_ld.append(to_host(initial[1]))
                    trace_it.append(0)
                fresh = False
                n_done = stop - it
                scalars = {k: to_host(v)[:n_done] for k, v in scalars.items()}
                for k, v in scalars.items():
                    diagnostics.setdefault(k, []).append(v)
                if record_trace:
                    counts = np.arange(it + 1, stop + 1)
                    keep = np.nonzero(counts % trace_every == 0)[0]
                    if keep.size:
                        trace_pos.append(to_host(trace[0])[keep])
                        trace_ld.append(to_host(trace[1])[keep])
                        trace_it.extend(counts[keep].tolist())
                it = stop
                if reinit_stragglers is not None:
                    n_re = 0
                    if it <= reinit_stragglers.until:
                        if reinit_fn is None:
                            init_of = (
                                (lambda d: build(d).init)
                                if data_algorithm
                                else (lambda: algorithm.init)
                            )
                            reinit_fn = _straggler_reinit(init_of, reinit_stragglers)
                        state, n_re = reinit_fn(state, key, jnp.int32(it), extra)
                        n_re = int(n_re)
                    counts = np.zeros(n_done, np.int32)
                    counts[-1] = n_re
                    diagnostics.setdefault("n_reinitialised", []).append(counts)
                postfix = {}
                if "mean_logdensity" in scalars:
                    postfix["logp"] = f"{float(scalars['mean_logdensity'][-1]):.4g}"
                if "bandwidth" in scalars:
                    postfix["bw"] = f"{float(scalars['bandwidth'][-1]):.3g}"
                if "mean_acceptance_rate" in scalars:
                    postfix["acc"] = f"{float(np.mean(scalars['mean_acceptance_rate'])):.2f}"
                bar.set_postfix(postfix, refresh=False)
                bar.update(n_done)
                if callback is not None and it % callback_every == 0:
                    callback(it, state)
                if stop_when is not None and it < n_iterations:
                    now = to_host(state.position)
                    so_far = {k: np.concatenate(v) for k, v in diagnostics.items()}
                    reason = stop_when(it, now, previous, so_far)
                    previous = now
                    if reason:
                        stop_reason = str(reason)
                        break
        finally:
            bar.close()

    if record_trace and trace_pos:
        trace_positions = np.concatenate([t if t.ndim == 3 else t[None] for t in trace_pos])
        trace_logdensity = np.concatenate([t if t.ndim == 2 else t[None] for t in trace_ld])
    else:
        trace_positions = np.zeros((0, n_particles, dim), to_host(state.position).dtype)
        trace_logdensity = np.zeros((0, n_particles), to_host(state.logdensity).dtype)
    settings = {
        "sampler": algorithm.name,
        "hyperparameters": dict(algorithm.settings),
        **key_record,
        "n_iterations": int(n_iterations),
        "n_iterations_done": int(it),
        "start_iteration": int(start_iteration),
        "n_particles": int(n_particles),
        "dim": int(dim),
        "trace_every": trace_every,
        "chunk_size": int(chunk_size),
    }
    return RunResult(
        final_positions=to_host(state.position),
        final_state=jax.tree.map(to_host, state) if not _addressable(state) else state,
        trace_positions=trace_positions,
        trace_logdensity=trace_logdensity,
        trace_iterations=np.asarray(trace_it, dtype=np.int64),
        diagnostics={k: np.concatenate(v) for k, v in diagnostics.items()},
        settings=settings,
        elapsed_s=time.perf_counter() - t0,
        stop_reason=stop_reason,
    )
