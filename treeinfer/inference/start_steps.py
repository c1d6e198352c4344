"""The steps of the start pipeline that :mod:`treeinfer.inference.fast` runs itself: the
global screen, the generalised Gauss-Newton curvature of the MAP fit's LM step, and the local
modes of the multi-start fit with their importance sampling. Moved here from
:mod:`treeinfer.inference.start_pipeline` (which re-exports them and builds on fast_posterior) so
that fast_posterior no longer imports the module that imports it (an import cycle); the method is
described there.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["distinct_modes", "ggn_terms", "multimode_importance", "noise_guess", "screen"]


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
            # the gains move with the step too: the force-noise bias correction depends on them
            # directly (treeinfer.model.force_noise_bias), not only through the residual
            t = jnp.concatenate([th[:g] + z[:g], z[g:]])
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

    ev._ggn = ev._program(run) if hasattr(ev, "_program") else jax.jit(run)
    return ev._ggn


def _psd(h: np.ndarray) -> np.ndarray:
    """Each ``[D, D]`` of ``h [S, D, D]`` projected onto the positive semi-definite cone (a
    Student-t residual or the NN prior can make the curvature indefinite; the LM step and the
    proposal need a PSD one)."""
    h = 0.5 * (h + np.swapaxes(h, -1, -2))
    w, v = np.linalg.eigh(h)
    return np.einsum("sde,se,sfe->sdf", v, np.maximum(w, 0.0), v)


def finite_psd(h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(_psd(h) with non-finite matrices zeroed, finite [S])``. A point whose curvature is not
    finite (an overflowing AR(1) density far from the data, a blown-up rollout) is dropped by
    the caller; it is zeroed first because one NaN makes the batched eigen-decomposition fail
    for EVERY point ("Eigenvalues did not converge": on noise-free data with
    ``--likelihood ar1`` the whole start pipeline fell back to uniform starts)."""
    h = np.array(h, float)
    finite = np.isfinite(h).all((-2, -1))
    h[~finite] = 0.0
    return _psd(h), finite


def ggn_terms(ev, theta, h: float, substeps: int | None = None, pad_to: int | None = None):
    """:func:`treeinfer.inference.fast_fit._lm_terms` for a generative likelihood: ``(value [S],
    grad [S, D], curvature [S, D, D], gram, r2)`` of ``-log p`` at ``theta [S, D]`` from one
    batch of the ``S (2g + 1)`` central-difference points in the gains (g = 2R; the noise
    columns need no rollout). ``gram`` and ``r2`` (the Boltzmann cone's terms) are zeros.
    ``pad_to``: the curvature program runs on this many rows (the last repeated), so that a fit
    whose active starts shrink reuses one compiled program."""
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
    args = (r[:, 0], jac, theta)
    if pad_to is not None and pad_to > s:
        args = tuple(np.concatenate([a, np.repeat(a[-1:], pad_to - s, 0)]) for a in args)
    value, grad, curv = (
        np.asarray(x, float)[:s] for x in _ggn_program(ev)(*(jnp.asarray(a, dt) for a in args))
    )
    curv, finite = finite_psd(curv)
    good = ok & np.isfinite(value) & np.isfinite(grad).all(1) & finite
    value = np.where(good, value, np.inf)
    grad[~good], curv[~good] = 0.0, 0.0
    return value, grad, curv, np.zeros((s, 1, d, d)), np.zeros((s, 1))


# local modes of the multi-start fit kept for importance sampling: within this many nats of the
# best, at least MODE_SEPARATION of the best's proposal standard deviations apart in some
# coordinate, at most MAX_MODES. Half a standard deviation, not two: the coarse fit's finals
# along a curved ridge lie within 2 sd of each other in the best's Laplace covariance, so only
# the best was polished, and it slid to one end of the ridge (chain2 of
# experiments/default_calibration.py, seed 1: from the child's damping 0.48 to the box edge
# 0.05, finals near the truth 2.6 nats lower never polished; the one-mode importance weights
# were "trusted", k_hat -0.01, with Kp intervals 4x narrower than the Cramer-Rao bound at the
# truth). Three modes along the ridge make a mixture proposal that covers it (the same seed:
# k_hat 0.37, the child's damping 0.02-0.73); on the standard problem the cost is the same.
MODE_GAP = 10.0
MODE_SEPARATION = 0.5
MAX_MODES = 3


def distinct_modes(fit, cov) -> np.ndarray:
    """``[M, D]`` the distinct local optima among ``fit.finals`` (a
    :class:`treeinfer.inference.mapfit.MapFit` of several starts), best first: finals within
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


def _mixture_weights(runs, order, n_particles, seed, min_ess):
    """Every draw of every run in call order ``order`` [(run, round)], weighted against the
    deterministic mixture of ALL the runs' proposals (the balance heuristic of multiple
    importance sampling; Veach & Guibas 1995, Owen & Zhou 2000):
    ``q_mix(x) = sum_(m, r) n_(m, r) q_(m, r)(x) / N``. Returns ``(draws, log_p, run_of [M],
    importance_resample's (index, log_weights, khat, ess, ok, reason))``.

    Why not each run's own weights pooled by its evidence share (as before): where two runs'
    proposals overlap (modes of the multi-start fit on one curved ridge: chain2 of
    experiments/default_calibration.py, the child's damping from 0.03 to 0.7) the shares
    count the overlap twice and the run that drifted onto another had to be dropped, and with
    it the end of the ridge that only it covered (seed 0: the truths Kp 37.7 / 98.7 lay outside
    the intervals, 38.1-54.7 / 89.1-98.3; with every run kept and these weights, inside). The
    mixture weights are unbiased whatever the overlap."""
    from .importance import _draw_log_density, importance_resample

    blocks, sizes = {}, []
    for j, r in enumerate(runs):
        ends = np.cumsum(r.sizes)
        for k, (a, b) in enumerate(zip(ends - r.sizes, ends)):
            blocks[(j, k + 1)] = (r.draws[a:b], r.log_p[a:b])
        sizes += [(j, k) for k in range(len(r.sizes))]
    draws = np.concatenate([blocks[o][0] for o in order])
    log_p = np.concatenate([blocks[o][1] for o in order])
    run_of = np.concatenate([np.full(len(blocks[o][0]), o[0]) for o in order])
    terms = []
    for j, k in sizes:
        m, c, df = runs[j].proposals[k]
        terms.append(np.log(runs[j].sizes[k]) + _draw_log_density(None, m, c, 0, df, draws)[1])
    log_q = np.logaddexp.reduce(np.stack(terms), axis=0) - np.log(len(draws))
    return (
        draws,
        log_p,
        run_of,
        importance_resample(draws, log_p, log_q, n_particles, seed, min_ess),
    )


def multimode_importance(
    log_density, modes, cov, n_draws, n_particles, seed, df, max_rounds, target, min_ess
):
    """:func:`treeinfer.inference.importance.adaptive_importance` around each of ``modes [M, D]``,
    pooled: every draw of every mode's rounds is weighted against the deterministic mixture of
    all the proposals used (:func:`_mixture_weights`), Pareto-smoothed once. Unbiased whether
    the modes' proposals overlap or not. Returns ``(ImportancePosterior, index [n_particles])``
    as ``adaptive_importance``, the draws in the order ``log_density`` was called; ``khat``,
    ``ess`` and ``ok`` are the pooled weights' (``ok``: k_hat within
    :data:`treeinfer.inference.importance.KHAT_LIMIT` and an effective sample size of
    ``min_ess``).

    The rounds are shared out (:class:`treeinfer.inference.importance.PopulationRounds`): one
    round at every mode, then, while the pool's k_hat is above the limit or its effective
    sample size below ``target``, one more round (at most ``max_rounds`` per mode) at each mode
    that carries more than 1% of the weight with a k_hat of its own above the limit, and at the
    mode whose draws limit the pool's effective sample size most (the largest sum of squared
    weights). Before, every mode ran its rounds until its own effective sample size reached
    ``target``: 7 rounds of 960 draws on the standard problem (pooled ESS 561 for a target of
    256), the largest single cost of the run."""
    from .importance import KHAT_LIMIT, PopulationRounds

    runs = [
        PopulationRounds(log_density, m, cov, n_draws, n_particles, seed + 101 * j, df, min_ess)
        for j, m in enumerate(np.asarray(modes, float))
    ]
    order = []  # (run, round) in the order log_density ran them
    for j, r in enumerate(runs):
        r.step()
        order.append((j, r.rounds))
    while True:
        _, _, run_of, (_, lw, khat, ess, _, _) = _mixture_weights(
            runs, order, n_particles, seed, min_ess
        )
        w = np.exp(lw)
        share = np.array([w[run_of == j].sum() for j in range(len(runs))])
        w_sq = np.array([np.sum(w[run_of == j] ** 2) for j in range(len(runs))])
        # another round where a run that carries weight has an untrustworthy tail of its own,
        # and at the run whose draws limit the pool's effective sample size most
        more = set()
        if not khat <= KHAT_LIMIT or ess < target:
            more = {j for j, r in enumerate(runs) if share[j] > 0.01 and r.khat > KHAT_LIMIT}
            more.add(int(np.argmax(w_sq)))
        more = [j for j in sorted(more) if runs[j].rounds < max_rounds and runs[j].adapt()]
        if not more:
            break
        for j in more:
            runs[j].step()
            order.append((j, runs[j].rounds))
    draws, log_p, _, (idx, lw, khat, ess, ok, reason) = _mixture_weights(
        runs, order, n_particles, seed, min_ess
    )
    best = runs[int(np.argmax(share))].result()[0]
    imp = best._replace(
        theta=draws[idx],
        draws=draws,
        log_weights=lw,
        log_density=log_p,
        khat=khat,
        ess=ess,
        ok=ok,
        reason=reason,
        rounds=sum(r.rounds for r in runs),
        raw_log_weights=None,
    )
    return imp, idx
