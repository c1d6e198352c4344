"""The one start pipeline (``--init auto``, the default): a posterior from a global screen, a
multi-start MAP fit and importance sampling, for every likelihood and prior.

    ready, theta0 = auto_start(problem, n_particles=64, seed=0)
    # ready: a Posterior when the importance weights pass their check (no sampler needed);
    # theta0 [P, D]: the particles the sampler starts from otherwise

The paper's dynamic model (theta = [log Kp, log Kd] and the likelihood's noise columns) goes
through :func:`treeinfer.fast_posterior.fast_posterior`: one compiled rollout program for the
gains, the likelihood's noise density evaluated on its residuals by a small program of its own
(:attr:`treeinfer.likelihood.LikelihoodTerms.residual_loglik`, the very function the problem's
likelihood uses), so noise columns (``sigma_x``, ...) cost no rollout. For the generative
likelihoods the Levenberg–Marquardt step of the MAP fit uses the generalised Gauss–Newton
curvature (:func:`ggn_terms`): the rollout is linearised by central differences, ``e(theta +
a) ~ e + J a``, and the noise density of the linearised residual is differentiated exactly in
``a`` and the noise columns (autodiff through the noise density only: a few microseconds);
the prior (smoothed box, the NN inequality prior, the noise priors of
:mod:`treeinfer.noise`) enters through its own autodiff derivatives. The importance weights
are then ``p / q`` with the problem's exact log-density, prior included.

With ``--noise-force`` the likelihood's force Jacobian is taken at a reference point, the MAP
of the errors-in-variables model (:func:`treeinfer.force_noise.reference_theta` finds it with
two compiled LM programs of its own, 30-200 s on a 2-core CPU). Here
(:func:`force_noise_reference`) the same two steps run on the one rollout program: the MAP of
the Gaussian model without the force term, then the MAP of the model whose force Jacobian is
taken there (sigma_x inferred jointly, where reference_theta fixes it at the data's estimate);
its gains are the reference.

Any other model (static, stiffness only, a tie, per-recording pulls) goes through the problem's
own jitted log-density: :func:`treeinfer.laplace.problem_laplace` for the MAP and the
covariance, then the same adaptive importance sampling (:func:`model_importance`).
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from .errors import ConfigError

__all__ = ["auto_start", "force_noise_reference", "ggn_terms", "model_importance", "noise_guess"]

# LM iterations of each force-noise reference step (the coarse-step fit of fast_posterior uses 15)
REFERENCE_LM_ITERATIONS = 15


def noise_guess(problem, r: np.ndarray, lower, upper) -> np.ndarray:
    """``[N, E]`` starting values of the noise columns for rollout residuals ``r [N, 2B, T]``
    (simulated minus recorded): each ``sigma`` column at the log of the masked displacement
    residual's root mean square (the Gaussian model's conditional MAP without prior), ``rho``
    at the middle of its box. The screen ranks gains by the density at these values."""
    labels = problem.noise.extra_labels
    b = np.shape(problem.obs.force)[0]
    mask = np.asarray(problem.obs.mask, bool)
    dx = r[:, :b]
    rms = np.sqrt(np.sum(np.where(mask, dx, 0.0) ** 2, (1, 2)) / max(mask.sum(), 1))
    rms = np.maximum(rms, 1e-12)
    c = 2 * problem.sim.n_joints
    out = np.empty((len(r), len(labels)))
    for j, lab in enumerate(labels):
        if lab == "rho":
            out[:, j] = 0.5 * (lower[c + j] + upper[c + j])
        else:
            out[:, j] = np.log(rms)
    return out


def screen(ev, pts, substeps):
    """``(log p [N], pts [N, D])`` of Latin-hypercube points ``pts``: the noise columns set by
    :func:`noise_guess` at each point's residuals (generative likelihoods; the Boltzmann loss has
    none), so the gains are ranked at a sensible noise level rather than a random one."""
    if ev.boltzmann or ev.problem.dim == ev.n_gains:
        return ev.log_density(pts, substeps), pts
    r, ok, _ = ev.evaluate(pts, substeps)
    pts = np.array(pts, float)
    p = ev.problem
    pts[:, ev.n_gains :] = noise_guess(p, r, np.asarray(p.lower), np.asarray(p.upper))
    out = ev.log_likelihood(r, pts) + ev.log_prior(pts)
    return np.where(ok & np.isfinite(out), out, -np.inf), pts


def _ggn_program(ev):
    """The jitted ``(e [S, G, T], J [S, G, T, g], theta [S, D]) -> (value [S], grad [S, D],
    curvature [S, D, D])`` of ``-log p`` (module docstring), kept on the evaluator."""
    prog = getattr(ev, "_ggn", None)
    if prog is not None:
        return prog
    terms, log_prior = ev.problem.noise, ev.problem.log_prior
    g, b = ev.n_gains, ev._rows

    def one(e0, jac, th):
        def phi(z):  # z = [a (gains step), noise columns]
            e = e0 + jac @ z[:g]
            t = jnp.concatenate([th[:g], z[g:]])
            return -terms.residual_loglik(-e[None, :b], -e[None, b:], t[None])[0]

        z0 = jnp.concatenate([jnp.zeros(g, th.dtype), th[g:]])
        return phi(z0), jax.grad(phi)(z0), jax.hessian(phi)(z0)

    def prior(th):
        def neg(t):
            return -log_prior(t[None])[0]

        return neg(th), jax.grad(neg)(th), jax.hessian(neg)(th)

    def run(e0, jac, theta):
        f, gr, h = jax.vmap(one)(e0, jac, theta)
        fp, gp, hp = jax.vmap(prior)(theta)
        return f + fp, gr + gp, h + hp

    ev._ggn = jax.jit(run)
    return ev._ggn


def _psd(h: np.ndarray) -> np.ndarray:
    """Each ``[D, D]`` of ``h [S, D, D]`` projected onto the positive semi-definite cone (a
    Student-t residual or the NN prior can make the curvature indefinite; the LM step and the
    proposal need a PSD one)."""
    h = 0.5 * (h + np.swapaxes(h, -1, -2))
    w, v = np.linalg.eigh(h)
    return np.einsum("sde,se,sfe->sdf", v, np.maximum(w, 0.0), v)


def ggn_terms(ev, theta, h: float, substeps: int | None = None):
    """:func:`treeinfer.fast_posterior._lm_terms` for a generative likelihood: ``(value [S],
    grad [S, D], curvature [S, D, D], gram, r2)`` of ``-log p`` at ``theta [S, D]`` from one
    batch of the ``S (2g + 1)`` central-difference points in the gains (g = 2R; the noise
    columns need no rollout). ``gram`` and ``r2`` (the Boltzmann cone's terms) are zeros."""
    s, d = theta.shape
    g = ev.n_gains
    step = np.zeros((2 * g + 1, d))
    step[1 : g + 1, :g] = h * np.eye(g)
    step[g + 1 :, :g] = -h * np.eye(g)
    pts = theta[:, None] + step[None]
    r, ok, _ = ev.evaluate(pts.reshape(-1, d), substeps)
    r = r.reshape(s, 2 * g + 1, *r.shape[1:])
    ok = ok.reshape(s, -1).all(1)
    jac = np.moveaxis((r[:, 1 : g + 1] - r[:, g + 1 :]) / (2 * h), 1, -1)  # [S, G, T, g]
    dt = ev._dtype
    value, grad, curv = (
        np.asarray(x, float)
        for x in _ggn_program(ev)(
            jnp.asarray(r[:, 0], dt), jnp.asarray(jac, dt), jnp.asarray(theta, dt)
        )
    )
    curv = _psd(curv)
    good = ok & np.isfinite(value) & np.isfinite(grad).all(1) & np.isfinite(curv).all((1, 2))
    value = np.where(good, value, np.inf)
    grad[~good], curv[~good] = 0.0, 0.0
    return value, grad, curv, np.zeros((s, 1, d, d)), np.zeros((s, 1))


def force_noise_reference(
    make: Callable, problem0, n_starts: int, seed: int, programs=None, log=lambda m: None
):
    """``(theta_ref [2R], finals [S, D])``: the force-noise term's reference (module docstring)
    and the final points of its second fit (the start pipeline's LM starts there).

    ``make(reference)`` builds the problem whose force Jacobian is taken at ``reference``
    (``[2R]`` log gains); ``problem0`` is the Gaussian problem without the force term. Both
    steps are :func:`treeinfer.fast_posterior.fast_posterior`'s screen and LM on one rollout
    program (the evaluators share it through ``programs``)."""
    from .fast_posterior import BatchEvaluator, default_chunk, fit_map_batched, latin_hypercube
    from .fast_posterior import resolve_coarse_substeps as coarse_of

    d, g = problem0.dim, 2 * problem0.sim.n_joints
    k = n_starts * (2 * g + 1)
    ev0 = BatchEvaluator(problem0, default_chunk(k, 8 * k), programs)
    coarse = coarse_of(ev0, "auto")
    lower, upper = np.asarray(problem0.lower, float), np.asarray(problem0.upper, float)
    pts = latin_hypercube(4 * k, lower, upper, seed)
    lp, pts = screen(ev0, pts, coarse)
    starts = pts[np.argsort(np.where(np.isfinite(lp), -lp, np.inf))[:n_starts]]
    first = fit_map_batched(ev0, starts, REFERENCE_LM_ITERATIONS, substeps=coarse)
    ref = np.clip(first.theta[:g], lower[:g], upper[:g])
    problem1 = make(ref)
    ev1 = BatchEvaluator(problem1, ev0.chunk, programs)
    if problem1.dim != d:
        raise ConfigError("force_noise_reference: the two problems have other columns")
    finals = first.finals[np.isfinite(first.values)]
    second = fit_map_batched(ev1, finals, REFERENCE_LM_ITERATIONS, substeps=coarse)
    ref = np.clip(second.theta[:g], lower[:g], upper[:g])
    log(
        "force-noise reference: MAP without the force term in "
        f"{first.iterations} LM iterations, then with it in {second.iterations}"
    )
    order = np.argsort(second.values)
    return ref, second.finals[order][np.isfinite(second.values[order])]


def model_importance(problem, n_particles: int, seed: int = 0, n_draws: int | None = None):
    """:class:`treeinfer.fast_posterior.FastPosterior`-like ``(theta [P, D], ok, reason,
    importance, lap)`` for a problem the rollout program does not run (static model, stiffness
    only, a tie, per-recording pulls): the MAP and covariance of its own log-density
    (:func:`treeinfer.laplace.problem_laplace`), then Student-t adaptive importance sampling
    with weights from ``problem.log_density`` (exact)."""
    from .fast_posterior import DEFAULT_DF
    from .importance import adaptive_importance
    from .laplace import problem_laplace

    lap = problem_laplace(problem, seed=seed)
    fn = jax.jit(problem.log_density)
    m = max(8 * problem.dim * 8, 4 * int(n_particles)) if n_draws is None else int(n_draws)
    dtype = jnp.asarray(0.0).dtype

    def log_density(x):
        return np.asarray(fn(jnp.asarray(x, dtype)), float)

    imp, idx = adaptive_importance(
        log_density, lap.theta, lap.cov, m, int(n_particles), seed, DEFAULT_DF, 3,
        4.0 * n_particles, min_ess=2.0 * n_particles,
    )  # fmt: skip
    return imp._replace(theta=imp.draws[idx]), idx, lap


def auto_start(problem, n_particles: int, seed: int = 0, log=lambda m: None, **options):
    """``(posterior or None, theta0 [P, D])`` of the start pipeline (module docstring):
    ``posterior`` (:func:`treeinfer.fast_posterior.posterior_from_fast`) when the importance
    weights pass their check, else None and the sampler starts from ``theta0``. ``options`` go
    to :func:`treeinfer.fast_posterior.fast_posterior` (the paper's dynamic model)."""
    from .fast_posterior import importance_for_run

    if problem.model is None:
        if problem.start_hint is not None and "starts" not in options:
            # the MAP fit is done (the force-noise reference's): a few LM steps from its finals
            options = {"starts": problem.start_hint, "max_iterations": 5, **options}
        return importance_for_run(problem, n_particles, seed, log, **options)
    return _model_start(problem, n_particles, seed, log)


def _model_start(problem, n_particles: int, seed: int, log):
    """:func:`auto_start` for a model the rollout program does not run."""
    from .fast_posterior import ParticleState
    from .inference import Posterior
    from .samplers import RunResult

    imp, idx, lap = model_importance(problem, n_particles, seed)
    verdict = (
        "used as the posterior (no sampler iterations)"
        if imp.ok
        else f"not trusted ({imp.reason}): the sampler runs from these particles"
    )
    log(
        f"importance posterior: MAP of the log-density ({lap.n_evals} evaluations), "
        f"{len(imp.draws)} draws in {imp.rounds} rounds, Pareto k_hat {imp.khat:.2f}, "
        f"effective sample size {imp.ess:.0f}: {verdict}"
    )
    theta = np.asarray(imp.theta, np.float32)
    if not imp.ok:
        return None, theta
    logp = np.asarray(imp.log_density[idx], np.float32)
    run_settings = {
        "method": "model_importance",
        "khat": imp.khat,
        "ess": imp.ess,
        "n_draws": len(imp.draws),
        "lm_iterations": 0,
        "importance_rounds": imp.rounds,
        "n_iterations": 0,
        "n_iterations_done": 0,
        "start_iteration": 0,
        "seed": seed,
    }
    run = RunResult(
        final_positions=theta,
        final_state=ParticleState(theta, logp),
        trace_positions=theta[None],
        trace_logdensity=logp[None],
        trace_iterations=np.zeros(1, np.int64),
        diagnostics={},
        settings=run_settings,
        elapsed_s=0.0,
        stop_reason=f"importance sampling (Pareto k_hat {imp.khat:.2f}, effective sample size "
        f"{imp.ess:.0f})",
    )
    kp, kd = problem.model.layout.gains(theta)
    settings = {
        "problem": problem.settings,
        "sampler": "importance",
        "sampler_options": {"n_draws": len(imp.draws)},
        "n_particles": len(theta),
        "n_iterations": 0,
        "seed": int(seed),
        "run": run_settings,
    }
    return Posterior(
        theta, np.asarray(kp), np.asarray(kd), logp, problem.labels, run, settings
    ), theta


# local modes of the multi-start fit kept for importance sampling: within this many nats of the
# best, at least MODE_SEPARATION of the best's proposal standard deviations apart in some
# coordinate, at most MAX_MODES
MODE_GAP = 10.0
MODE_SEPARATION = 2.0
MAX_MODES = 3


def distinct_modes(fit, cov) -> np.ndarray:
    """``[M, D]`` the distinct local optima among ``fit.finals`` (a
    :class:`treeinfer.mapfit.MapFit` of several starts), best first: finals within
    :data:`MODE_GAP` nats of the best ``-log p``, a new mode when it lies more than
    :data:`MODE_SEPARATION` standard deviations of ``cov`` (the best's proposal) from every
    kept one in some coordinate. On the standard problem with the force-noise term the
    posterior has two modes 0.5 nats apart (the child's and the parent's stiffness trade off:
    Kp 30 / 62 and 45 / 53 N m/rad); the best alone left the true values outside every
    interval."""
    finals, values = np.asarray(fit.finals, float), np.asarray(fit.values, float)
    sd = np.sqrt(np.maximum(np.diag(np.asarray(cov, float)), 1e-12))
    order = [i for i in np.argsort(values) if np.isfinite(values[i])]
    if not order:
        return np.asarray(fit.theta, float)[None]
    best = values[order[0]]
    kept = []
    for i in order:
        if values[i] > best + MODE_GAP or len(kept) >= MAX_MODES:
            break
        if all(np.max(np.abs(finals[i] - finals[j]) / sd) > MODE_SEPARATION for j in kept):
            kept.append(i)
    return finals[kept]


def multimode_importance(
    log_density, modes, cov, n_draws, n_particles, seed, df, max_rounds, target, min_ess
):
    """:func:`treeinfer.importance.adaptive_importance` around each of ``modes [M, D]``, pooled:
    each mode's draws keep their (Pareto-smoothed, normalised) weights, scaled by that mode's
    share of the evidence, ``Z_m = mean(p / q_m)`` over its draws (raw weights). Exact for
    modes whose proposals do not overlap; where two proposals cover the same mode each run
    estimates the whole posterior and the pool averages two estimates of it. Returns
    ``(ImportancePosterior, index [n_particles])`` as ``adaptive_importance``; ``khat`` is the
    largest of the modes'; ``ok`` needs every mode with a share above 1% to have a k_hat
    within :data:`treeinfer.importance.KHAT_LIMIT` and the pool an effective sample size of
    ``min_ess``."""
    from .importance import KHAT_LIMIT, adaptive_importance, systematic_resample

    runs = [
        adaptive_importance(
            log_density, m, cov, n_draws, n_particles, seed + 101 * j, df, max_rounds, target,
            min_ess=min_ess,
        )[0]
        for j, m in enumerate(np.asarray(modes, float))
    ]  # fmt: skip
    log_z = np.array(
        [np.logaddexp.reduce(r.raw_log_weights) - np.log(len(r.raw_log_weights)) for r in runs]
    )
    share = np.exp(log_z - np.logaddexp.reduce(log_z))
    lw = np.concatenate([r.log_weights + np.log(max(s, 1e-300)) for r, s in zip(runs, share)])
    lw = lw - np.logaddexp.reduce(lw)
    w = np.exp(lw)
    ess = float(1.0 / np.sum(w**2))
    big = [r for r, s in zip(runs, share) if s > 0.01]
    khat = float(max(r.khat for r in big))
    # each mode's tail (k_hat) must be trustworthy; the effective sample size is the pool's (a
    # mode with a 30% share needs only its share of it)
    reasons = [
        f"Pareto k_hat {r.khat:.2f} > {KHAT_LIMIT} at a mode" for r in big if r.khat > KHAT_LIMIT
    ]
    if ess < min_ess:
        reasons.append(f"effective sample size {ess:.0f} < {min_ess:.0f}")
    draws = np.concatenate([r.draws for r in runs])
    idx = systematic_resample(np.random.default_rng(seed), lw, n_particles)
    best = runs[int(np.argmax(share))]
    imp = best._replace(
        theta=draws[idx],
        draws=draws,
        log_weights=lw,
        log_density=np.concatenate([r.log_density for r in runs]),
        khat=khat,
        ess=ess,
        ok=not reasons,
        reason="; ".join(dict.fromkeys(reasons)),
        rounds=sum(r.rounds for r in runs),
        raw_log_weights=None,
    )
    return imp, idx
