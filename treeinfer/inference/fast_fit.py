"""The MAP step of :func:`treeinfer.inference.fast.fast_posterior` on the host:
:func:`latin_hypercube` screening points and :func:`fit_map_batched`, Levenberg–Marquardt from
several starts at once with central-difference Jacobians, each iteration one run of the
:class:`~treeinfer.inference.fast_evaluator.BatchEvaluator` program.

Separate from :mod:`treeinfer.inference.fast` (issue 26): the fit is one step of the pipeline,
also run on its own by the start pipeline (the force-noise reference's two fits).
:mod:`treeinfer.inference.fast` re-exports every name (they lived there before the split).
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from .fast_evaluator import BatchEvaluator

__all__ = ["fit_map_batched", "latin_hypercube"]

# The objective is -log p in nats, whose size grows with the number of data points (4,220 on
# the standard problem: 3 pulls of 3 s at 100 Hz), so a purely relative stopping rule stops far
# from the mode there: ``tolerance * (1 + |f|)`` with the default 1e-4 let a start "converge" on
# a step that gained 0.42 nats, and the whole fit stop once two starts were within
# ``sqrt(1e-4) (1 + |f|)`` = 42 nats of the best. On a curved ridge (a parent's and a child's
# stiffness trading off) the starts then stopped on 8 different points of the ridge, 1.3 nats
# below its top where the truth was, and the posterior built there missed it by 5-8 sd (SBC
# data set 90 of experiments/results/sbc_default_s15_main/). Both rules are capped in nats:
STEP_NATS = 1e-3  # a start has converged when an accepted step gains less than this
AGREE_NATS = 0.5  # the fit stops when two converged starts are this close to the best


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


# a running start this close (log units, every gain) to another start at least as good has joined
# its basin: it stops (not counted as converged), so that many starts cost what their distinct
# basins cost
MERGE_TOL = 0.02


def _merged(theta, f, done, n_gains: int) -> np.ndarray:
    """``[S]`` running starts within :data:`MERGE_TOL` of another start with a lower (or equal,
    then earlier) objective."""
    g = theta[:, :n_gains]
    out = np.zeros(len(theta), bool)
    for i in np.flatnonzero(~done & np.isfinite(f)):
        near = np.max(np.abs(g - g[i]), axis=1) < MERGE_TOL
        better = (f < f[i]) | ((f == f[i]) & (np.arange(len(f)) < i))
        out[i] = bool(np.any(near & better & np.isfinite(f)))
    return out


def _active_terms(terms, ev, theta, rows, h, substeps, n):
    """``terms`` at ``theta[rows]`` only, scattered into ``n`` rows (objective inf elsewhere)."""
    d = theta.shape[1]
    f, g, hs = np.full(n, np.inf), np.zeros((n, d)), np.zeros((n, d, d))
    if len(rows) == 0:
        return f, g, hs, np.zeros((n, 1, d, d)), np.zeros((n, 1))
    kw = {} if ev.boltzmann else {"pad_to": n}
    sub = terms(ev, theta[rows], h, substeps, **kw)
    gram, r2 = np.zeros((n, *sub[3].shape[1:])), np.zeros((n, *sub[4].shape[1:]))
    for a, b in zip((f, g, hs, gram, r2), sub):
        a[rows] = b
    return f, g, hs, gram, r2


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
    |f|)`` or :data:`STEP_NATS`, whichever is smaller; the fit stops when every start has
    stopped, or when two starts have stopped within ``sqrt(tolerance) (1 + |f|)`` or
    :data:`AGREE_NATS` (the smaller) of the lowest objective found. Returns a
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
    n = len(theta)
    f, g, hs, gram, r2 = _active_terms(terms, ev, theta, np.arange(n), h, substeps, n)
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
        # only the starts still running are simulated (a converged or merged one costs nothing)
        ft, gt, ht, gram_t, r2_t = _active_terms(
            terms, ev, trial, np.flatnonzero(~done), h, substeps, n
        )
        accept = ~done & np.isfinite(ft) & (ft < f)
        flat = accept & ((f - ft) < np.minimum(tolerance * (1.0 + np.abs(f)), STEP_NATS))
        for a, b in ((theta, trial), (f, ft), (g, gt), (hs, ht), (gram, gram_t), (r2, r2_t)):
            a[accept] = b[accept]
        lam = np.where(accept, np.maximum(lam / 3.0, 1e-9), lam * 4.0)
        newly = ~done & (flat | (np.max(np.abs(steps), 1) < 1e-6))
        converged |= newly
        done |= newly | (lam > 1e10) | _merged(theta, f, done, ev.n_gains)
        if done.all():
            break
        low = np.min(f)
        agree = min(math.sqrt(tolerance) * (1 + abs(low)), AGREE_NATS)
        at_low = converged & (f - low <= agree)
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
