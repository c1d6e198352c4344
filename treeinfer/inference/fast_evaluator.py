"""The one rollout program of :func:`treeinfer.inference.fast.fast_posterior`:
:class:`BatchEvaluator` runs the rollout residuals and the log-prior of ``K`` parameter sets per
call (the observations padded to a shape bucket and passed as arguments), :func:`default_chunk`
picks ``K`` for the backend, and :func:`check_problem` says which problems the program runs.

Separate from :mod:`treeinfer.inference.fast` (issue 26) because it is the program, not the
pipeline: the start pipeline's force-noise reference fits
(:func:`treeinfer.inference.start_pipeline.force_noise_reference`) and the run layer's problem
check use it without the screen, fit and importance steps around it.
:mod:`treeinfer.inference.fast` re-exports every name (they lived there before the split).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ConfigError
from ..sim.startup import device_array
from ..sim.threads import map_calls

__all__ = ["BatchEvaluator", "check_problem", "default_chunk", "held_evaluator"]


class BatchEvaluator:
    """Boltzmann residuals and log-prior of ``K`` parameter sets per call.

    ``evaluate(theta [N, D])`` (any N; padded to multiples of ``K`` and run in chunks) returns
    ``(r [N, 2B, T], stable [N], log_prior [N])``: the masked displacement (m) then velocity
    (m/s) errors of each training trajectory, whether every rollout was stable, and
    ``problem.log_prior``. ``log_density(theta)`` is ``problem.log_density`` from them:
    ``-sum_g ||r_g|| / kT + log_prior``, ``-inf`` where unstable. ``calls`` counts rollout-program
    runs.

    The rollout program takes the observations as **arguments** (the likelihood's own programs
    embed them as constants), padded to ``shape`` ``[B', T']`` (:func:`treeinfer.sim.startup.
    bucket_observations`; default ``problem.settings["shape_bucket"]``, recorded by the run
    layer, else the data's shape): its XLA program depends on the simulator, the batch and that
    shape only, so another data set of the same bucket reuses it, from ``programs`` (a
    :class:`~treeinfer.sim.program_cache.ProgramCache`, keyed by simulator, grasp point, batch and
    shape) in this process and from the persistent compilation cache in the next. Padded rows
    and steps carry ``mask = False`` and are cut from ``r``; padded rows count as stable. The
    log-prior (box and inequality network; no data) is a second, small program of its own.
    """

    def __init__(self, problem, chunk: int, programs=None, shape=None, traced_substeps=None):
        check_problem(problem)
        from ..sim.startup import bucket_observations

        self.problem, self.chunk, self.calls = problem, int(chunk), 0
        sim = problem.sim
        self.substeps = int(sim.substeps)
        # the step count as a program argument unless the Pallas kernel runs the rollouts with
        # the simulator's own step (pallas.TRACED_SUBSTEPS, on by default; a traced count
        # would then fall back to the fused path)
        if traced_substeps is None:
            from ..sim import pallas

            traced_substeps = sim.backend != "pallas" or pallas.TRACED_SUBSTEPS
        self.traced = bool(traced_substeps)
        self.runs: dict[int, int] = {}  # program runs per substep count
        self.kT = float(problem.kT)
        # the rollout takes the gains only; noise columns (sigma_x, ...) cost no rollout
        self.n_gains = 2 * sim.n_joints
        terms = problem.noise
        self.boltzmann = terms is None or terms.black_box
        self._noise = None
        # with a program cache (a run's, a batch's) the small programs around the rollout take
        # what they close over (the recording's bounds, mask, force-noise basis, integration
        # floor) as arguments: compiled once per shape, not once per recording
        # (treeinfer.sim.args_program; a batch's second item compiled 6 programs, 3 with it)
        self._arg_programs = programs
        sim, obs = problem.sim, problem.obs
        gf = problem.settings.get("grasp_fraction")
        if gf is not None and math.isclose(gf, problem.tree.grasp_fraction):
            gf = None  # the simulator's own grasp site: the likelihood's exact path
        b, t = np.shape(obs.force)
        shape = problem.settings.get("shape_bucket") if shape is None else shape
        padded = obs if shape is None else bucket_observations(obs, *shape)
        self.shape, self._rows, self._steps = tuple(np.shape(padded.force)), b, t
        self._dtype = sim.dtype
        self._data = tuple(
            device_array(x, dt)
            for x, dt in (
                (padded.force, self._dtype),
                (padded.displacement, self._dtype),
                (padded.velocity, self._dtype),
                (padded.mask, bool),
                (t, np.int32),
            )
        )
        self._run = rollout_program(
            sim, gf, self.chunk, self.shape, self._data, programs, self.traced, self.substeps
        )
        self._prior = self._program(problem.log_prior)
        if not self.boltzmann:  # the problem's own noise density, on the host's residuals
            self._noise = self._program(terms.residual_loglik)

    def _program(self, fn):
        """``fn`` compiled: one program per argument shape shared through the program cache
        (:class:`treeinfer.sim.args_program.ArgsProgram`), else ``jax.jit``."""
        if self._arg_programs is None:
            return jax.jit(fn)
        from ..sim.args_program import ArgsProgram
        from ..sim.program_cache import ProgramCache

        programs = self._arg_programs
        if isinstance(programs, _HeldOnly):  # only the rollout program must be held already
            programs = programs.programs
        # a cache of their own, kept in the command's as one entry: a run builds a dozen of
        # these small programs (prior, noise density, Gauss-Newton terms of each problem), and in
        # the command's cache (8 programs) they would push out the rollout and sampler programs
        small = programs.get(("BatchEvaluator small programs",), lambda: ProgramCache(32))
        return ArgsProgram(fn, small)

    def evaluate(self, theta, substeps: int | None = None):
        """``(r, stable, log_prior)`` at ``theta [N, D]`` (class docstring); ``substeps``:
        simulation steps per observation (default the simulator's own, ``self.substeps``;
        another count needs ``self.traced``)."""
        s = self.substeps if substeps is None else int(substeps)
        if s != self.substeps and not self.traced:
            raise ConfigError(
                f"substeps: this rollout program runs the simulator's own step "
                f"({self.substeps} substeps), not {s}"
            )
        if s < 1:
            raise ConfigError(f"substeps: must be an integer >= 1, got {substeps!r}")
        extra = (np.int32(s),) if self.traced else ()
        theta = np.atleast_2d(np.asarray(theta, float))
        n, k = len(theta), self.chunk
        pad = (-n) % k
        full = np.concatenate([theta, np.repeat(theta[-1:], pad, 0)]) if pad else theta
        starts = range(0, len(full), k)
        self.calls += len(starts)
        self.runs[s] = self.runs.get(s, 0) + len(starts)

        def chunk(i):  # the values on the host: the call's thread waits for its program
            th = device_array(full[i : i + k], self._dtype)
            gains = th if th.shape[1] == self.n_gains else th[:, : self.n_gains]
            outs = (*self._run(gains, *self._data, *extra), self._prior(th))
            return [np.asarray(o) for o in outs]

        # the chunks on the idle cores (treeinfer.sim.threads: the same values, sooner)
        outs = map_calls(chunk, starts)
        r, ok, lp = (np.concatenate([np.asarray(o[j], float) for o in outs])[:n] for j in range(3))
        b, t, nb = self._rows, self._steps, self.shape[0]
        r = np.concatenate([r[:, :b, :t], r[:, nb : nb + b, :t]], axis=1)  # the data's rows, steps
        return r, ok.astype(bool), lp

    def rollout(self, theta, substeps: int | None = None):
        """``(tau [N, B, T], tau_dot [N, B, T], stable [N])``: the rollouts at the data's rows
        and steps, from the residuals of :meth:`evaluate` with the recorded displacement and
        velocity added back (in the program's dtype, so where the simulated and recorded values
        are within a factor two of each other the sum is exact); zeros where unstable, as
        :class:`treeinfer.sim.Rollout`. Right only where the data's mask is True (the residual
        is zero elsewhere): the run layer's training fit uses it for fully observed data, so
        that it runs the start pipeline's compiled program instead of compiling a prediction
        of its own (:func:`held_evaluator`)."""
        r, ok, _ = self.evaluate(theta, substeps)
        b, dt = self._rows, np.dtype(self._dtype)
        obs = self.problem.obs
        x = np.asarray(obs.displacement, dt).astype(float)
        v = np.asarray(obs.velocity, dt).astype(float)
        keep = ok[:, None, None]
        tau = np.where(keep, r[:, :b] + x, 0.0).astype(dt)
        tau_dot = np.where(keep, r[:, b:] + v, 0.0).astype(dt)
        return tau, tau_dot, ok

    def loss_terms(self, theta, substeps: int | None = None):
        """``(norms [N, G], stable [N], log_prior [N], r [N, G, T])``."""
        r, ok, lp = self.evaluate(theta, substeps)
        return np.sqrt(np.sum(r**2, axis=-1)), ok, lp, r

    def log_density(self, theta, substeps: int | None = None) -> np.ndarray:
        """``[N]`` log p(theta | data) up to a constant (as ``problem.log_density``; with
        ``substeps`` the simulator's step changed to that many substeps)."""
        return self.log_density_terms(theta, substeps)[0]

    def log_density_terms(self, theta, substeps: int | None = None):
        """``(log p [N], r [N, G, T])``: :meth:`log_density` and the residuals it came from."""
        theta = np.atleast_2d(np.asarray(theta, float))
        norms, ok, lp, r = self.loss_terms(theta, substeps)
        if self.boltzmann:
            out = -norms.sum(-1) / self.kT + lp
        else:
            out = self.log_likelihood(r, theta) + lp
        return np.where(ok & np.isfinite(out), out, -np.inf), r

    def log_prior(self, theta) -> np.ndarray:
        """``[N]`` ``problem.log_prior`` at ``theta [N, D]``, in batches of ``chunk`` rows."""
        theta = np.atleast_2d(np.asarray(theta, float))
        n, k = len(theta), self.chunk
        pad = (-n) % k
        full = np.concatenate([theta, np.repeat(theta[-1:], pad, 0)]) if pad else theta
        out = [
            self._prior(device_array(full[i : i + k], self._dtype)) for i in range(0, len(full), k)
        ]
        return np.concatenate([np.asarray(o, float) for o in out])[:n]

    def log_likelihood(self, r, theta) -> np.ndarray:
        """``[N]`` the problem's generative log-likelihood from the residuals ``r [N, 2B, T]``
        (simulated minus recorded, :meth:`evaluate`) and the noise columns of ``theta [N, D]``
        (:attr:`treeinfer.model.likelihood.LikelihoodTerms.residual_loglik`, the same noise density
        the problem's likelihood uses), in batches of ``chunk`` rows (one compiled shape)."""
        b, k = self._rows, self.chunk
        n = len(theta)
        pad = (-n) % k
        if pad:
            r = np.concatenate([r, np.repeat(r[-1:], pad, 0)])
            theta = np.concatenate([theta, np.repeat(theta[-1:], pad, 0)])
        out = []
        for i in range(0, len(theta), k):
            ri = device_array(r[i : i + k], self._dtype)
            out.append(
                self._noise(-ri[:, :b], -ri[:, b:], device_array(theta[i : i + k], self._dtype))
            )
        return np.concatenate([np.asarray(o, float) for o in out])[:n]


def rollout_program(sim, gf, chunk, shape, data, programs, traced=True, substeps=1):
    """The jitted rollout program of :class:`BatchEvaluator` (``chunk`` parameter sets, the
    observations ``data`` padded to ``shape`` as arguments), from ``programs`` (a
    :class:`~treeinfer.sim.program_cache.ProgramCache`; None: a new one), built there if
    missing. Its key leaves the step out where the step count is an argument (``traced``:
    :meth:`treeinfer.sim.Simulator.program_key`)."""
    from ..sim.startup import cached_program

    dtype = sim.dtype
    key = (
        "fast_posterior.BatchEvaluator",
        sim.program_key(traced),
        gf,
        int(chunk),
        2 * sim.n_joints,
        tuple(shape),
        str(dtype),
        "traced substeps" if traced else "static substeps",
    )
    example = (jax.ShapeDtypeStruct((int(chunk), 2 * sim.n_joints), dtype), *data)
    if traced:
        example = (*example, np.int32(substeps))

    def build():  # traced once per machine: treeinfer.sim.startup.cached_program
        return cached_program(_rollout_residuals(sim, gf, traced), example, repr(key))

    return build() if programs is None else programs.get(key, build)


def compile_rollout_program(sim, gf, chunk, obs, shape, programs) -> None:
    """Compile (and fill ``programs`` with) the rollout program a :class:`BatchEvaluator` of
    ``chunk`` sets on observations ``obs`` (padded to ``shape``, or None) will ask for, by one
    call on zeros at one substep; e.g. on a second thread while the step is chosen
    (``treeinfer.runs.problem``). The program depends on the data's shapes only and, its step
    count an argument, not on the step: a simulator of the same settings at any step compiles
    the same one."""
    from ..sim.startup import bucket_observations

    padded = obs if shape is None else bucket_observations(obs, *shape)
    dtype = sim.dtype
    b, t = np.shape(padded.force)
    # as the evaluator passes them (device_array): the same program, not another trace of it
    zeros = np.zeros((b, t))
    data = (
        device_array(zeros, dtype), device_array(zeros, dtype), device_array(zeros, dtype),
        device_array(zeros, bool), device_array(np.shape(obs.force)[1], np.int32),
    )  # fmt: skip
    run = rollout_program(sim, gf, chunk, (b, t), data, programs)
    theta = device_array(np.zeros((int(chunk), 2 * sim.n_joints)), dtype)
    jax.block_until_ready(run(theta, *data, np.int32(1)))


class _NotHeld(Exception):
    pass


class _HeldOnly:
    """A :class:`~treeinfer.sim.program_cache.ProgramCache` view that hands out the programs it
    holds and raises :class:`_NotHeld` instead of building one."""

    def __init__(self, programs):
        self.programs = programs

    def get(self, key, build):
        if key not in self.programs:
            raise _NotHeld(key)
        return self.programs.get(key, build)


def held_evaluator(problem, programs, chunk: int, shape=None):
    """A :class:`BatchEvaluator` of ``problem`` (batch ``chunk``, shape bucket ``shape``) whose
    rollout program ``programs`` already holds, e.g. the start pipeline's after the run's
    importance posterior; None when it holds none or the problem is not one the program runs:
    nothing is traced or compiled here."""
    if programs is None:
        return None
    try:
        return BatchEvaluator(problem, chunk, _HeldOnly(programs), shape)
    except (_NotHeld, ConfigError):
        return None


def default_chunk(k: int, n_draws: int) -> int:
    """The rollout program's batch for an LM batch of ``k`` points and importance rounds of
    ``n_draws``: ``k`` on a CPU, where the work is arithmetic and a padded row costs its share;
    on an accelerator ``n_draws`` rounded up to a multiple of ``k``, because a rollout there is
    bound by the latency of its sequential steps, not by lanes (832 parameter sets x 3 pulls
    fill 78 of an H100's 132 multiprocessors in one wave and take about as long as 104): an
    importance round is then one program run instead of eight, the screen one instead of four
    (BENCHMARKS.md, issue 15: a new recording's importance fit on an H100)."""
    if jax.default_backend() == "cpu":
        return int(k)
    return -(-int(n_draws) // int(k)) * int(k)


def _rollout_residuals(sim, gf, traced_substeps: bool = False):
    """``(theta [K, 2R], forces, displacement, velocity, mask [B, T], n_steps[, substeps]) ->
    (r [K, 2B, T], stable [K])``: the masked displacement and velocity errors of the rollouts
    (the Boltzmann loss's residuals) and whether every real row (one with a True mask entry)
    stayed stable.

    ``traced_substeps``: the program takes the simulation substeps per observation as a last
    (int32) argument, so one compiled program runs any step (the multi-fidelity fit of
    :func:`fast_posterior` screens and fits at a coarse step and weights at the accurate one).
    On the CPU it is also the faster program at the simulator's own step: 0.26 s against 0.43 s
    for 104 parameter sets of the standard problem at 14 substeps (2-core box; the static count
    runs the pull of :mod:`treeinfer.sim.sensitivity`, built for derivatives; the values agree
    to float32 rounding, ``tests/test_fast_posterior.py``).

    ``n_steps`` (a traced integer: one program for every data length of a bucket) is the
    unpadded data's length T0: the simulated velocity at sample T0 - 1 is the one-sided
    difference, as in the unpadded simulation (:func:`treeinfer.sim.velocity`: second-order
    one-sided at the last sample), not the central one the padded steps would give (that changed
    the log density by up to 3e-4 relative, ``tests/test_startup.py``)."""
    from ..model.likelihood import gains_from_theta
    from ..sim import _simulate, simulate

    inv = 1.0 / (2.0 * sim.obs_dt)  # treeinfer.data.trajectories.velocity_from_displacement's

    def run(theta, forces, disp, vel, mask, n_steps, *substeps):
        kp, kd = gains_from_theta(theta, sim.n_joints)
        if traced_substeps:
            out = _simulate(sim, kp, kd, forces, gf, substeps=substeps[0])
        else:
            out = simulate(sim, kp, kd, forces, gf)
        x = out.tau

        def at(i):
            return jax.lax.dynamic_index_in_dim(x, i, axis=-1, keepdims=True)

        last = (3.0 * at(n_steps - 1) - 4.0 * at(n_steps - 2) + at(n_steps - 3)) * inv
        end = jnp.arange(x.shape[-1]) == n_steps - 1
        tau_dot = jnp.where(end, jnp.where(out.stable[..., None], last, 0.0), out.tau_dot)
        m = mask.astype(out.tau.dtype)
        dpos = (out.tau - disp.astype(out.tau.dtype)) * m
        dvel = (tau_dot - vel.astype(out.tau.dtype)) * m
        stable = jnp.all(out.stable | ~jnp.any(mask, axis=-1), axis=-1)
        return jnp.concatenate([dpos, dvel], axis=1), stable

    return run


def check_problem(problem) -> None:
    """ConfigError unless ``problem`` is the paper's dynamic model (theta = [log Kp, log Kd]
    and the likelihood's noise columns) with a likelihood that offers its density from the
    rollout residuals (every likelihood :func:`treeinfer.model.likelihood.likelihood_terms`
    builds)."""
    noise = getattr(problem, "noise", None)
    if problem.model is not None:
        raise ConfigError(
            "fast posterior: the rollout program runs the paper's dynamic model only (not a "
            "static model, stiffness-only parameters, a tie or per-recording pulls)"
        )
    extra = 0 if noise is None else len(noise.extra_labels)
    if problem.dim != 2 * problem.sim.n_joints + extra:
        raise ConfigError(
            f"fast posterior: theta has {problem.dim} columns, expected 2R + {extra} noise columns"
        )
    if noise is not None and not noise.black_box and noise.residual_loglik is None:
        raise ConfigError("fast posterior: this likelihood offers no density of the residuals")
