"""A posterior in seconds on a CPU: one compiled rollout program, a screened MAP fit and
importance sampling, no sampler iterations.

    result = fast_posterior(problem, n_particles=128)
    result.theta          # [P, D] posterior particles; result.ok says whether to trust them

The steps, all through **one** jitted batched rollout of a fixed number of parameter sets
(:class:`BatchEvaluator`; on a 2-core CPU each extra XLA program of the standard problem costs
3-12 s to compile, more than the work it does). Its batch is K below on a CPU and an importance
round's draws on an accelerator (:func:`default_chunk`: latency-bound there, so one run a round):

1. **Screen**: the Boltzmann loss at ``n_screen`` Latin-hypercube points of the prior box (no
   gradients); the ``n_starts`` lowest are the starting points.
2. **Levenberg–Marquardt** from them (the same damped Gauss–Newton step as
   :func:`treeinfer.inference.mapfit.fit_map`, kind ``"norm"``), with the residual Jacobian by
   central differences: each iteration evaluates the ``n_starts * (2D + 1)`` points of one call (=
   K). The prior enters through its values at the same points (gradient and PSD-clipped diagonal
   curvature by central differences); it is smooth on the step's scale.
3. **Importance sampling** (:mod:`treeinfer.inference.importance`) from the Student-t (df
   :data:`DEFAULT_DF`) matched to the Boltzmann loss at the mode
   (:func:`treeinfer.inference.laplace.norm_loss_covariance`, plus the box's precision), ``n_draws``
   draws weighted by ``p / q`` with Pareto smoothing, then, while the effective sample size is
   below ``4 P`` (at most 3 rounds), ``n_draws`` more from the weighted draws' moments, all
   reweighted against the mixture of the proposals
   (:func:`treeinfer.inference.importance.adaptive_importance`). The ``P`` particles are one draw
   per equal-weight stratum along the draws' leading prediction component
   (:func:`treeinfer.inference.importance.sorted_resample`). ``ok`` is ``k_hat <= 0.7``, an
   effective sample size of at least ``2 P``, and the even and odd draws' training bands within 20 %
   (:func:`treeinfer.inference.importance.band_split`, a guard against gross instability).

On the standard problem (10 seeds, ``experiments/importance_robustness.py``, 2-core CPU, 4
substeps; the held-out band against an exact one, 8.58 mm: 16384 Student-t importance draws,
averaged over 32 subsets of 128 particles) the former path (the fit's Gaussian, one round, 832
draws, ESS 37-169) scattered by 6.5 % (sd), worst 10.2 %; this one (Student-t, three rounds,
sorted resampling, ESS 634-888): mean -0.6 %, sd 3.9 %, worst 5.9 %. 128 exact posterior draws
scatter by 6.6 % themselves.

**Multi-fidelity** (``coarse_substeps``, default ``"auto"``: the stability step, 4 substeps on
the standard problem against the accuracy-controlled 14): the rollout program takes the step as
an argument (one compiled program), the screen, the LM fit (15 iterations) and two importance
rounds run at the coarse step, at about a third of the cost; the coarse rounds' weighted moments
are the first proposal of the accurate step's rounds, and only the accurate rounds' draws are
weighted and returned, so the result targets the accurate posterior exactly (any proposal gives
correct weights; ``tests/test_fast_posterior_multifidelity.py`` checks the weighted moments
against quadrature at the accurate step where the coarse posterior is measurably elsewhere).
Rollout-program runs on the standard problem (batch 104): before, 60 at 14 substeps; now 37 at
4 and 16-24 at 14.

Why not :func:`treeinfer.inference.mapfit.fit_problem` then ``problem.log_density``: that is three
programs (the LM's value/gradient/curvature with its vmapped Jacobian, the log-density at M
draws, the sampler's chunk), 11-14 s of compilation each on the 2-core box; here the LM,
screening and weights are NumPy on the host around one rollout program (D is small; the
log-prior, which holds no data, is a second small program).

Only the paper's model and loss: ``theta = [log Kp, log Kd]``, the Boltzmann likelihood.
"""

from __future__ import annotations

import math
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ConfigError
from ..sim.startup import device_array

# the coarse-step importance rounds draw with seed + COARSE_SEED (the accurate step's with seed)
COARSE_SEED = 7919
# Student-t proposals (every round): Gaussian ones leave the posterior's tails short, so the
# band came out 5-6 % narrow on average (experiments/importance_robustness.py, BENCHMARKS.md)
DEFAULT_DF = 8.0
# accurate-step LM iterations after the coarse fit for a generative likelihood (importance_for_run)
GENERATIVE_POLISH = 8

__all__ = [
    "DEFAULT_DF",
    "BatchEvaluator",
    "FastPosterior",
    "ParticleState",
    "default_chunk",
    "fast_posterior",
    "fit_map_batched",
    "importance_for_run",
    "posterior_from_fast",
    "resolve_coarse_substeps",
]


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
        from ..sim.startup import bucket_observations, cached_program

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
        if not self.boltzmann:  # the problem's own noise density, on the host's residuals
            self._noise = jax.jit(terms.residual_loglik)
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
        sim_key = sim.program_key(self.traced)
        key = (
            "fast_posterior.BatchEvaluator",
            sim_key,
            gf,
            self.chunk,
            self.n_gains,
            self.shape,
            str(self._dtype),
            "traced substeps" if self.traced else "static substeps",
        )
        example = (jax.ShapeDtypeStruct((self.chunk, self.n_gains), self._dtype), *self._data)
        if self.traced:
            example = (*example, np.int32(self.substeps))

        def build():  # traced once per machine: treeinfer.sim.startup.cached_program
            fn = _rollout_residuals(sim, gf, self.traced)
            return cached_program(fn, example, repr(key))

        self._run = build() if programs is None else programs.get(key, build)
        self._prior = jax.jit(problem.log_prior)

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
        outs = []
        for i in range(0, len(full), k):
            self.calls += 1
            self.runs[s] = self.runs.get(s, 0) + 1
            th = device_array(full[i : i + k], self._dtype)
            gains = th if th.shape[1] == self.n_gains else th[:, : self.n_gains]
            outs.append((*self._run(gains, *self._data, *extra), self._prior(th)))
        r, ok, lp = (np.concatenate([np.asarray(o[j], float) for o in outs])[:n] for j in range(3))
        b, t, nb = self._rows, self._steps, self.shape[0]
        r = np.concatenate([r[:, :b, :t], r[:, nb : nb + b, :t]], axis=1)  # the data's rows, steps
        return r, ok.astype(bool), lp

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


def latin_hypercube(n: int, lower, upper, seed: int = 0) -> np.ndarray:
    """``[n, D]`` Latin-hypercube points in the box ``[lower, upper]``: the same points as
    :func:`treeinfer.inference.mapfit.latin_hypercube` (``scipy.stats.qmc.LatinHypercube``,
    scrambled, seeded by ``numpy.random.default_rng(seed)``; ``tests/test_fast_posterior.py`` checks
    equality), in NumPy because importing ``scipy.stats`` costs 0.6-1.3 s of a cold start."""
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    rng = np.random.default_rng(seed).spawn(1)[0]  # as scipy's engine: a spawned child
    d = lower.size
    jitter = rng.uniform(size=(n, d))
    perms = np.tile(np.arange(1, n + 1), (d, 1))
    for i in range(d):
        rng.shuffle(perms[i, :])
    return (perms.T - jitter) / n * (upper - lower) + lower


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


def _lm_terms(ev: BatchEvaluator, theta, h: float, substeps: int | None = None):
    """Objective ``-log p`` [S], gradient [S, D], Gauss–Newton curvature [S, D, D] and the
    per-group ``(gram [S, G, D, D], r2 [S, G])`` at ``theta [S, D]``, from one batch of the
    ``S (2D + 1)`` central-difference points (simulated with ``substeps``, default the
    simulator's own)."""
    s, d = theta.shape
    eye = h * np.eye(d)
    pts = np.concatenate([theta[:, None], theta[:, None] + eye, theta[:, None] - eye], 1)
    r, ok, lp = ev.evaluate(pts.reshape(-1, d), substeps)
    r = r.reshape(s, 2 * d + 1, *r.shape[1:])
    ok = ok.reshape(s, -1).all(1)
    lp = lp.reshape(s, -1)
    r0 = r[:, 0]  # [S, G, T]
    jac = np.moveaxis((r[:, 1 : d + 1] - r[:, d + 1 :]) / (2 * h), 1, -1)  # [S, G, T, D]
    norms = np.sqrt(np.sum(r0**2, -1) + 1e-300)  # [S, G]
    u = r0 / norms[..., None]
    ju = np.einsum("sgt,sgtd->sgd", u, jac)
    gram = np.einsum("sgtd,sgte->sgde", jac, jac)
    kT = ev.kT
    value = norms.sum(-1) / kT - lp[:, 0]
    grad = ju.sum(1) / kT - (lp[:, 1 : d + 1] - lp[:, d + 1 :]) / (2 * h)
    curv = np.sum((gram - ju[..., :, None] * ju[..., None, :]) / norms[..., None, None], 1) / kT
    prior_diag = -(lp[:, 1 : d + 1] - 2 * lp[:, :1] + lp[:, d + 1 :]) / h**2
    curv = curv + np.einsum("sd,de->sde", np.maximum(prior_diag, 0.0), np.eye(d))
    good = ok & np.isfinite(value) & np.isfinite(grad).all(1) & np.isfinite(curv).all((1, 2))
    value = np.where(good, value, np.inf)
    grad[~good], curv[~good] = 0.0, 0.0
    return value, grad, curv, gram, norms**2


def fit_map_batched(
    ev: BatchEvaluator,
    starts,
    max_iterations: int = 30,
    tolerance: float = 1e-4,
    max_step: float = 1.0,
    rel_step: float | None = None,
    substeps: int | None = None,
):
    """Levenberg–Marquardt on ``-log p`` from ``starts [S, D]`` through ``ev`` (one call per
    iteration; the rollouts with ``substeps`` per observation, default the simulator's own).
    The update rule is :func:`treeinfer.inference.mapfit.fit_map`'s (Marquardt scaling with a floor,
    step capped at ``max_step`` log units, damping /3 on success and x4 on failure).
    A start stops when an accepted step lowers its objective by less than ``tolerance * (1 +
    |f|)``; the fit stops when every start has stopped, or when two starts have stopped within
    ``sqrt(tolerance)`` of the lowest objective found. Returns a
    :class:`treeinfer.inference.mapfit.MapFit` (``cov`` = ``H^-1`` of the Gauss–Newton curvature,
    ``norm_cov`` the Boltzmann-matched covariance)."""
    from ..model.gradients import default_rel_step
    from .laplace import _inverse_psd, norm_loss_covariance
    from .mapfit import MapFit

    p = ev.problem
    h = default_rel_step(jnp.float32) if rel_step is None else float(rel_step)
    theta = np.array(starts, float)
    if ev.boltzmann:
        terms = _lm_terms
    else:  # a generative likelihood: its generalised Gauss-Newton curvature
        from .start_steps import ggn_terms as terms
    f, g, hs, gram, r2 = terms(ev, theta, h, substeps)
    n = len(theta)
    scale0 = np.array([np.mean(np.abs(np.diag(x))) + 1e-12 for x in hs])
    lam = 1e-3 * np.ones(n)
    done, converged = ~np.isfinite(f), np.zeros(n, bool)
    it = 0
    for it in range(1, max_iterations + 1):
        steps = np.zeros_like(theta)
        for i in np.flatnonzero(~done):
            damp = lam[i] * (np.diag(hs[i]) + 1e-6 * scale0[i])
            try:
                step = np.linalg.solve(hs[i] + np.diag(damp), -g[i])
            except np.linalg.LinAlgError:
                step = -g[i] / (np.diag(hs[i]) + damp + 1e-12)
            big = np.max(np.abs(step))
            steps[i] = step if big <= max_step else step * (max_step / big)
        trial = theta + steps
        ft, gt, ht, gram_t, r2_t = terms(ev, trial, h, substeps)
        accept = ~done & np.isfinite(ft) & (ft < f)
        flat = accept & ((f - ft) < tolerance * (1.0 + np.abs(f)))
        for a, b in ((theta, trial), (f, ft), (g, gt), (hs, ht), (gram, gram_t), (r2, r2_t)):
            a[accept] = b[accept]
        lam = np.where(accept, np.maximum(lam / 3.0, 1e-9), lam * 4.0)
        newly = ~done & (flat | (np.max(np.abs(steps), 1) < 1e-6))
        converged |= newly
        done |= newly | (lam > 1e10)
        if done.all():
            break
        low = np.min(f)
        at_low = converged & (f - low <= math.sqrt(tolerance) * (1 + abs(low)))
        if np.isfinite(low) and at_low.sum() >= 2:
            break
    best = int(np.argmin(f))
    if not np.isfinite(f[best]):
        from ..errors import SimulationError

        raise SimulationError(
            "fast posterior: every starting point gave an unstable simulation; narrow the prior "
            "box or check the data's units"
        )
    hess = 0.5 * (hs[best] + hs[best].T)
    settings = {
        "n_starts": n,
        "jacobian": "fd",
        "kind": "norm" if ev.boltzmann else "generalised Gauss-Newton",
        "max_iterations": max_iterations,
        "tolerance": tolerance,
        "max_step": max_step,
        "batched": True,
        "substeps": ev.substeps if substeps is None else int(substeps),
    }
    return MapFit(
        theta[best].copy(),
        _inverse_psd(hess),
        hess,
        float(f[best]),
        np.array(starts, float),
        theta,
        f,
        converged,
        it,
        np.asarray(p.lower, float)[: ev.n_gains],
        np.asarray(p.upper, float)[: ev.n_gains],
        ev.n_gains,
        settings,
        norm_loss_covariance(gram[best], r2[best], ev.kT) if ev.boltzmann else None,
    )


class FastPosterior(NamedTuple):
    """Result of :func:`fast_posterior`.

    theta: [P, D] particles (importance resample). ok: trust them (PSIS ``khat <= 0.7``,
    enough effective samples, a stable band); reason: why not. fit: the
    :class:`~treeinfer.inference.mapfit.MapFit`. importance: the
    :class:`~treeinfer.inference.importance.ImportancePosterior`. log_density: [P] at ``theta``.
    phases: wall seconds per phase (``compile`` is the first program run).
    calls: rollout-program runs. settings: JSON-ready options and diagnostics.
    """

    theta: np.ndarray
    ok: bool
    reason: str
    fit: object
    importance: object
    log_density: np.ndarray
    phases: dict
    calls: int
    settings: dict


def fast_posterior(
    problem,
    n_particles: int = 128,
    n_starts: int = 8,
    n_screen: int | None = None,
    n_draws: int | None = None,
    max_iterations: int | None = None,
    tolerance: float = 1e-4,
    df: float = DEFAULT_DF,
    seed: int = 0,
    evaluator: BatchEvaluator | None = None,
    max_rounds: int = 3,
    target_ess: float | None = None,
    programs=None,
    coarse_substeps: int | str | None = "auto",
    polish_iterations: int = 0,
    coarse_rounds: int = 2,
    starts=None,
) -> FastPosterior:
    """Posterior particles of ``problem`` without sampler iterations (module docstring).

    Args:
      problem: a :func:`treeinfer.inference.problem.make_problem` problem (dynamic model,
      Boltzmann). n_particles: P particles returned.
      n_starts: LM starting points S; the program's batch is ``K = S (2D + 1)`` sets.
      n_screen: screened box points (default ``4 K``). n_draws: importance draws (default
        ``8 K``, at least ``4 P``; the Pareto k_hat needs several hundred to be reliable: with
        256 draws of a near-perfect proposal it read 1-2 on a one-joint test, a false alarm).
        max_iterations, tolerance: of the LM (:func:`fit_map_batched`). df: Student-t degrees
        of freedom of the importance proposals (:data:`DEFAULT_DF`; inf: Gaussian). seed: of
        the screen, the draws and the resample.
      evaluator: a :class:`BatchEvaluator` of the same problem to reuse (any batch; default
        :func:`default_chunk`).
      programs: a :class:`~treeinfer.sim.program_cache.ProgramCache` for the evaluator's rollout
        program (shared by every data set of one shape bucket, :class:`BatchEvaluator`).
      max_rounds, target_ess: :func:`treeinfer.inference.importance.adaptive_importance`: while the
        effective sample size is below ``target_ess`` (default ``4 P``), up to ``max_rounds``
        rounds of ``n_draws`` each, the later ones from the weighted draws' moments; ``ok``
        needs ``min(target_ess, 2 P)``.
      coarse_substeps: multi-fidelity: the screen and the LM fit simulate with this many
        substeps per observation (a cheaper, less accurate step), the importance weights with
        the simulator's own (accurate) step, so the posterior is still the accurate one: any
        proposal gives exact weights, the fit only has to place it near the mode. ``"auto"``:
        the step that is merely stable (``sim.step_info["stability_substeps"]``) when it is
        coarser than the simulator's and the rollout program takes the step as an argument
        (:class:`BatchEvaluator` ``traced``; the Pallas kernel only with
        :data:`treeinfer.sim.pallas.TRACED_SUBSTEPS`, the default), else the simulator's own;
        None: the simulator's own everywhere.
      polish_iterations: LM iterations at the accurate step from the coarse fit's mode (0:
        none; each costs one program run).
      coarse_rounds: with a coarse step, importance rounds at that step
        (:func:`treeinfer.inference.importance.adaptive_importance` from the fit's proposal) before
        the accurate step's: their weighted draws' mean and covariance are the first proposal of the
        accurate rounds (Student-t, ``df``), the accurate rounds adapt further (``max_rounds``)
        and only their draws are weighted and returned. On the standard problem the fit's own
        Student-t gives an effective sample size of 50-70 of 832 draws, the coarse posterior's
        180-270; the coarse rounds cost about a third of accurate ones (4 against 14 substeps).
      max_iterations (None): 15 with a coarse step (the coarse importance rounds re-centre the
        proposal), else 30.
      starts: ``[S, D]`` LM starting points instead of the screen's (e.g. a MAP found before,
        :func:`treeinfer.inference.start_pipeline.force_noise_reference`); None: screen the box.
    """
    from .importance import (
        BAND_SPLIT_LIMIT,
        adaptive_importance,
        band_split,
        leading_projection,
        proposal_from_fit,
        sorted_resample,
        weighted_moments,
    )

    for name, v in (("n_particles", n_particles), ("n_starts", n_starts)):
        if not (isinstance(v, (int, np.integer)) and v >= 1):
            raise ConfigError(f"{name}: must be an integer >= 1, got {v!r}")
    # one LM iteration's batch: the central differences in the gains (2R of them; a generative
    # likelihood's noise columns need no rollout, start_steps.ggn_terms), so the force-noise
    # reference's fits (start_pipeline.force_noise_reference) and this one share the program
    k = n_starts * (4 * problem.sim.n_joints + 1)
    n_screen = 4 * k if n_screen is None else int(n_screen)
    n_draws = max(8 * k, 4 * n_particles) if n_draws is None else int(n_draws)
    if n_screen < n_starts:
        raise ConfigError(f"n_screen: must be >= n_starts ({n_starts}), got {n_screen}")
    if not (isinstance(coarse_rounds, (int, np.integer)) and coarse_rounds >= 0):
        raise ConfigError(f"coarse_rounds: must be an integer >= 0, got {coarse_rounds!r}")
    if not (isinstance(polish_iterations, (int, np.integer)) and polish_iterations >= 0):
        raise ConfigError(f"polish_iterations: must be an integer >= 0, got {polish_iterations!r}")
    if evaluator is None:
        evaluator = BatchEvaluator(problem, default_chunk(k, n_draws), programs)
    ev = evaluator
    if ev.problem is not problem:
        raise ConfigError("evaluator: built for another problem")
    coarse = resolve_coarse_substeps(ev, coarse_substeps)
    if max_iterations is None:
        max_iterations = 15 if coarse != ev.substeps and coarse_rounds > 0 else 30
    phases, t = {}, time.perf_counter()
    lower, upper = np.asarray(problem.lower, float), np.asarray(problem.upper, float)
    ev.evaluate(lower[None], coarse)  # compile (and run once)
    phases["compile"], t = time.perf_counter() - t, time.perf_counter()
    from .start_steps import screen

    if starts is None:
        pts = latin_hypercube(n_screen, lower, upper, seed)
        lp, pts = screen(ev, pts, coarse)
        order = np.argsort(np.where(np.isfinite(lp), -lp, np.inf))
        starts = pts[order[:n_starts]]
    else:
        starts = np.atleast_2d(np.asarray(starts, float))
    phases["screen"], t = time.perf_counter() - t, time.perf_counter()
    fit = fit_map_batched(ev, starts, max_iterations, tolerance, substeps=coarse)
    coarse_fit = fit
    modes = None
    if polish_iterations and coarse != ev.substeps:
        from .start_steps import distinct_modes

        # every distinct local mode of the multi-start fit within MODE_GAP nats is polished
        # and sampled (start_pipeline.multimode_importance), not the best one alone
        modes = distinct_modes(fit, proposal_from_fit(fit)[1])
        fit = fit_map_batched(ev, modes, polish_iterations, tolerance)
        modes = distinct_modes(fit, proposal_from_fit(fit)[1])
    phases["map_fit"], t = time.perf_counter() - t, time.perf_counter()
    mean, cov = proposal_from_fit(fit)
    target = 4.0 * n_particles if target_ess is None else float(target_ess)
    coarse_imp = None
    if coarse != ev.substeps and coarse_rounds > 0:
        # the proposal: the coarse step's own (importance-weighted) posterior, whose shape the
        # fit's Gaussian matches poorly (effective sample size 50-70 of 832 draws)
        coarse_imp, _ = adaptive_importance(
            lambda x: ev.log_density(x, coarse), mean, cov, n_draws, int(n_particles),
            seed + COARSE_SEED, float(df), int(coarse_rounds), target,
        )  # fmt: skip
        if np.isfinite(coarse_imp.ess) and coarse_imp.ess >= 2 * len(mean):
            mean, cov = weighted_moments(coarse_imp.draws, coarse_imp.log_weights)
        phases["coarse_importance"], t = time.perf_counter() - t, time.perf_counter()
    mask = np.asarray(problem.obs.mask, bool)
    kept = []  # each draw's displacement residual at the data's points, for the band check

    def log_density(theta):
        out, r = ev.log_density_terms(theta)
        kept.append(r[:, : mask.shape[0]][:, mask])
        return out

    if modes is not None and len(modes) > 1:
        from .start_steps import multimode_importance

        imp, idx = multimode_importance(
            log_density, modes, cov, n_draws, int(n_particles), seed, float(df), max_rounds,
            target, min(target, 2.0 * n_particles),
        )  # fmt: skip
    else:
        imp, idx = adaptive_importance(
            log_density, mean, cov, n_draws, int(n_particles), seed, float(df), max_rounds,
            target, min_ess=min(target, 2.0 * n_particles),
        )  # fmt: skip
    pred = np.concatenate(kept) + np.asarray(problem.obs.displacement, float)[mask]
    width_a, width_b, split = band_split(pred, imp.log_weights)
    # the particles: one draw per equal-weight stratum along the predictions' leading component
    idx = sorted_resample(
        seed, imp.log_weights, int(n_particles), leading_projection(pred, imp.log_weights)
    )
    imp = imp._replace(theta=imp.draws[idx])
    theta, khat, ess, ok, reason = imp.theta, imp.khat, imp.ess, imp.ok, imp.reason
    if not split <= BAND_SPLIT_LIMIT:
        ok = False
        why = (
            f"the two halves of the draws give training bands {width_a * 1e3:.2f} and "
            f"{width_b * 1e3:.2f} mm wide ({100 * split:.0f}% apart > "
            f"{100 * BAND_SPLIT_LIMIT:.0f}%)"
        )
        reason = f"{reason}; {why}" if reason else why
        imp = imp._replace(ok=False, reason=reason)
    phases["importance"] = time.perf_counter() - t
    settings = {
        "method": "fast_posterior",
        "n_starts": n_starts,
        "batch": k,
        "n_screen": n_screen,
        "n_draws": n_draws,
        "df": None if math.isinf(df) else df,
        "lm_iterations": coarse_fit.iterations,
        "n_fit_starts": len(coarse_fit.starts),
        "lm_values": [float(v) for v in coarse_fit.values],
        "substeps": ev.substeps,
        "fit_substeps": coarse,
        "polish_iterations": fit.iterations if fit is not coarse_fit else 0,
        "coarse_importance": None
        if coarse_imp is None
        else {"rounds": coarse_imp.rounds, "ess": coarse_imp.ess, "khat": coarse_imp.khat},
        "program_runs_by_substeps": {str(s): n for s, n in sorted(ev.runs.items())},
        "khat": khat,
        "ess": ess,
        "n_modes": 1 if modes is None else len(modes),
        "importance_rounds": imp.rounds,
        "band_split": split,
        "max_rounds": max_rounds,
        "ok": ok,
        "reason": reason,
        "program_calls": ev.calls,
    }
    return FastPosterior(
        theta, ok, reason, fit, imp, imp.log_density[idx], phases, ev.calls, settings
    )


def resolve_coarse_substeps(ev: BatchEvaluator, coarse) -> int:
    """The substeps per observation of :func:`fast_posterior`'s screen and fit (its
    ``coarse_substeps``, resolved against the evaluator ``ev``)."""
    fine = ev.substeps
    if coarse is None:
        return fine
    if isinstance(coarse, str):
        if coarse != "auto":
            raise ConfigError(
                f"coarse_substeps: expected an integer, 'auto' or None, got {coarse!r}"
            )
        stable = ev.problem.sim.step_info.get("stability_substeps", fine)
        return int(stable) if ev.traced and 1 <= int(stable) < fine else fine
    if not (isinstance(coarse, (int, np.integer)) and coarse >= 1):
        raise ConfigError(f"coarse_substeps: must be an integer >= 1, got {coarse!r}")
    if coarse != fine and not ev.traced:
        raise ConfigError(
            "coarse_substeps: this rollout program runs only the simulator's own step "
            f"({fine} substeps; the Pallas kernel with TREEINFER_PALLAS_TRACED_SUBSTEPS=off)"
        )
    return int(coarse)


class ParticleState(NamedTuple):
    """The minimal sampler state of a posterior that no sampler produced (the run layer reads
    ``position`` and ``logdensity``)."""

    position: np.ndarray
    logdensity: np.ndarray


def importance_run_result(theta, logp, run_settings: dict, importance, elapsed_s: float):
    """The :class:`treeinfer.inference.samplers.RunResult` of an importance posterior that no
    sampler refined: one state (iteration 0) of ``theta [P, D]`` and ``logp [P]``, ``stop_reason``
    naming the weights' Pareto k_hat and effective sample size (``importance.khat``, ``.ess``).
    Shared by the paper's model (:func:`posterior_from_fast`) and the other models' start
    (:mod:`treeinfer.inference.start_pipeline`)."""
    from .samplers import RunResult

    return RunResult(
        final_positions=theta,
        final_state=ParticleState(theta, logp),
        trace_positions=theta[None],
        trace_logdensity=logp[None],
        trace_iterations=np.zeros(1, np.int64),
        diagnostics={},
        settings=run_settings,
        elapsed_s=elapsed_s,
        stop_reason=f"importance sampling (Pareto k_hat {importance.khat:.2f}, "
        f"effective sample size {importance.ess:.0f})",
    )


def posterior_from_fast(problem, result: FastPosterior, seed: int = 0):
    """A :class:`treeinfer.inference.problem.Posterior` of ``result`` (zero sampler iterations), for
    the run layer (``--init importance --iterations 0``): ``run`` is a
    :class:`treeinfer.inference.samplers.RunResult` whose trace is the one state (iteration 0),
    ``stop_reason`` says that importance sampling produced it, and ``settings`` record the
    fit and the weights' diagnostics (``khat``, ``ess``)."""
    from ..model.likelihood import gains_from_theta
    from .problem import Posterior

    theta = np.asarray(result.theta, np.float32)
    logp = np.asarray(result.log_density, np.float32)
    run_settings = {
        **result.settings,
        "n_iterations": 0,
        "n_iterations_done": 0,
        "start_iteration": 0,
        "seed": seed,
    }
    run = importance_run_result(
        theta, logp, run_settings, result.importance, float(sum(result.phases.values()))
    )
    kp, kd = gains_from_theta(theta, problem.sim.n_joints)
    settings = {
        "problem": problem.settings,
        "sampler": "importance",
        "sampler_options": {k: result.settings[k] for k in ("n_starts", "n_draws", "df")},
        "n_particles": len(theta),
        "n_iterations": 0,
        "seed": int(seed),
        "run": run_settings,
    }
    return Posterior(theta, np.asarray(kp), np.asarray(kd), logp, problem.labels, run, settings)


def importance_for_run(problem, n_particles: int, seed: int = 0, log=lambda msg: None, **options):
    """The run layer's ``--init importance``: :func:`fast_posterior`, one status line to ``log``,
    and ``(posterior, theta0)``: ``posterior`` (:func:`posterior_from_fast`) when the weights
    pass their check, so no sampler needs to run, else None; ``theta0`` [P, D] the particles
    (the sampler's start when ``posterior`` is None). ``options`` go to :func:`fast_posterior`.
    """
    if not (problem.noise is None or problem.noise.black_box):
        # a generative likelihood's posterior is sharp (2 mm noise on ~900 samples): the coarse
        # step moves its mode by several posterior widths (importance rounds at the coarse step
        # then gave an effective sample size of 2-3 of 832 on the standard problem), so the
        # coarse fit is polished at the accurate step and only accurate rounds are drawn
        # one more round than the Boltzmann path: Pareto k_hat 0.74 after three rounds with an
        # effective sample size of 225 sent the standard problem to the sampler (issue 27)
        options = {
            "coarse_rounds": 0,
            "polish_iterations": GENERATIVE_POLISH,
            "max_rounds": 4,
            **options,
        }
    res = fast_posterior(problem, n_particles, seed=seed, **options)
    imp = res.importance
    verdict = (
        "used as the posterior (no sampler iterations)"
        if res.ok
        else f"not trusted ({res.reason}): the sampler runs from these particles"
    )
    log(
        f"importance posterior: MAP from {res.settings['n_fit_starts']} starts in "
        f"{res.settings['lm_iterations']} LM iterations"
        + (
            f" (+{res.settings['polish_iterations']} at the accurate step)"
            if res.settings["polish_iterations"]
            else ""
        )
        + f", {len(imp.draws)} draws in {imp.rounds} "
        f"round{'s' if imp.rounds > 1 else ''}, Pareto k_hat "
        f"{imp.khat:.2f}, effective sample size {imp.ess:.0f}: {verdict}"
    )
    return (posterior_from_fast(problem, res, seed) if res.ok else None), res.theta
